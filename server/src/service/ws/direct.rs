//! A websocket over its accepted socket, written directly (issue 38).
//!
//! The handshake is axum's checks and answer; after the upgrade the session keeps the TCP
//! socket itself instead of axum's `WebSocket`:
//! - **writes** go through the connection's outbox straight into the socket, from whatever
//!   queued them — the tick's fan-out for frames — as websocket frames built once
//!   ([`posecast_stream::direct`]). No task wakes per frame, no lock is shared with the reader,
//!   and a frame's bytes are not copied per connection. The writer task runs only while the
//!   socket is full, and to close.
//! - **reads** go through tungstenite as before (the same limits, close codes and errors), over
//!   a read side whose own writes are dropped: the session answers pings and close frames
//!   through the outbox instead, so they stay in order with everything else.

use super::{Writer, serve_parts};
use crate::app::AppState;
use crate::service::admission::{Admitted, Greeter, Shared, Slot};
use crate::service::head_errors::TypedHeadErrors;
use crate::service::listener::SocketInfo;
use axum::extract::ws::{CloseFrame, Message, Utf8Bytes};
use axum::http::{HeaderValue, StatusCode, header};
use axum::response::Response;
use axum_tokio_tungstenite::WebSocketStream;
use axum_tungstenite as ts;
use bytes::Bytes;
use futures_util::StreamExt;
use hyper_util::rt::TokioIo;
use posecast_proto::msg::MAX_CLIENT_MESSAGE_BYTES;
use posecast_stream::direct::{DirectSocket, DirectWrite, run_direct};
use posecast_stream::outbox::Outbox;
use std::io::{self, IoSlice};
use std::net::SocketAddr;
use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context, Poll};
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::TcpStream;
use tracing::warn;

/// Answers a checked upgrade request (101, `Sec-WebSocket-Accept` from `key`) and serves the
/// session on the upgraded socket once hyper hands it over.
pub fn accept(
    on_upgrade: hyper::upgrade::OnUpgrade,
    key: &HeaderValue,
    state: Arc<AppState>,
    peer: Option<SocketAddr>,
    greeter: Option<Greeter>,
    tcp: Option<SocketInfo>,
) -> Response {
    tokio::spawn(async move {
        let Ok(upgraded) = on_upgrade.await else {
            return;
        };
        match upgraded.downcast::<TokioIo<TypedHeadErrors<Admitted>>>() {
            Ok(parts) => {
                let admitted = parts.io.into_inner().into_inner();
                let Some((stream, shared)) = admitted.into_shared() else {
                    return;
                };
                serve(stream, shared, parts.read_buf, state, peer, greeter, tcp).await;
            }
            Err(_) => warn!("an upgraded websocket was not the listener's socket; dropped"),
        }
    });
    let mut response = Response::new(axum::body::Body::empty());
    *response.status_mut() = StatusCode::SWITCHING_PROTOCOLS;
    let headers = response.headers_mut();
    headers.insert(header::CONNECTION, HeaderValue::from_static("upgrade"));
    headers.insert(header::UPGRADE, HeaderValue::from_static("websocket"));
    headers.insert(header::SEC_WEBSOCKET_ACCEPT, accept_key(key.as_bytes()));
    response
}

/// RFC 6455 §4.2.2: base64 of the SHA-1 of the client's key and the protocol's GUID.
fn accept_key(key: &[u8]) -> HeaderValue {
    use base64::Engine as _;
    use sha1::{Digest, Sha1};
    let mut sha1 = Sha1::default();
    sha1.update(key);
    sha1.update(b"258EAFA5-E914-47DA-95CA-C5AB0DC85B11");
    let b64 = base64::engine::general_purpose::STANDARD.encode(sha1.finalize());
    HeaderValue::from_str(&b64).unwrap_or_else(|_| HeaderValue::from_static(""))
}

