//! Asset uploads over HTTP (see [`crate::ingest`] for what happens to the files).
//!
//! - `POST /api/assets/{name}`: a new asset from a `multipart/form-data` body whose file
//!   parts' names give the format (one `.glb`, `.vrm` or `.vrma`; one `.gltf` with its `.bin`/image files; one
//!   `.bvh`; one `.skel` with an optional `.skin`, `.anim` clips and `.morph` targets of the
//!   `.skin`), or from a raw body of one file: `Content-Type: model/gltf-binary`, or any type with `?format=glb|gltf|vrm|vrma|bvh|skel`.
//!   → `200 {"result": [AssetInfo, …]}` (several for a multi-skin glTF).
//! - `POST /api/assets/{name}/clips`: `.anim` clips (multipart) added to an uploaded `.skel`
//!   asset. → `200 {"result": AssetInfo}`.
//!
//! An upload's pipeline options ([`PipelineOptions`]) come as multipart text fields (parts
//! without a file name) or query parameters: `options` (the whole JSON object), or any of
//! `name_map` (a JSON object), `metres_per_unit`, `up_axis` (`+z`, or a JSON object),
//! `humanoid`, `neutral`, `simplify`, each replacing that field of `options`.
//!
//! Bodies are limited to `Config::max_upload_bytes` (413 `too_large`). Errors are typed:
//! `import_failed` (422) with the importer's message, `invalid_value` (400) for a bad name or
//! body, `conflict` (409) for a name in use.

use super::rest::{AppError, Bearer};
use crate::auth::Caller;

use crate::app::AppState;
use crate::ingest;
use axum::Json;
use axum::body::Bytes;
use axum::extract::{FromRequest, Multipart, Path, Request, State};
use axum::http::{StatusCode, header};
use posecast_proto::msg::{ErrorCode, ProtocolError};
use posecast_rigs::import::files::FileSet;
use posecast_rigs::rig::PipelineOptions;
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

fn import_failed(e: &posecast_rigs::import::ImportError) -> ProtocolError {
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

/// Pipeline options given as fields: `options` first (the whole object), then each single
/// field over it. Unknown field names are refused (a typo must not pass silently).
fn options_from_fields(fields: &[(String, String)]) -> Result<PipelineOptions, ProtocolError> {
    let parse = |name: &str, text: &str| -> Result<Value, ProtocolError> {
        serde_json::from_str(text)
            .or_else(|_| match name {
                // Bare words are strings: up_axis=+z, neutral=keep.
                "up_axis" | "neutral" => Ok(Value::String(text.to_owned())),
                _ => Err(()),
            })
            .map_err(|()| bad(format!("option {name}: {text:?} is not JSON")))
    };
    let mut object = serde_json::Map::new();
    if let Some((_, text)) = fields.iter().find(|(k, _)| k == "options") {
        match parse("options", text)? {
            Value::Object(o) => object = o,
            other => return Err(bad(format!("options must be a JSON object, not {other}"))),
        }
    }
    for (name, text) in fields {
        match name.as_str() {
            "options" | "format" => {}
            "up_axis" => {
                let v = match parse(name, text)? {
                    Value::String(up) => serde_json::json!({ "up": up }),
                    v => v,
                };
                object.insert(name.clone(), v);
            }
            "name_map" | "expression_map" | "metres_per_unit" | "humanoid" | "neutral"
            | "simplify" => {
                object.insert(name.clone(), parse(name, text)?);
            }
            other => {
                return Err(bad(format!(
                    "unknown field {other:?}: send files (with a filename), options, name_map, \
                     expression_map, metres_per_unit, up_axis, humanoid, neutral or simplify"
                )));
            }
        }
    }
    serde_json::from_value(Value::Object(object))
        .map_err(|e| bad(format!("bad pipeline options: {e}")))
}

/// The query's `name=value` pairs, percent-decoded.
fn query_fields(request: &Request) -> Result<Vec<(String, String)>, ProtocolError> {
    axum::extract::Query::<Vec<(String, String)>>::try_from_uri(request.uri())
        .map(|q| q.0)
        .map_err(|e| bad(format!("bad query: {}", e.body_text())))
}

/// The file set of a request (multipart file parts, or a raw body of one file) and the
/// pipeline options given with it (multipart text fields and query parameters).
async fn file_set(
    state: &Arc<AppState>,
    name: &str,
    request: Request,
) -> Result<(FileSet, PipelineOptions), ProtocolError> {
    let mut fields = query_fields(&request)?;
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
            let Some(file) = field
                .file_name()
                .map(|f| f.rsplit(['/', '\\']).next().unwrap_or(f).to_owned())
            else {
                // A text field: a pipeline option.
                let key = field.name().unwrap_or_default().to_owned();
                let text = field
                    .text()
                    .await
                    .map_err(|e| bad(format!("bad multipart field {key}: {}", e.body_text())))?;
                fields.push((key, text));
                continue;
            };
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
                    "send multipart/form-data, or one file with Content-Type: model/gltf-binary or ?format=glb|gltf|vrm|vrma|bvh|skel",
                ));
            }
        };
        if !matches!(
            format.as_str(),
            "glb" | "gltf" | "vrm" | "vrma" | "bvh" | "skel"
        ) {
            return Err(bad(format!(
                "format {format:?} is not glb, gltf, vrm, vrma, bvh or skel"
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
    Ok((set, options_from_fields(&fields)?))
}

/// `POST /api/assets/{name}`.
pub async fn upload(
    State(state): State<Arc<AppState>>,
    Bearer(caller): Bearer,
    Path(name): Path<String>,
    request: Request,
) -> Result<Json<Value>, AppError> {
    let result = async {
        state.config.access.authorize_upload(&caller)?;
        posecast_rigs::library::check_name(&name)?;
        let (set, options) = file_set(&state, &name, request).await?;
        Ok::<_, AppError>(ingest::upload(&state.services, &caller, &name, set, options).await?)
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
    Bearer(caller): Bearer,
    Path(name): Path<String>,
    request: Request,
) -> Result<Json<Value>, AppError> {
    let result = async {
        state.config.access.authorize_upload(&caller)?;
        let (set, options) = file_set(&state, &name, request).await?;
        if options != PipelineOptions::default() {
            return Err(AppError::from(bad(
                "clips take no pipeline options: change the asset's with configure_asset",
            )));
        }
        Ok::<_, AppError>(ingest::add_clips(&state.services, &name, set).await?)
    }
    .await;
    audit_upload("add_clips", &name, &caller, result.as_ref().map(|_| ()));
    Ok(Json(json!({ "result": result? })))
}
