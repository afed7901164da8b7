//! JSON over HTTP: the same commands as the websocket, and read-only listings.
//!
//! - `POST /api/commands` with a [`Command`] body → `200 {"kind": …, "result": …}` (the result tagged with its shape) or a typed error.
//! - `GET /api/scenes`, `GET /api/assets`, `GET /api/takes`: the `list_scenes` /
//!   `list_assets` / `list_takes` results; `GET /api/takes/{take}` (`get_take`),
//!   `GET /api/takes/{take}.glb` and `GET /api/takes/{take}/{avatar}.bvh` (exports, with
//!   `?from=&to=` seconds), `DELETE /api/takes/{take}` (`delete_take`).
//!
//! Every request may carry `Authorization: Bearer <token>` ([`crate::auth`]); refusals are
//! 401 (with `WWW-Authenticate: Bearer`) or 403 with the typed error as body.

use crate::app::AppState;
use crate::auth::Caller;
use crate::control;
use axum::Json;
use axum::extract::FromRequestParts;
use axum::extract::{Path, Query, State};
use axum::http::request::Parts;
use axum::http::{StatusCode, header};
use axum::response::{IntoResponse, Response};
use bytes::Bytes;
use posecast_proto::command::Command;
use posecast_proto::msg::{ErrorCode, ProtocolError};
use serde_json::Value;
use std::sync::Arc;

/// A typed error as an HTTP response: the status follows the code, the body is
/// `{"code", "message"}`.
#[derive(Debug)]
pub struct AppError(pub ProtocolError);

impl From<posecast_core::error::Error> for AppError {
    fn from(e: posecast_core::error::Error) -> Self {
        Self(e.into())
    }
}

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
            | ErrorCode::UnknownJoint
            | ErrorCode::UnknownExpression
            | ErrorCode::UnknownTake
            | ErrorCode::UnknownAsset
            | ErrorCode::NoMesh => StatusCode::NOT_FOUND,
            ErrorCode::Unauthorized => StatusCode::UNAUTHORIZED,
            ErrorCode::Forbidden => StatusCode::FORBIDDEN,
            ErrorCode::Conflict => StatusCode::CONFLICT,
            ErrorCode::MessageTooLarge | ErrorCode::TooLarge => StatusCode::PAYLOAD_TOO_LARGE,
            ErrorCode::ImportFailed | ErrorCode::NotHumanoid => StatusCode::UNPROCESSABLE_ENTITY,
            ErrorCode::Internal => StatusCode::INTERNAL_SERVER_ERROR,
            ErrorCode::MethodNotAllowed => StatusCode::METHOD_NOT_ALLOWED,
            ErrorCode::QuotaExceeded | ErrorCode::RateLimited => StatusCode::TOO_MANY_REQUESTS,
            ErrorCode::NotFound => StatusCode::NOT_FOUND,
            ErrorCode::Timeout => StatusCode::REQUEST_TIMEOUT,
            ErrorCode::Unavailable => StatusCode::SERVICE_UNAVAILABLE,
            ErrorCode::StorageFull => StatusCode::INSUFFICIENT_STORAGE,
            ErrorCode::OutcomeUnknown => StatusCode::GATEWAY_TIMEOUT,
            _ => StatusCode::BAD_REQUEST,
        };
        let mut response = (status, Json(self.0)).into_response();
        if status == StatusCode::UNAUTHORIZED {
            response.headers_mut().insert(
                header::WWW_AUTHENTICATE,
                header::HeaderValue::from_static("Bearer realm=\"posecast\""),
            );
        }
        response
    }
}

/// The caller of a request, from its `Authorization: Bearer <token>` header (none:
/// anonymous; the scheme is case-insensitive, RFC 7235 §2.1). A header that is not a bearer
/// token, or an unknown token, is refused with 401.
#[derive(Debug, Clone)]
pub struct Bearer(pub Caller);

impl FromRequestParts<Arc<AppState>> for Bearer {
    type Rejection = AppError;

    async fn from_request_parts(
        parts: &mut Parts,
        state: &Arc<AppState>,
    ) -> Result<Self, Self::Rejection> {
        let Some(value) = parts.headers.get(header::AUTHORIZATION) else {
            return Ok(Self(Caller::Anonymous));
        };
        let identified = value
            .to_str()
            .ok()
            .and_then(bearer_token)
            .ok_or_else(|| {
                ProtocolError::new(
                    ErrorCode::Unauthorized,
                    "the Authorization header must be `Bearer <token>`",
                )
            })
            .and_then(|token| Ok(state.config.access.identify(Some(token))?));
        if let Err(e) = &identified {
            // The request never reaches its handler: its refusal is audited here (the
            // token itself is never logged).
            tracing::info!(
                target: "posecast::audit",
                op = %parts.method,
                target = %parts.uri.path(),
                caller = "-",
                outcome = %format!("{:?}: {}", e.code, e.message),
                "refused"
            );
        }
        Ok(Self(identified?))
    }
}

