//! The HTTP and websocket service: `fn app(state) -> Router`, so tests start the server
//! in-process on port 0.
//!
//! - `GET /ws`: the websocket protocol (`ws`, `proto/PROTOCOL.md`).
//! - `POST /api/commands`, `GET /api/scenes`, `GET /api/assets`,
//!   `GET /api/assets/{name}/mesh.glb` (`rest`).
//! - `POST /api/assets/{name}`, `POST /api/assets/{name}/clips`: uploads (`upload`), with
//!   their own body limit (`Config::max_upload_bytes`); everything else keeps 64 KiB.
//! - `GET /healthz` (`health`: 503 with the progress while starting, then `ok`),
//!   `GET /metrics`.
//! - `GET /`, `GET /dashboard/{file}`: the web dashboard (`dashboard`);
//! - `GET /sdk/{file}`: the JavaScript client `posecast.js` and its declarations (`dashboard`).
//!
//! Connections reach the router through `listener`, the accept loop: connection caps
//! (`admission`), request-head and body deadlines (`body_deadline`) and the websocket
//! liveness rules, all configured by `NetLimits`; counted in [`crate::metrics::net`].
//!
//! Every error response has the typed body `{"code", "message"}`, including axum's own
//! rejections (405, 413, extractor errors) and unknown paths (404): see [`typed_errors`]; and
//! hyper's answers to a head it cannot parse (400, 414, 431): see `head_errors`.

mod admission;
pub use admission::IDLE_BEFORE_EVICTION;
mod body_deadline;
mod dashboard;
mod head_errors;
mod health;
pub mod limits;
mod linger;
pub(crate) mod listener;

pub(crate) mod quic;
mod rest;
mod tokens;
mod upload;
mod ws;
mod ws_liveness;

use crate::app::AppState;
use axum::Router;
use axum::extract::{State, WebSocketUpgrade};
use axum::http::{Method, StatusCode, Uri, header};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use posecast_proto::msg::{ErrorCode, MAX_CLIENT_MESSAGE_BYTES, ProtocolError};
use rest::AppError;
use std::sync::Arc;

/// The whole service.
pub fn app(state: Arc<AppState>) -> Router {
    let counted = state.clone();
    Router::new()
        .route("/ws", get(ws_upgrade))
        .route("/api/commands", post(rest::command))
        .route("/api/scenes", get(rest::scenes))
        .route("/api/assets", get(rest::assets))
        .route("/api/assets/{name}/mesh.glb", get(rest::mesh))
        .route(
            "/api/assets/{name}/clips/{file}",
            get(rest::clip_file).delete(rest::delete_clip),
        )
        .route("/api/takes", get(rest::takes))
        .route(
            "/api/takes/{take}",
            get(rest::take).delete(rest::delete_take),
        )
        .route("/api/takes/{take}/{file}", get(rest::take_avatar))
        .route("/api/quic", get(quic_info))
        .route("/api/tokens", post(tokens::mint).get(tokens::list))
        .route("/api/tokens/{id}", axum::routing::delete(tokens::revoke))
        .layer(axum::extract::DefaultBodyLimit::max(
            MAX_CLIENT_MESSAGE_BYTES,
        ))
        .route(
            "/api/assets/{name}",
            post(upload::upload)
                .layer(axum::extract::DefaultBodyLimit::max(
                    state.config.max_upload_bytes,
                ))
                .delete(rest::delete_asset),
        )
        .route(
            "/api/assets/{name}/clips",
            post(upload::add_clips).layer(axum::extract::DefaultBodyLimit::max(
                state.config.max_upload_bytes,
            )),
        )
        .route("/healthz", get(health::healthz))
        .route("/metrics", get(metrics))
        .route("/", get(dashboard::index))
        .route("/dashboard/{file}", get(dashboard::file))
        .route("/sdk/{file}", get(dashboard::sdk))
        .fallback(not_found)
        // The body deadline starts once the request may run, not while start-up holds it.
        .layer(axum::middleware::from_fn_with_state(
            state.clone(),
            body_deadline::limit,
        ))
        .layer(axum::middleware::from_fn_with_state(
            state.clone(),
            health::wait_until_ready,
        ))
        .layer(axum::middleware::map_response(typed_errors))
        .layer(axum::middleware::map_response_with_state(
            counted,
            count_refusals,
        ))
        .with_state(state)
}

