//! A deadline on reading a request body (`NetLimits::body_read_timeout`).
//!
//! hyper bounds the request head (`header_read_timeout`) but not the body: a client that
//! announces a 32 MiB upload and sends a byte a minute would hold its connection (and a
//! handler) for a year. The body is wrapped so that a read past the deadline fails; the
//! handler's extractor then fails, and the answer becomes `408 timeout` whatever the handler
//! made of the error (a multipart or JSON rejection would otherwise read as a bad request).
//! The connection closes after that answer: the rest of the body was never read.

use super::rest::AppError;
use crate::app::AppState;
use crate::metrics::net::Timeout;
use axum::body::{Body, Bytes};
use axum::extract::{Request, State};
use axum::http::{HeaderValue, header};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use http_body::Frame;
use posecast_proto::msg::{ErrorCode, ProtocolError};
use std::future::Future;
use std::pin::Pin;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::task::{Context, Poll};
use std::time::Duration;

/// Why reading a wrapped body failed.
#[derive(Debug, thiserror::Error)]
pub enum BodyError {
    /// The client's body stream failed.
    #[error(transparent)]
    Inner(#[from] axum::Error),
    /// The deadline passed first.
    #[error("the request body was not received within {0:?}")]
    TimedOut(Duration),
}

/// A request body that fails once its deadline has passed.
struct DeadlineBody {
    inner: Body,
    deadline: Pin<Box<tokio::time::Sleep>>,
    limit: Duration,
    expired: Arc<AtomicBool>,
}

impl http_body::Body for DeadlineBody {
    type Data = Bytes;
    type Error = BodyError;

    fn poll_frame(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<Frame<Bytes>, BodyError>>> {
        let this = self.get_mut();
        // Data already there is taken even at the deadline: only waiting is bounded.
        if let Poll::Ready(frame) = Pin::new(&mut this.inner).poll_frame(cx) {
            return Poll::Ready(frame.map(|f| f.map_err(BodyError::from)));
        }
        if this.deadline.as_mut().poll(cx).is_ready() {
            this.expired.store(true, Ordering::Relaxed);
            return Poll::Ready(Some(Err(BodyError::TimedOut(this.limit))));
        }
        Poll::Pending
    }

    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }

    fn size_hint(&self) -> http_body::SizeHint {
        self.inner.size_hint()
    }
}

/// Middleware: bounds the time to read the request's body; answers `408 timeout` (and closes
/// the connection) when the handler ran into the deadline.
pub async fn limit(State(state): State<Arc<AppState>>, request: Request, next: Next) -> Response {
    let limit = state.config.net.body_read_timeout;
    let expired = Arc::new(AtomicBool::new(false));
    let request = request.map(|inner| {
        Body::new(DeadlineBody {
            inner,
            deadline: Box::pin(tokio::time::sleep(limit)),
            limit,
            expired: expired.clone(),
        })
    });
    let response = next.run(request).await;
    if !expired.load(Ordering::Relaxed) {
        return response;
    }
    state.metrics.net.timed_out(Timeout::Body);
    let mut response = AppError(ProtocolError::new(
        ErrorCode::Timeout,
        format!(
            "the request body was not received within {} s",
            limit.as_secs_f64()
        ),
    ))
    .into_response();
    response
        .headers_mut()
        .insert(header::CONNECTION, HeaderValue::from_static("close"));
    response
}