/// The token of an `Authorization` value `Bearer <token>`, the scheme in any case.
fn bearer_token(value: &str) -> Option<&str> {
    let (scheme, token) = value.trim_start().split_once([' ', '\t'])?;
    let token = token.trim();
    (scheme.eq_ignore_ascii_case("bearer") && !token.is_empty()).then_some(token)
}

/// The longest idempotency key taken (a UUID is 36 characters).
const MAX_IDEMPOTENCY_KEY: usize = 128;

/// `POST /api/commands`.
pub async fn command(
    State(state): State<Arc<AppState>>,
    Bearer(caller): Bearer,
    headers: axum::http::HeaderMap,
    body: Bytes,
) -> Result<Json<Value>, AppError> {
    // A retry after an unknown outcome (a timeout) carries the first try's key and is
    // applied at most once (`docs/src/how-to/cluster.md`).
    let key = match headers.get("idempotency-key").map(|v| v.to_str()) {
        None => None,
        Some(Ok(k)) if !k.is_empty() && k.len() <= MAX_IDEMPOTENCY_KEY => Some(k.to_owned()),
        Some(_) => {
            return Err(ProtocolError::new(
                ErrorCode::InvalidValue,
                format!(
                    "Idempotency-Key must be 1 to {MAX_IDEMPOTENCY_KEY} visible ASCII characters"
                ),
            )
            .into());
        }
    };
    // The body is JSON whatever its Content-Type (so `curl -d '{…}'` works). That is safe
    // from cross-site form posts because every command needs an `Authorization` header,
    // which a form cannot set.
    let command: Command = serde_json::from_slice(&body).map_err(|e| {
        ProtocolError::new(ErrorCode::BadMessage, format!("not a valid command: {e}"))
    })?;
    let result = match control::authorize(&state, &caller, &command) {
        Ok(()) => control::execute_as(&state, &caller, &command, key.as_deref()).await,
        Err(e) => Err(e),
    };
    control::audit(caller.name(), &command, &result);
    let result = state.config.access.visible(&caller, result?);
    Ok(Json(result.to_tagged_value()))
}

/// `DELETE /api/assets/{name}`: the `delete_asset` command.
pub async fn delete_asset(
    State(state): State<Arc<AppState>>,
    Bearer(caller): Bearer,
    Path(name): Path<String>,
) -> Result<Json<Value>, AppError> {
    run(&state, &caller, &Command::DeleteAsset { asset: name }).await
}

/// `DELETE /api/assets/{name}/clips/{clip}`: the `delete_clip` command (the clip's bare name,
/// or `{clip}.glb` as `GET` serves it).
pub async fn delete_clip(
    State(state): State<Arc<AppState>>,
    Bearer(caller): Bearer,
    Path((name, clip)): Path<(String, String)>,
) -> Result<Json<Value>, AppError> {
    let clip = match clip.strip_suffix(".glb") {
        Some(stem)
            if state
                .world
                .library
                .get(&name)
                .is_some_and(|r| r.clip(&clip).is_none()) =>
        {
            stem.to_owned()
        }
        _ => clip,
    };
    run(&state, &caller, &Command::DeleteClip { asset: name, clip }).await
}

/// Authorises, runs and audits `command` as `POST /api/commands` does.
async fn run(
    state: &AppState,
    caller: &Caller,
    command: &Command,
) -> Result<Json<Value>, AppError> {
    let result = match control::authorize(state, caller, command) {
        Ok(()) => control::execute_as(state, caller, command, None).await,
        Err(e) => Err(e),
    };
    control::audit(caller.name(), command, &result);
    Ok(Json(result?.to_tagged_value()))
}

/// `GET /api/scenes`.
pub async fn scenes(
    State(state): State<Arc<AppState>>,
    Bearer(caller): Bearer,
) -> Result<Json<Value>, AppError> {
    state.config.access.authorize_read(&caller)?;
    let scenes = control::execute_durable(&state, &Command::ListScenes).await?;
    Ok(Json(
        state.config.access.visible(&caller, scenes).to_value(),
    ))
}