/// Counts HTTP refusals for a token (401, 403) in the metrics; the websocket counts its own.
async fn count_refusals(State(state): State<Arc<AppState>>, response: Response) -> Response {
    match response.status() {
        StatusCode::UNAUTHORIZED => state.metrics.refused(false),
        StatusCode::FORBIDDEN => state.metrics.refused(true),
        _ => {}
    }
    response
}

async fn not_found(method: Method, uri: Uri) -> AppError {
    AppError(ProtocolError::new(
        ErrorCode::NotFound,
        format!("no endpoint {method} {}", uri.path()),
    ))
}

/// Largest untyped error body kept as the typed error's message.
const MAX_ERROR_TEXT: usize = 1024;

/// Gives an error response that is not already JSON the typed body `{"code", "message"}`, like
/// every error of our own handlers: axum answers a wrong method (405, empty), a body over the
/// limit (413) and extractor failures (400) in plain text. The status and headers stay (the
/// `Allow` of a 405, the dashboard's policy headers); the message is the original text, or
/// names the method and path.
pub async fn typed_errors(method: Method, uri: Uri, response: Response) -> Response {
    let status = response.status();
    let is_json = response
        .headers()
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.starts_with("application/json"));
    if !(status.is_client_error() || status.is_server_error()) || is_json {
        return response;
    }
    let code = match status {
        StatusCode::UNAUTHORIZED => ErrorCode::Unauthorized,
        StatusCode::FORBIDDEN => ErrorCode::Forbidden,
        StatusCode::NOT_FOUND => ErrorCode::NotFound,
        StatusCode::METHOD_NOT_ALLOWED => ErrorCode::MethodNotAllowed,
        StatusCode::CONFLICT => ErrorCode::Conflict,
        StatusCode::PAYLOAD_TOO_LARGE => ErrorCode::TooLarge,
        StatusCode::REQUEST_TIMEOUT => ErrorCode::Timeout,
        StatusCode::SERVICE_UNAVAILABLE => ErrorCode::Unavailable,
        s if s.is_server_error() => ErrorCode::Internal,
        _ => ErrorCode::BadMessage,
    };
    let (mut parts, body) = response.into_parts();
    let text = axum::body::to_bytes(body, MAX_ERROR_TEXT)
        .await
        .ok()
        .and_then(|b| String::from_utf8(b.to_vec()).ok())
        .map(|t| t.trim().to_owned())
        .unwrap_or_default();
    let message = match code {
        ErrorCode::MethodNotAllowed => {
            let allowed = parts
                .headers
                .get(header::ALLOW)
                .and_then(|v| v.to_str().ok())
                .unwrap_or("none");
            format!(
                "{method} is not allowed on {}; allowed: {allowed}",
                uri.path()
            )
        }
        ErrorCode::TooLarge if text.is_empty() => "the request body is too large".to_owned(),
        ErrorCode::TooLarge => format!("the request body is too large ({text})"),
        _ if text.is_empty() => format!(
            "{method} {}: {}",
            uri.path(),
            status.canonical_reason().unwrap_or("error")
        ),
        _ => text,
    };
    let (typed, body) = axum::Json(ProtocolError::new(code, message))
        .into_response()
        .into_parts();
    parts.headers.remove(header::CONTENT_LENGTH);
    if let Some(content_type) = typed.headers.get(header::CONTENT_TYPE) {
        parts
            .headers
            .insert(header::CONTENT_TYPE, content_type.clone());
    }
    Response::from_parts(parts, body)
}

