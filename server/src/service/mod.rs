//! The HTTP and websocket service: `fn app(state) -> Router`, so tests start the server
//! in-process on port 0.
//!
//! - `GET /ws`: the websocket protocol ([`ws`], `proto/PROTOCOL.md`).
//! - `POST /api/commands`, `GET /api/scenes`, `GET /api/assets`,
//!   `GET /api/assets/{name}/mesh.glb` ([`rest`]).
//! - `POST /api/assets/{name}`, `POST /api/assets/{name}/clips`: uploads ([`upload`]), with
//!   their own body limit (`Config::max_upload_bytes`); everything else keeps 64 KiB.
//! - `GET /healthz`, `GET /metrics`.
//! - `GET /`, `GET /dashboard/{file}`: the web dashboard ([`dashboard`]).

pub mod dashboard;
pub mod rest;
pub mod upload;
pub mod ws;

use crate::state::AppState;
use axum::Router;
use axum::extract::{State, WebSocketUpgrade};
use axum::http::{StatusCode, header};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use posecast_proto::msg::MAX_CLIENT_MESSAGE_BYTES;
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
        .layer(axum::extract::DefaultBodyLimit::max(
            MAX_CLIENT_MESSAGE_BYTES,
        ))
        .route(
            "/api/assets/{name}",
            post(upload::upload).layer(axum::extract::DefaultBodyLimit::max(
                state.config.max_upload_bytes,
            )),
        )
        .route(
            "/api/assets/{name}/clips",
            post(upload::add_clips).layer(axum::extract::DefaultBodyLimit::max(
                state.config.max_upload_bytes,
            )),
        )
        .route("/healthz", get(|| async { "ok" }))
        .route("/metrics", get(metrics))
        .route("/", get(dashboard::index))
        .route("/dashboard/{file}", get(dashboard::file))
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

async fn ws_upgrade(ws: WebSocketUpgrade, State(state): State<Arc<AppState>>) -> Response {
    ws.max_message_size(MAX_CLIENT_MESSAGE_BYTES)
        .max_frame_size(MAX_CLIENT_MESSAGE_BYTES)
        .on_upgrade(move |socket| ws::serve(socket, state))
}

async fn metrics(State(state): State<Arc<AppState>>) -> impl IntoResponse {
    let subscribers: Vec<(String, usize)> = state
        .scenes()
        .iter()
        .map(|s| (s.id.0.clone(), s.subscriber_count()))
        .collect();
    (
        [(header::CONTENT_TYPE, "text/plain; version=0.0.4")],
        state.metrics.render(&subscribers),
    )
}