/// `GET /api/assets/{name}/mesh.glb`: the rig's normalised skinned mesh (the space of its
/// description's inverse binds).
pub async fn mesh(
    State(state): State<Arc<AppState>>,
    Bearer(caller): Bearer,
    Path(name): Path<String>,
) -> Result<Response, AppError> {
    state.config.access.authorize_read(&caller)?;
    let rig = state.world.library.require(&name)?;
    if rig.asset.meshes.is_empty() {
        return Err(posecast_core::error::Error::NoMesh(name).into());
    }
    let bytes = posecast_rigs::export::mesh_glb(rig.skeleton(), &rig.asset.meshes)
        .map_err(|e| ProtocolError::new(ErrorCode::Internal, format!("rig {name}: {e}")))?;
    Ok((
        [
            (axum::http::header::CONTENT_TYPE, "model/gltf-binary"),
            // Pages of any origin load it (three.js's GLTFLoader fetches with CORS), as they
            // load the client from /sdk/; reads that need a token still need it.
            (axum::http::header::ACCESS_CONTROL_ALLOW_ORIGIN, "*"),
        ],
        bytes,
    )
        .into_response())
}

/// `GET /api/assets/{name}/clips/{clip}.glb` (the rig's mesh and skin with the clip as its
/// one animation) and `…/{clip}.bvh` (the skeleton and the clip as BVH motion): any clip of a
/// rig, recorded ones included. Written on the blocking pool (a long clip takes a while).
pub async fn clip_file(
    State(state): State<Arc<AppState>>,
    Bearer(caller): Bearer,
    Path((name, file)): Path<(String, String)>,
) -> Result<Response, AppError> {
    state.config.access.authorize_read(&caller)?;
    let (clip, format) = file.rsplit_once('.').ok_or_else(|| {
        ProtocolError::new(
            ErrorCode::NotFound,
            format!("{file}: ask for <clip>.glb or <clip>.bvh"),
        )
    })?;
    let rig = state.world.library.require(&name)?;
    let clip = rig
        .clip(clip)
        .cloned()
        .ok_or_else(|| posecast_core::error::Error::UnknownClip {
            rig: name.clone(),
            clip: clip.to_owned(),
        })?;
    let (content_type, export): (
        &str,
        fn(&posecast_rigs::rig::Rig, &posecast_rigs::clip::Clip) -> _,
    ) = match format {
        "glb" => ("model/gltf-binary", |rig, clip| {
            posecast_rigs::export::clip_glb(rig, clip)
        }),
        "bvh" => ("text/plain; charset=utf-8", |rig, clip| {
            posecast_rigs::export::clip_bvh(rig, clip).map(String::into_bytes)
        }),
        other => {
            return Err(ProtocolError::new(
                ErrorCode::NotFound,
                format!("clips are exported as .glb or .bvh, not .{other}"),
            )
            .into());
        }
    };
    let bytes = tokio::task::spawn_blocking(move || export(&rig, &clip))
        .await
        .map_err(|e| posecast_core::error::Error::internal("export task failed", &e))?
        .map_err(|e| posecast_core::error::Error::internal(&format!("exporting {file}"), &e))?;
    Ok((
        [
            (axum::http::header::CONTENT_TYPE, content_type.to_owned()),
            (
                axum::http::header::CONTENT_DISPOSITION,
                format!("attachment; filename=\"{name}.{file}\""),
            ),
        ],
        bytes,
    )
        .into_response())
}

/// `GET /api/takes`: the `list_takes` result.
pub async fn takes(
    State(state): State<Arc<AppState>>,
    Bearer(caller): Bearer,
) -> Result<Json<Value>, AppError> {
    state.config.access.authorize_read(&caller)?;
    Ok(Json(
        control::execute_as(&state, &caller, &Command::ListTakes, None)
            .await?
            .to_value(),
    ))
}