async fn ws_upgrade(
    State(state): State<Arc<AppState>>,
    request: axum::extract::Request,
) -> Response {
    use axum::extract::FromRequestParts;
    let (mut parts, _body) = request.into_parts();
    let peer = parts
        .extensions
        .get::<axum::extract::ConnectInfo<std::net::SocketAddr>>()
        .map(|c| c.0);
    let greeter = parts.extensions.get::<admission::Greeter>().cloned();
    let socket = parts.extensions.get::<listener::SocketInfo>().copied();
    // The listener's own connections keep their socket (`ws::direct`); axum's checks of the
    // request and its rejections stand either way.
    let on_upgrade = parts.extensions.get::<hyper::upgrade::OnUpgrade>().cloned();
    let ws = match WebSocketUpgrade::from_request_parts(&mut parts, &state).await {
        Ok(ws) => ws,
        Err(rejection) => return rejection.into_response(),
    };
    let key = parts.headers.get(axum::http::header::SEC_WEBSOCKET_KEY);
    if let (true, Some(on_upgrade), Some(key), Some(_)) =
        (state.config.net.ws_direct_writes, on_upgrade, key, socket)
    {
        drop(ws);
        return ws::direct::accept(on_upgrade, key, state, peer, greeter, socket);
    }
    ws.max_message_size(MAX_CLIENT_MESSAGE_BYTES)
        .max_frame_size(MAX_CLIENT_MESSAGE_BYTES)
        .read_buffer_size(ws::READ_BUFFER_BYTES)
        .write_buffer_size(ws::WRITE_BUFFER_BYTES)
        .on_upgrade(move |ws| ws::serve(ws, state, peer, greeter, socket))
}

/// `GET /api/quic`: the WebTransport endpoint, if this server has one (`--quic-listen`):
/// `{available, port, cert_sha256, self_signed}` — a page connects to
/// `https://<this host>:<port>/` with `serverCertificateHashes` set to `cert_sha256` when
/// `self_signed`. Public, like the websocket's address, and readable by pages of any origin
/// (which load the client from `/sdk/` and connect from there).
async fn quic_info(State(state): State<Arc<AppState>>) -> impl IntoResponse {
    let info = axum::Json(match state.quic.get() {
        Some(q) => serde_json::json!({
            "available": true,
            "port": q.port,
            "cert_sha256": q.cert_sha256,
            "self_signed": q.self_signed,
        }),
        None => serde_json::json!({ "available": false }),
    });
    (
        [(axum::http::header::ACCESS_CONTROL_ALLOW_ORIGIN, "*")],
        info,
    )
}

/// `GET /metrics`: readable by whoever may read (anyone with open views; a view or control
/// token with `--require-view-token`). Scene names are private to token holders: anonymous
/// callers get the total subscriber count only, a scene-limited token its own scenes.
async fn metrics(
    State(state): State<Arc<AppState>>,
    rest::Bearer(caller): rest::Bearer,
) -> Result<impl IntoResponse, rest::AppError> {
    let access = &state.config.access;
    access.authorize_read(&caller)?;
    let scenes = state.world.scenes();
    let total = scenes.iter().map(|s| s.subscriber_count()).sum();
    let subscribers: Vec<(String, usize)> = match caller {
        crate::auth::Caller::Anonymous => Vec::new(),
        _ => scenes
            .iter()
            .filter(|s| access.authorize_view(&caller, &s.id).is_ok())
            .map(|s| (s.id.0.clone(), s.subscriber_count()))
            .collect(),
    };
    let replays = state.world.replayed_takes().len() as u64;
    state
        .metrics
        .takes
        .now(state.takes.recording(), replays, state.takes.held_bytes());
    let text = state.metrics.render(&subscribers, total).map_err(|e| {
        AppError(ProtocolError::new(
            ErrorCode::Internal,
            format!("encoding metrics: {e}"),
        ))
    })?;
    Ok(([(header::CONTENT_TYPE, crate::metrics::CONTENT_TYPE)], text))
}