async fn serve(
    stream: Arc<TcpStream>,
    shared: Shared,
    read_buf: Bytes,
    state: Arc<AppState>,
    peer: Option<SocketAddr>,
    greeter: Option<Greeter>,
    tcp: Option<SocketInfo>,
) {
    let socket = Arc::new(Socket {
        stream: stream.clone(),
        eviction: shared.eviction(),
    });
    let config = ts::protocol::WebSocketConfig::default()
        .max_message_size(Some(MAX_CLIENT_MESSAGE_BYTES))
        .max_frame_size(Some(MAX_CLIENT_MESSAGE_BYTES))
        .read_buffer_size(super::READ_BUFFER_BYTES)
        .write_buffer_size(0);
    let reader = ReadSide { stream, shared };
    let ws = WebSocketStream::from_partially_read(
        reader,
        read_buf.to_vec(),
        ts::protocol::Role::Server,
        Some(config),
    )
    .await;
    let outbox = Arc::new(Outbox::new());
    outbox.attach_direct(socket.clone(), state.metrics.clone());
    let writer: Writer = {
        let outbox = outbox.clone();
        Box::pin(async move { run_direct(&outbox, &*socket).await })
    };
    let answers = outbox.clone();
    let received = ws.filter_map(move |read| {
        std::future::ready(match read {
            Ok(m) => received(m, &answers).map(Ok),
            Err(e) => Some(Err(axum::Error::new(e))),
        })
    });
    serve_parts(writer, received, outbox, state, peer, greeter, tcp).await;
}

/// A received message as axum's, answering what tungstenite would have answered itself: a ping
/// with its pong, a close with its close (the same code).
fn received(m: ts::Message, outbox: &Outbox) -> Option<Message> {
    Some(match m {
        ts::Message::Text(t) => Message::Text(Utf8Bytes::from(t.as_str())),
        ts::Message::Binary(b) => Message::Binary(b),
        ts::Message::Ping(b) => {
            outbox.push_control(Message::Pong(b.clone()));
            Message::Ping(b)
        }
        ts::Message::Pong(b) => Message::Pong(b),
        ts::Message::Close(c) => {
            let c = c.map(|c| CloseFrame {
                code: c.code.into(),
                reason: Utf8Bytes::from(c.reason.as_str()),
            });
            outbox.close_with(c.as_ref().map_or(1000, |c| c.code), "");
            Message::Close(c)
        }
        ts::Message::Frame(_) => return None,
    })
}

/// The socket as the outbox writes it: fails once the connection is evicted.
#[derive(Debug)]
struct Socket {
    stream: Arc<TcpStream>,
    eviction: Option<Arc<Slot>>,
}

impl DirectWrite for Socket {
    fn try_write_vectored(&self, bufs: &[IoSlice<'_>]) -> io::Result<usize> {
        if let Some(e) = &self.eviction {
            e.check()?;
        }
        // `sendmsg`, not `writev`: the socket's own call skips the file layer (a tenth of
        // the server's kernel time per frame in a profile at 1,000 viewers). `try_io` keeps
        // tokio's readiness right (cleared on `WouldBlock`, so `writable` waits).
        self.stream.try_io(tokio::io::Interest::WRITABLE, || {
            socket2::SockRef::from(&*self.stream).send_vectored(bufs)
        })
    }
}

impl DirectSocket for Socket {
    fn writable(&self) -> impl Future<Output = io::Result<()>> + Send {
        self.stream.writable()
    }
}

/// The socket as tungstenite reads it. What tungstenite writes (its own answers to pings and
/// close frames) is dropped: [`received`] answers through the outbox.
struct ReadSide {
    stream: Arc<TcpStream>,
    shared: Shared,
}

impl AsyncRead for ReadSide {
    fn poll_read(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        self.shared.before_read(cx.waker())?;
        loop {
            std::task::ready!(self.stream.poll_read_ready(cx))?;
            match self.stream.try_read(buf.initialize_unfilled()) {
                Ok(n) => {
                    if n > 0 {
                        self.shared.heard();
                    }
                    buf.advance(n);
                    return Poll::Ready(Ok(()));
                }
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => {}
                Err(e) => return Poll::Ready(Err(e)),
            }
        }
    }
}

impl AsyncWrite for ReadSide {
    fn poll_write(
        self: Pin<&mut Self>,
        _: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        Poll::Ready(Ok(buf.len()))
    }

    fn poll_flush(self: Pin<&mut Self>, _: &mut Context<'_>) -> Poll<io::Result<()>> {
        Poll::Ready(Ok(()))
    }

    fn poll_shutdown(self: Pin<&mut Self>, _: &mut Context<'_>) -> Poll<io::Result<()>> {
        Poll::Ready(Ok(()))
    }
}

#[cfg(test)]
mod tests {
    /// RFC 6455 §1.3's worked example.
    #[test]
    fn the_accept_key_is_the_rfcs() {
        assert_eq!(
            super::accept_key(b"dGhlIHNhbXBsZSBub25jZQ=="),
            "s3pPLMBiTxaQ9kYGzzhZRbK+xOo="
        );
    }
}