/// `GET /api/takes/{take}`: the `get_take` result; `GET /api/takes/{take}.glb?from=&to=`: the
/// take (or the range, seconds) as one glTF, every avatar's mesh and skin and one animation
/// moving them all ([`crate::takes::export`]).
pub async fn take(
    State(state): State<Arc<AppState>>,
    Bearer(caller): Bearer,
    Path(name): Path<String>,
    Query(range): Query<crate::takes::export::Range>,
) -> Result<Response, AppError> {
    state.config.access.authorize_read(&caller)?;
    let Some(take) = name.strip_suffix(".glb") else {
        let info =
            control::execute_as(&state, &caller, &Command::GetTake { take: name }, None).await?;
        return Ok(Json(info.to_value()).into_response());
    };
    // The take shows its scene: only to who may watch it.
    control::takes::describe(&state, &caller, take).await?;
    let file = name.clone();
    let take = take.to_owned();
    let _turn = crate::takes::export::turn().await;
    let (takes, world) = (state.takes.clone(), state.clone());
    let bytes = tokio::task::spawn_blocking(move || {
        let index = takes.index(&take)?;
        let source = takes.source(&take)?;
        let avatars =
            crate::takes::export::clips(&take, index, source, &world.world.library, range, None)?;
        let figures: Vec<posecast_rigs::export::TakeAvatar<'_>> = avatars
            .iter()
            .map(|a| posecast_rigs::export::TakeAvatar {
                name: &a.description.id.0,
                rig: &a.rig,
                clip: &a.clip,
            })
            .collect();
        posecast_rigs::export::take_glb(&figures, &take)
            .map_err(|e| posecast_core::error::Error::internal(&format!("exporting {take}"), &e))
    })
    .await
    .map_err(|e| posecast_core::error::Error::internal("export task failed", &e))??;
    Ok(attachment("model/gltf-binary", &file, bytes))
}

/// `GET /api/takes/{take}/{avatar}.bvh?from=&to=`: one avatar of a take (or of the range,
/// seconds) as BVH motion of its rig, its root in scene space.
pub async fn take_avatar(
    State(state): State<Arc<AppState>>,
    Bearer(caller): Bearer,
    Path((take, file)): Path<(String, String)>,
    Query(range): Query<crate::takes::export::Range>,
) -> Result<Response, AppError> {
    state.config.access.authorize_read(&caller)?;
    let avatar = file.strip_suffix(".bvh").ok_or_else(|| {
        ProtocolError::new(
            ErrorCode::NotFound,
            format!("{file}: an avatar of a take is exported as <avatar>.bvh"),
        )
    })?;
    let avatar = posecast_proto::msg::AvatarId(avatar.to_owned());
    control::takes::describe(&state, &caller, &take).await?;
    let _turn = crate::takes::export::turn().await;
    let (takes, world, name) = (state.takes.clone(), state.clone(), take.clone());
    let bytes = tokio::task::spawn_blocking(move || {
        let index = takes.index(&name)?;
        let source = takes.source(&name)?;
        let exported = crate::takes::export::clips(
            &name,
            index,
            source,
            &world.world.library,
            range,
            Some(&avatar),
        )?;
        let one = exported
            .first()
            .ok_or_else(|| posecast_core::error::Error::UnknownAvatar(avatar.clone()))?;
        posecast_rigs::export::clip_bvh(&one.rig, &one.clip)
            .map(String::into_bytes)
            .map_err(|e| posecast_core::error::Error::internal(&format!("exporting {avatar}"), &e))
    })
    .await
    .map_err(|e| posecast_core::error::Error::internal("export task failed", &e))??;
    Ok(attachment(
        "text/plain; charset=utf-8",
        &format!("{take}.{file}"),
        bytes,
    ))
}

/// `DELETE /api/takes/{take}`: the `delete_take` command.
pub async fn delete_take(
    State(state): State<Arc<AppState>>,
    Bearer(caller): Bearer,
    Path(take): Path<String>,
) -> Result<Json<Value>, AppError> {
    run(&state, &caller, &Command::DeleteTake { take }).await
}

/// A download named `file`.
fn attachment(content_type: &str, file: &str, bytes: Vec<u8>) -> Response {
    (
        [
            (header::CONTENT_TYPE, content_type.to_owned()),
            (
                header::CONTENT_DISPOSITION,
                format!("attachment; filename=\"{file}\""),
            ),
        ],
        bytes,
    )
        .into_response()
}

/// `GET /api/assets`.
pub async fn assets(
    State(state): State<Arc<AppState>>,
    Bearer(caller): Bearer,
) -> Result<Json<Value>, AppError> {
    state.config.access.authorize_read(&caller)?;
    Ok(Json(
        control::execute(&state, &Command::ListAssets)?.to_value(),
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_bearer_scheme_is_case_insensitive_and_needs_a_token() {
        for value in [
            "Bearer abc",
            "bearer abc",
            "BEARER abc",
            "bEaReR  abc ",
            "Bearer\tabc",
        ] {
            assert_eq!(bearer_token(value), Some("abc"), "{value:?}");
        }
        for value in [
            "Basic abc",
            "Bearer",
            "Bearer ",
            "Bearerabc",
            "Token abc",
            "",
        ] {
            assert_eq!(bearer_token(value), None, "{value:?}");
        }
    }
}
