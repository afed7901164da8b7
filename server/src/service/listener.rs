//! The accept loop: every TCP connection is admitted under the caps ([`super::admission`]) or
//! refused with an answer, served by hyper's HTTP/1 with a request-head deadline, and shut down
//! gracefully on the signal.
//!
//! This replaces `axum::serve`, which has no connection caps, no header timeout (it sets no
//! timer, so a silent socket was held forever) and sleeps a fixed second after any accept
//! error with a log line each time.

use super::admission::{Admission, Admitted, Refusal};
use super::head_errors::TypedHeadErrors;
use super::limits::{REFUSAL_TIMEOUT, REFUSING_MAX, effective_max_connections, nofile_soft_limit};
use super::rest::AppError;
use crate::config::NetLimits;
use crate::metrics::Metrics;
use crate::metrics::net::Timeout;
use axum::Router;
use axum::extract::State;
use axum::extract::ws::{
    CloseFrame, Message, WebSocketUpgrade, rejection::WebSocketUpgradeRejection,
};
use axum::http::{HeaderValue, header};
use axum::response::{IntoResponse, Response};
use hyper::server::conn::http1;
use hyper_util::rt::{TokioIo, TokioTimer};
use hyper_util::service::TowerToHyperService;
use posecast_proto::msg::{ErrorCode, ProtocolError};
use std::future::Future;
use std::io;
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio::net::TcpListener;
use tokio::sync::{Semaphore, watch};
use tracing::{debug, trace, warn};

/// WebSocket close code 1013, Try Again Later (RFC 6455 §7.4.1 via the IANA registry).
pub const CLOSE_TRY_AGAIN_LATER: u16 = 1013;

/// First pause after a failed `accept`; doubled after each further failure.
const ACCEPT_BACKOFF_MIN: Duration = Duration::from_millis(10);
/// Longest pause between two `accept`s while they keep failing.
const ACCEPT_BACKOFF_MAX: Duration = Duration::from_secs(1);
/// At most one warning about failing accepts this often.
const ACCEPT_WARN_EVERY: Duration = Duration::from_secs(60);

/// Serves `router` on `listener` until `signal` resolves; then stops accepting, lets every
/// HTTP connection finish its request in flight (idle ones close at once) and returns when
/// they are all gone. Upgraded websockets are not waited for here: they are the
/// [`crate::app::AppState`]'s connections.
///
/// # Errors
/// None today: accept failures are retried with back-off, never returned.
pub async fn serve(
    listener: TcpListener,
    router: Router,
    limits: NetLimits,
    metrics: Arc<Metrics>,
    signal: impl Future<Output = ()> + Send,
) -> io::Result<()> {
    let nofile = nofile_soft_limit();
    let max_total = effective_max_connections(limits.max_connections, nofile);
    if max_total < limits.max_connections {
        warn!(
            configured = limits.max_connections,
            max_connections = max_total,
            nofile,
            "connection cap lowered to fit the open-files limit"
        );
    }
    let admission = Admission::new(
        max_total,
        limits.max_connections_per_address,
        metrics.clone(),
    );
    let refusing = Arc::new(Semaphore::new(REFUSING_MAX));
    // Dropping `stop_tx` tells every connection to shut down gracefully; each connection
    // holds a `done_rx`, so `done_tx.closed()` resolves when the last one has ended.
    let (stop_tx, stop_rx) = watch::channel(());
    let (done_tx, done_rx) = watch::channel(());
    let mut backoff = ACCEPT_BACKOFF_MIN;
    let mut failing = false;
    // Out of descriptors, accepts fail and succeed in turns as connections come and go: one
    // warning per ACCEPT_WARN_EVERY with the count, not one per failure.
    let mut last_warning: Option<Instant> = None;
    let mut failures: u64 = 0;
    tokio::pin!(signal);
    loop {
        let accepted = tokio::select! {
            biased;
            () = &mut signal => break,
            accepted = listener.accept() => accepted,
        };
        let (stream, peer) = match accepted {
            Ok(accepted) => {
                if failing {
                    debug!("accepting connections again");
                    failing = false;
                }
                backoff = ACCEPT_BACKOFF_MIN;
                accepted
            }
            // The peer gave up between its SYN and our accept: nothing to do.
            Err(e) if is_connection_error(&e) => continue,
            Err(e) => {
                // Usually EMFILE/ENFILE. The connection stays in the listen backlog; retrying
                // at once would spin on the same error, so wait (longer each time) while the
                // existing connections go on and close. One warning per episode, not per try.
                metrics.net.accept_error();
                failing = true;
                failures += 1;
                if last_warning.is_none_or(|at| at.elapsed() >= ACCEPT_WARN_EVERY) {
                    warn!(
                        error = %e,
                        failures,
                        "accept failed; backing off (up to 1 s) while existing connections go on"
                    );
                    last_warning = Some(Instant::now());
                    failures = 0;
                } else {
                    debug!(error = %e, ?backoff, "accept still failing");
                }
                tokio::select! {
                    biased;
                    () = &mut signal => break,
                    () = tokio::time::sleep(backoff) => {}
                }
                backoff = (backoff * 2).min(ACCEPT_BACKOFF_MAX);
                continue;
            }
        };
        // Pose frames are small writes at 60 Hz: without TCP_NODELAY, Nagle holds each one
        // until the previous one is acknowledged, and delayed ACKs make that up to 40 ms.
        if let Err(e) = stream.set_nodelay(true) {
            debug!(error = %e, "cannot set TCP_NODELAY");
        }
        // Bounded kernel queue: see `NetLimits::tcp_notsent_lowat`.
        if limits.tcp_notsent_lowat > 0
            && let Err(e) =
                socket2::SockRef::from(&stream).set_tcp_notsent_lowat(limits.tcp_notsent_lowat)
        {
            debug!(error = %e, "cannot set TCP_NOTSENT_LOWAT");
        }
        match admission.try_admit(peer.ip()) {
            Ok(permit) => {
                trace!(%peer, "connection accepted");
                let greeter = permit.greeter();
                let socket_info = SocketInfo::of(&stream);
                let conn = Connection {
                    io: Admitted::with_permit(stream, permit),
                    // The client's address, for handlers that log it (`ConnectInfo`), and
                    // the slot a websocket's hello is reported to (eviction at the cap).
                    // The socket's descriptor too, for the kernel's figures of the connection
                    // (the adaptive rate's, `SocketInfo`).
                    router: router
                        .clone()
                        .layer(axum::Extension(axum::extract::ConnectInfo(peer)))
                        .layer(axum::Extension(greeter))
                        .layer(axum::Extension(socket_info)),
                    header_read_timeout: limits.header_read_timeout,
                    metrics: metrics.clone(),
                };
                tokio::spawn(conn.run(stop_rx.clone(), done_rx.clone()));
            }
            Err(why) => match refusing.clone().try_acquire_owned() {
                Ok(slot) => {
                    trace!(%peer, cap = why.label(), "refusing connection");
                    let wait = limits.header_read_timeout.min(REFUSAL_TIMEOUT);
                    tokio::spawn(refuse(Admitted::new(stream, slot), why, wait));
                }
                Err(_) => {
                    // Answering costs a descriptor for up to REFUSAL_TIMEOUT; under a flood
                    // the bound on those matters more than the answer.
                    metrics.net.unanswered();
                    drop(stream);
                }
            },
        }
    }
    drop(listener);
    drop(stop_tx);
    drop(done_rx);
    done_tx.closed().await;
    Ok(())
}

