//! Asset uploads over HTTP (see [`ingest`] for what happens to the files).
//!
//! - `POST /api/assets/{name}`: a new asset from a `multipart/form-data` body whose file
//!   parts' names give the format (one `.glb`; one `.gltf` with its `.bin`/image files; one
//!   `.bvh`; one `.skel` with an optional `.skin` and `.anim` clips), or from a raw body of one
//!   file: `Content-Type: model/gltf-binary`, or any type with `?format=glb|gltf|bvh|skel`.
//!   → `200 {"result": [AssetInfo, …]}` (several for a multi-skin glTF).
//! - `POST /api/assets/{name}/clips`: `.anim` clips (multipart) added to an uploaded `.skel`
//!   asset. → `200 {"result": AssetInfo}`.
//!
//! Bodies are limited to `Config::max_upload_bytes` (413 `too_large`). Errors are typed:
//! `import_failed` (422) with the importer's message, `invalid_value` (400) for a bad name or
//! body, `conflict` (409) for a name in use.

use super::rest::AppError;
use crate::auth::Caller;
mod ingest;

use crate::import::files::FileSet;
use crate::state::AppState;
use axum::Json;
use axum::body::Bytes;
use axum::extract::{FromRequest, Multipart, Path, Request, State};
use axum::http::{StatusCode, header};
use posecast_proto::msg::{ErrorCode, ProtocolError};
use serde_json::{Value, json};
use std::sync::Arc;

fn too_large(state: &AppState) -> ProtocolError {
    ProtocolError::new(
        ErrorCode::TooLarge,
        format!(
            "uploads are limited to {} bytes",
            state.config.max_upload_bytes
        ),
    )
}

fn bad(message: impl Into<String>) -> ProtocolError {
    ProtocolError::new(ErrorCode::InvalidValue, message)
}

fn import_failed(e: &crate::import::ImportError) -> ProtocolError {
    ProtocolError::new(ErrorCode::ImportFailed, e.to_string())
}

/// The `format` query parameter, if any.
fn format_param(request: &Request) -> Option<String> {
    request.uri().query().and_then(|q| {
        q.split('&')
            .filter_map(|kv| kv.split_once('='))
            .find(|(k, _)| *k == "format")
            .map(|(_, v)| v.to_ascii_lowercase())
    })
}

/// The file set of a request: multipart file parts, or a raw body of one file.
async fn file_set(
    state: &Arc<AppState>,
    name: &str,
    request: Request,
) -> Result<FileSet, ProtocolError> {
    let content_type = request
        .headers()
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .unwrap_or("")
        .to_ascii_lowercase();
    let mut set = FileSet::new();
    if content_type.starts_with("multipart/form-data") {
        let mut multipart = Multipart::from_request(request, state)
            .await
            .map_err(|e| bad(format!("not a multipart body: {}", e.body_text())))?;
        loop {
            let field = match multipart.next_field().await {
                Ok(Some(f)) => f,
                Ok(None) => break,
                Err(e) if e.status() == StatusCode::PAYLOAD_TOO_LARGE => {
                    return Err(too_large(state));
                }
                Err(e) => return Err(bad(format!("bad multipart body: {}", e.body_text()))),
            };
            // Browsers send a bare file name; anything with folders keeps its last part.
            let file = field
                .file_name()
                .map(|f| f.rsplit(['/', '\\']).next().unwrap_or(f).to_owned())
                .ok_or_else(|| bad("every part must be a file (with a filename)"))?;
            let bytes = match field.bytes().await {
                Ok(b) => b,
                Err(e) if e.status() == StatusCode::PAYLOAD_TOO_LARGE => {
                    return Err(too_large(state));
                }
                Err(e) => return Err(bad(format!("bad multipart body: {}", e.body_text()))),
            };
            set.insert(&file, bytes.to_vec())
                .map_err(|e| import_failed(&e))?;
        }
    } else {
        let format = match format_param(&request) {
            Some(f) => f,
            None if content_type.starts_with("model/gltf-binary") => "glb".to_owned(),
            None => {
                return Err(bad(
                    "send multipart/form-data, or one file with Content-Type: model/gltf-binary or ?format=glb|gltf|bvh|skel",
                ));
            }
        };
        if !matches!(format.as_str(), "glb" | "gltf" | "bvh" | "skel") {
            return Err(bad(format!(
                "format {format:?} is not glb, gltf, bvh or skel"
            )));
        }
        let bytes = Bytes::from_request(request, state).await.map_err(|e| {
            if e.status() == StatusCode::PAYLOAD_TOO_LARGE {
                too_large(state)
            } else {
                bad(e.body_text())
            }
        })?;
        set.insert(&format!("{name}.{format}"), bytes.to_vec())
            .map_err(|e| import_failed(&e))?;
    }
    if set.is_empty() {
        return Err(bad("no files in the request"));
    }
    Ok(set)
}

/// `POST /api/assets/{name}`.
pub async fn upload(
    State(state): State<Arc<AppState>>,
    caller: Caller,
    Path(name): Path<String>,
    request: Request,
) -> Result<Json<Value>, AppError> {
    let result = async {
        state.config.access.authorize_upload(&caller)?;
        crate::library::check_name(&name)?;
        let set = file_set(&state, &name, request).await?;
        Ok::<_, AppError>(ingest::upload(&state, &name, set).await?)
    }
    .await;
    audit_upload("upload", &name, &caller, result.as_ref().map(|_| ()));
    Ok(Json(json!({ "result": result? })))
}

/// The audit line of an upload (`posecast::audit`, at `info`), refusals included.
fn audit_upload(op: &str, name: &str, caller: &Caller, result: Result<(), &AppError>) {
    let outcome = match result {
        Ok(()) => "ok".to_owned(),
        Err(e) => format!("{:?}: {}", e.0.code, e.0.message),
    };
    tracing::info!(target: "posecast::audit", op, target = %format!("asset {name}"), caller = caller.name(), outcome, "upload");
}

/// `POST /api/assets/{name}/clips`.
pub async fn add_clips(
    State(state): State<Arc<AppState>>,
    caller: Caller,
    Path(name): Path<String>,
    request: Request,
) -> Result<Json<Value>, AppError> {
    let result = async {
        state.config.access.authorize_upload(&caller)?;
        let set = file_set(&state, &name, request).await?;
        Ok::<_, AppError>(ingest::add_clips(&state, &name, set).await?)
    }
    .await;
    audit_upload("add_clips", &name, &caller, result.as_ref().map(|_| ()));
    Ok(Json(json!({ "result": result? })))
}
