//! JSON over HTTP: the same commands as the websocket, and read-only listings.
//!
//! - `POST /api/commands` with a [`Command`] body → `200 {"result": …}` or a typed error.
//! - `GET /api/scenes`, `GET /api/assets`: the `list_scenes` / `list_assets` results.

use crate::control;
use crate::state::AppState;
use axum::Json;
use axum::extract::rejection::JsonRejection;
use axum::extract::{Path, State};
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use posecast_proto::command::Command;
use posecast_proto::msg::{ErrorCode, ProtocolError};
use serde_json::{Value, json};
use std::sync::Arc;

/// A typed error as an HTTP response: the status follows the code, the body is
/// `{"code", "message"}`.
#[derive(Debug)]
pub struct AppError(pub ProtocolError);

impl From<ProtocolError> for AppError {
    fn from(e: ProtocolError) -> Self {
        Self(e)
    }
}

impl IntoResponse for AppError {
    fn into_response(self) -> Response {
        let status = match self.0.code {
            ErrorCode::UnknownScene
            | ErrorCode::UnknownAvatar
            | ErrorCode::UnknownClip
            | ErrorCode::UnknownJoint => StatusCode::NOT_FOUND,
            ErrorCode::Unauthorized => StatusCode::UNAUTHORIZED,
            ErrorCode::Forbidden => StatusCode::FORBIDDEN,
            ErrorCode::Conflict => StatusCode::CONFLICT,
            ErrorCode::MessageTooLarge | ErrorCode::TooLarge => StatusCode::PAYLOAD_TOO_LARGE,
            ErrorCode::ImportFailed => StatusCode::UNPROCESSABLE_ENTITY,
            ErrorCode::Internal => StatusCode::INTERNAL_SERVER_ERROR,
            _ => StatusCode::BAD_REQUEST,
        };
        (status, Json(self.0)).into_response()
    }
}

/// `POST /api/commands`.
pub async fn command(
    State(state): State<Arc<AppState>>,
    body: Result<Json<Command>, JsonRejection>,
) -> Result<Json<Value>, AppError> {
    let Json(command) = body.map_err(|e| {
        ProtocolError::new(
            ErrorCode::BadMessage,
            format!("not a valid command: {}", e.body_text()),
        )
    })?;
    let result = control::execute_durable(&state, &command).await?;
    Ok(Json(json!({ "result": result })))
}

/// `GET /api/scenes`.
pub async fn scenes(State(state): State<Arc<AppState>>) -> Result<Json<Value>, AppError> {
    Ok(Json(control::execute(&state, &Command::ListScenes)?))
}

/// `GET /api/assets/{name}/mesh.glb`: the rig's normalised skinned mesh (the space of its
/// description's inverse binds).
pub async fn mesh(
    State(state): State<Arc<AppState>>,
    Path(name): Path<String>,
) -> Result<Response, AppError> {
    let rig = state.library.get(&name).ok_or_else(|| {
        ProtocolError::new(
            ErrorCode::UnknownAvatar,
            format!("no rig (asset) named {name}"),
        )
    })?;
    if rig.asset.meshes.is_empty() {
        return Err(ProtocolError::new(
            ErrorCode::UnknownAvatar,
            format!("rig {name} has no mesh"),
        )
        .into());
    }
    let bytes = crate::export::mesh_glb(rig.skeleton(), &rig.asset.meshes);
    Ok((
        [(axum::http::header::CONTENT_TYPE, "model/gltf-binary")],
        bytes,
    )
        .into_response())
}

/// `GET /api/assets`.
pub async fn assets(State(state): State<Arc<AppState>>) -> Result<Json<Value>, AppError> {
    Ok(Json(control::execute(&state, &Command::ListAssets)?))
}