/// An accepted socket, for the kernel's figures of its connection (Linux: `TCP_INFO`), which
/// the adaptive rate follows ([`posecast_stream::pace::SocketFigures`]).
///
/// It holds the descriptor's number, not the descriptor: read it only while the connection's
/// websocket (which owns the socket) is alive — the websocket's reader loop does. A stale
/// number could name another socket by then; reading it is harmless to memory (the kernel
/// fills a buffer of the size given, or fails) but would give that socket's figures.
#[derive(Debug, Clone, Copy)]
pub struct SocketInfo {
    #[cfg(target_os = "linux")]
    fd: std::os::fd::RawFd,
}

impl SocketInfo {
    /// The accepted `stream`'s.
    #[must_use]
    pub fn of(stream: &tokio::net::TcpStream) -> Self {
        #[cfg(target_os = "linux")]
        {
            use std::os::fd::AsRawFd;
            Self {
                fd: stream.as_raw_fd(),
            }
        }
        #[cfg(not(target_os = "linux"))]
        {
            let _ = stream;
            Self {}
        }
    }

    /// The kernel's figures now, or `None` (not Linux, or the kernel refused): the adaptive
    /// rate then goes by round trips.
    #[must_use]
    pub fn figures(&self) -> Option<posecast_stream::pace::SocketFigures> {
        #[cfg(target_os = "linux")]
        {
            tcp_info::figures(self.fd)
        }
        #[cfg(not(target_os = "linux"))]
        {
            None
        }
    }
}

/// `getsockopt(TCP_INFO)`: the only unsafe code of the server (no safe wrapper of it in the
/// tree: socket2 and rustix have none), a plain read into a buffer of the struct's size.
#[cfg(target_os = "linux")]
#[allow(unsafe_code)]
mod tcp_info {
    use posecast_stream::pace::SocketFigures;
    use std::mem::{MaybeUninit, offset_of, size_of};

