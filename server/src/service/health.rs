//! `GET /healthz`, and holding back the REST API while the server is still starting
//! ([`crate::readiness`]).

use super::rest::AppError;
use crate::app::AppState;
use crate::readiness::Phase;
use axum::Json;
use axum::extract::{Request, State};
use axum::http::{StatusCode, header};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use serde::Serialize;
use std::sync::Arc;

/// What `/healthz` says while it is not ready (503); ready is the plain text `ok` (200).
#[derive(Debug, Serialize)]
#[serde(tag = "status", rename_all = "snake_case")]
enum NotReady {
    /// Loading: asset sources done (loaded or skipped) of the total. Scenes are restored
    /// after the last one.
    Starting {
        assets_loaded: usize,
        assets_total: usize,
    },
    /// Start-up failed; the process is about to exit.
    Failed { error: String },
    /// Shut down before it was ready.
    Stopped,
}

/// `GET /healthz`: `ok` (200) once everything stored is restored; before that 503 with a
/// JSON body saying what is loading, so a load balancer waits (`Retry-After: 1`).
pub async fn healthz(State(state): State<Arc<AppState>>) -> Response {
    let body = match state.readiness.phase() {
        Phase::Ready => {
            if state.cluster().is_some_and(|c| c.degraded()) {
                // Still serving the scenes ticked here: not a reason to take it out of a
                // load balancer, but worth an operator's look.
                return Json(serde_json::json!({
                    "status": "degraded",
                    "reason": "the connection to NATS is lost: scenes of other servers are not relayed and commands for them fail"
                }))
                .into_response();
            }
            return "ok".into_response();
        }
        Phase::Starting => {
            let (assets_loaded, assets_total) = state.readiness.progress();
            NotReady::Starting {
                assets_loaded,
                assets_total,
            }
        }
        Phase::Failed(error) => NotReady::Failed { error },
        Phase::Stopped => NotReady::Stopped,
    };
    (
        StatusCode::SERVICE_UNAVAILABLE,
        [(header::RETRY_AFTER, "1")],
        Json(body),
    )
        .into_response()
}

/// Requests under `/api/` wait until the server is ready, then run as usual: while starting,
/// a scene list would be empty and an asset missing only because it is not loaded yet, and a
/// change could collide with a scene about to be restored. Everything else (`/healthz`,
/// `/metrics`, the dashboard's files, the websocket upgrade) is served at once.
pub async fn wait_until_ready(
    State(state): State<Arc<AppState>>,
    request: Request,
    next: Next,
) -> Response {
    if request.uri().path().starts_with("/api/")
        && let Err(e) = state.readiness.wait().await
    {
        return AppError(e.into()).into_response();
    }
    next.run(request).await
}