    pub(super) fn figures(fd: std::os::fd::RawFd) -> Option<SocketFigures> {
        // SAFETY: `tcp_info` is plain integers: all zeroes is a valid value.
        let mut info: libc::tcp_info = unsafe { MaybeUninit::zeroed().assume_init() };
        let mut len = size_of::<libc::tcp_info>() as libc::socklen_t;
        // SAFETY: the kernel writes at most `len` bytes to `info`, which holds that many, and
        // sets `len` to what it wrote. A descriptor that is not a TCP socket fails (no write).
        let rc = unsafe {
            libc::getsockopt(
                fd,
                libc::SOL_TCP,
                libc::TCP_INFO,
                (&raw mut info).cast(),
                &raw mut len,
            )
        };
        // Older kernels fill less of the struct: each field only if it was written.
        let has = |offset: usize, size: usize| rc == 0 && len as usize >= offset + size;
        if !has(offset_of!(libc::tcp_info, tcpi_notsent_bytes), 4) {
            return None;
        }
        let micros = |us: u32| std::time::Duration::from_micros(u64::from(us));
        let min_rtt = if has(offset_of!(libc::tcp_info, tcpi_min_rtt), 4) {
            micros(info.tcpi_min_rtt)
        } else {
            micros(info.tcpi_rtt)
        };
        Some(SocketFigures {
            acked: info.tcpi_bytes_acked,
            unsent: u64::from(info.tcpi_notsent_bytes),
            rtt: micros(info.tcpi_rtt),
            min_rtt,
        })
    }
}

fn is_connection_error(e: &io::Error) -> bool {
    matches!(
        e.kind(),
        io::ErrorKind::ConnectionRefused
            | io::ErrorKind::ConnectionAborted
            | io::ErrorKind::ConnectionReset
    )
}

/// One admitted HTTP connection.
struct Connection {
    io: Admitted,
    router: Router,
    header_read_timeout: Duration,
    metrics: Arc<Metrics>,
}

impl Connection {
    async fn run(self, mut stop: watch::Receiver<()>, done: watch::Receiver<()>) {
        let mut builder = http1::Builder::new();
        builder
            .timer(TokioTimer::new())
            .header_read_timeout(self.header_read_timeout);
        let service = TowerToHyperService::new(self.router);
        let conn = builder
            .serve_connection(TokioIo::new(TypedHeadErrors::new(self.io)), service)
            .with_upgrades();
        tokio::pin!(conn);
        let mut stopping = false;
        loop {
            tokio::select! {
                result = conn.as_mut() => {
                    if let Err(e) = result {
                        if e.is_timeout() {
                            self.metrics.net.timed_out(Timeout::Header);
                        }
                        trace!(error = %e, "HTTP connection ended");
                    }
                    break;
                }
                // `changed` fails once the sender is dropped: that is the signal, taken once.
                _ = stop.changed(), if !stopping => {
                    stopping = true;
                    conn.as_mut().graceful_shutdown();
                }
            }
        }
        drop(done);
    }
}

/// Answers a refused connection's one request, within `wait` (the header timeout, at most
/// [`REFUSAL_TIMEOUT`]): 503 `unavailable`
/// with `Retry-After`, or for a websocket upgrade the upgrade and then close 1013 — a browser's
/// WebSocket reports only close codes, never an HTTP status, so a dashboard could not tell
/// "busy" from "down" otherwise. The request is read first so the answer is not lost to a
/// reset (closing a socket with unread input sends RST, which can discard the response).
async fn refuse<G: Unpin + Send + 'static>(io: Admitted<G>, why: Refusal, wait: Duration) {
    let mut builder = http1::Builder::new();
    builder.timer(TokioTimer::new()).header_read_timeout(wait);
    let router = Router::new().fallback(refusal).with_state(why);
    let conn = builder
        .serve_connection(
            TokioIo::new(TypedHeadErrors::new(io)),
            TowerToHyperService::new(router),
        )
        .with_upgrades();
    if tokio::time::timeout(wait, conn).await.is_err() {
        trace!("refused connection did not finish in time; dropped");
    }
}

async fn refusal(
    State(why): State<Refusal>,
    upgrade: Result<WebSocketUpgrade, WebSocketUpgradeRejection>,
) -> Response {
    let message = match why {
        Refusal::Global => "the server holds as many connections as it allows; try again later",
        Refusal::PerAddress => {
            "your address holds as many connections as the server allows one address; try again later"
        }
    };
    match upgrade {
        Ok(ws) => ws.read_buffer_size(1024).write_buffer_size(0).on_upgrade(
            move |mut socket| async move {
                let close = socket.send(Message::Close(Some(CloseFrame {
                    code: CLOSE_TRY_AGAIN_LATER,
                    reason: "try again later".into(),
                })));
                // A peer that does not read must not hold the slot: the close is best effort.
                tokio::time::timeout(REFUSAL_TIMEOUT, close).await.ok();
                trace!(message, "websocket refused with 1013");
            },
        ),
        Err(_) => {
            let mut response =
                AppError(ProtocolError::new(ErrorCode::Unavailable, message)).into_response();
            let headers = response.headers_mut();
            headers.insert(header::RETRY_AFTER, HeaderValue::from_static("1"));
            // One answer per refused connection: hyper closes after a response that says so.
            // (Not `keep_alive(false)` on the builder: that also forbids the upgrade above.)
            headers.insert(header::CONNECTION, HeaderValue::from_static("close"));
            response
        }
    }
}
