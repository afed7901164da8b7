//! WebTransport (HTTP/3 over QUIC) beside the websocket (`--quic-listen`, issue 31): the same
//! protocol, with frames as datagrams ([`posecast_proto::quic`] has the framing).
//!
//! - **The endpoint** listens on one UDP port with the certificate of `--quic-cert` and
//!   `--quic-key`, or a self-signed one made at start and valid 14 days — what browsers accept
//!   by its hash (`serverCertificateHashes`) — whose SHA-256 `GET /api/quic` publishes.
//! - **A session** is a websocket session ([`super::ws::serve_parts`]) over the client's first
//!   bidirectional stream: every message framed as kind, length and payload, in order. Its
//!   outbox is a datagram one: frames are wire v1, each in one datagram — a larger one cut by
//!   avatar into frames that each fit and decode alone (an avatar's chunk larger than a
//!   datagram goes on the stream) — and a delta goes out only against a keyframe the client
//!   acknowledged, every avatar of it, with datagrams; until then the newest keyframe goes
//!   again before each delta. A lost datagram costs its own tick. QUIC's congestion
//!   control (`--quic-congestion`: CUBIC, or BBR) paces what is sent.

use super::admission::{Admission, Greeter};
use super::ws;
use crate::app::{AppState, QuicInfo};
use crate::config::{QUIC_RETRY_LOAD, QuicCongestion, QuicRetry};
use crate::metrics::Metrics;
use axum::extract::ws::Message;
use axum_tungstenite::error::{CapacityError, Error as WsError, ProtocolError as WsProtocol};
use futures_util::{Sink, Stream, StreamExt};
use posecast_proto::frame2;
use posecast_proto::msg::MAX_CLIENT_MESSAGE_BYTES;
use posecast_proto::quic as wire;
use posecast_stream::outbox::Outbox;
use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::Duration;
use tokio::task::JoinHandle;
use tracing::{debug, info};
use wtransport::endpoint::IncomingSession;
use wtransport::tls::Sha256DigestFmt;
use wtransport::{Connection, Endpoint, Identity, RecvStream, SendStream, ServerConfig};

/// QUIC's datagram send buffer (quinn's default, set explicitly: [`send_datagrams`] reads
/// what waits in it from the space left).
const DATAGRAM_BUFFER: usize = 1 << 20;

/// Datagrams (of the largest size) waiting in QUIC's send buffer past which a new frame is
/// superseded rather than queued: a burst (a keyframe and its parts, a joiner's frames) fits,
/// a path that cannot keep up does not build a backlog. (Superseding a frame as soon as an
/// earlier write's datagrams waited 4 ms lost deltas on a machine under CPU load, where one
/// write's datagrams can be that far apart.)
const SUPERSEDED_AT: usize = 8;

/// Wire v2 frames (protocol version 8) of the size of this one waiting in QUIC's send buffer
/// past which it is superseded (see [`SUPERSEDED_AT`]).
const V2_SUPERSEDED_AT: usize = 2;

/// How long a client may take to complete the QUIC and WebTransport handshakes.
const HANDSHAKE: Duration = Duration::from_secs(10);

/// The QUIC application close code of a session evicted at the connection cap: the
/// websocket's close code for it, 1013 (try again later).
const EVICTED: u32 = 1013;

/// Days the self-signed certificate is valid: browsers accept a certificate by its hash only
/// when it is valid for at most 14 days.
const SELF_SIGNED_DAYS: u32 = 14;

/// The controller factory of `choice`.
fn congestion(
    choice: QuicCongestion,
) -> Arc<dyn wtransport::quinn::congestion::ControllerFactory + Send + Sync> {
    use wtransport::quinn::congestion::{BbrConfig, CubicConfig, NewRenoConfig};
    match choice {
        QuicCongestion::Bbr => Arc::new(BbrConfig::default()),
        QuicCongestion::Cubic => Arc::new(CubicConfig::default()),
        QuicCongestion::NewReno => Arc::new(NewRenoConfig::default()),
    }
}

fn io_error(what: String) -> std::io::Error {
    std::io::Error::other(what)
}

/// Binds the endpoint of `--quic-listen` (none: `Ok(None)`) and starts accepting sessions;
/// returns the accept loop's task.
///
/// # Errors
/// The certificate files cannot be read, or the UDP address cannot be bound.
pub async fn start(state: &Arc<AppState>) -> std::io::Result<Option<JoinHandle<()>>> {
    let Some(addr) = state.config.quic_listen else {
        return Ok(None);
    };
    let (identity, self_signed) = match &state.config.quic_identity {
        Some((cert, key)) => {
            let identity = Identity::load_pemfiles(cert, key).await.map_err(|e| {
                io_error(format!(
                    "cannot read --quic-cert {} / --quic-key {}: {e}",
                    cert.display(),
                    key.display()
                ))
            })?;
            (identity, false)
        }
        None => {
            let mut names = vec![
                "localhost".to_owned(),
                "127.0.0.1".to_owned(),
                "::1".to_owned(),
            ];
            if !addr.ip().is_unspecified() && !addr.ip().is_loopback() {
                names.push(addr.ip().to_string());
            }
            let identity = Identity::self_signed_builder()
                .subject_alt_names(names)
                .from_now_utc()
                .validity_days(SELF_SIGNED_DAYS)
                .build()
                .map_err(|e| io_error(format!("cannot make a certificate: {e}")))?;
            (identity, true)
        }
    };
    let hash = identity
        .certificate_chain()
        .as_slice()
        .first()
        .map(|c| c.hash().fmt(Sha256DigestFmt::DottedHex).replace(':', ""))
        .ok_or_else(|| io_error("the certificate chain is empty".into()))?;
    let mut transport = wtransport::config::QuicTransportConfig::default();
    transport.datagram_send_buffer_size(DATAGRAM_BUFFER);
    transport.congestion_controller_factory(congestion(state.config.quic_congestion));
    // Datagrams stay within the path's initial MTU (1,200 bytes, which every QUIC path
    // carries): with path MTU discovery on, a frame cut at a larger size found later is
    // dropped by quinn, unsent, when it suspects a black hole (a few packets declared lost, as
    // on a busy host) and falls back — one avatar's tick lost without the network losing
    // anything.
    transport.mtu_discovery_config(None);
    let config = ServerConfig::builder()
        .with_bind_address(addr)
        .with_custom_transport(identity, transport)
        .keep_alive_interval(Some(Duration::from_secs(3)))
        .max_idle_timeout(Some(state.config.net.ws_idle_timeout))
        .map_err(|e| io_error(format!("idle timeout: {e}")))?
        .build();
    let endpoint = Endpoint::server(config)
        .map_err(|e| io_error(format!("cannot listen on UDP {addr}: {e}")))?;
    let bound = endpoint.local_addr()?;
    info!(udp = %bound, cert_sha256 = %hash, self_signed, "WebTransport listening");
    state
        .quic
        .set(QuicInfo {
            port: bound.port(),
            cert_sha256: hash,
            self_signed,
        })
        .ok();
    let state = state.clone();
    // Sessions count under the websocket's caps (`--max-connections`,
    // `--max-connections-per-address`), apart from the websockets, by the same rules: past a
    // cap a session is answered `429 Too Many Requests` before it is established, unless one
    // that has not said hello, or an anonymous one idle for a while, can make way.
    let net = &state.config.net;
    let admission = Admission::for_quic(
        net.max_connections,
        net.max_connections_per_address,
        state.metrics.clone(),
    );
    let handshakes = Arc::new(AtomicUsize::new(0));
    Ok(Some(tokio::spawn(async move {
        loop {
            let incoming = endpoint.accept().await;
            if needs_retry(
                state.config.quic_retry,
                handshakes.load(Ordering::Relaxed),
                incoming.remote_address_validated(),
            ) {
                state.metrics.quic.retried();
                incoming.retry();
                continue;
            }
            let handshake = Handshake::begin(&handshakes);
            tokio::spawn(session(
                state.clone(),
                admission.clone(),
                incoming,
                handshake,
            ));
        }
    })))
}

/// Whether a new client whose address is (or is not) `validated` gets a Retry with
/// `in_progress` handshakes under way (`--quic-retry`).
fn needs_retry(policy: QuicRetry, in_progress: usize, validated: bool) -> bool {
    !validated
        && match policy {
            QuicRetry::Never => false,
            QuicRetry::UnderLoad => in_progress >= QUIC_RETRY_LOAD,
            QuicRetry::Always => true,
        }
}

/// A handshake in progress, counted until it ends either way (dropped).
struct Handshake(Arc<AtomicUsize>);

impl Handshake {
    fn begin(count: &Arc<AtomicUsize>) -> Self {
        count.fetch_add(1, Ordering::Relaxed);
        Self(count.clone())
    }
}

impl Drop for Handshake {
    fn drop(&mut self) {
        self.0.fetch_sub(1, Ordering::Relaxed);
    }
}

/// One WebTransport session, from its handshake to its end.
async fn session(
    state: Arc<AppState>,
    admission: Arc<Admission>,
    incoming: IncomingSession,
    handshake: Handshake,
) {
    let Ok(Ok(request)) = tokio::time::timeout(HANDSHAKE, incoming).await else {
        debug!("a QUIC handshake failed or timed out");
        return;
    };
    drop(handshake);
    let peer = request.remote_address();
    let Ok(permit) = admission.try_admit(peer.ip()) else {
        debug!(%peer, "a WebTransport session over a connection cap: refused");
        request.too_many_requests().await;
        return;
    };
    let greeter = permit.greeter();
    let Ok(Ok(conn)) = tokio::time::timeout(HANDSHAKE, request.accept()).await else {
        debug!(%peer, "a WebTransport session was not established");
        return;
    };
    // The client opens its stream at once, as a websocket client says hello.
    let opened = tokio::time::timeout(state.config.net.hello_timeout, conn.accept_bi()).await;
    let Ok(Ok((send, recv))) = opened else {
        conn.close(1u32.into(), b"no stream opened");
        return;
    };
    state.metrics.quic.session();
    let outbox = Arc::new(Outbox::for_datagrams());
    let acks = tokio::spawn(read_acks(
        conn.clone(),
        outbox.clone(),
        state.metrics.clone(),
        greeter.clone(),
    ));
    // Evicted to admit a newcomer: the connection closes, which ends the session's reads and
    // writes wherever they are.
    let eviction = {
        let (conn, greeter) = (conn.clone(), greeter.clone());
        tokio::spawn(async move {
            greeter.evicted().await;
            debug!(%peer, "a WebTransport session evicted at the connection cap");
            conn.close(
                EVICTED.into(),
                b"evicted: the server is at its connection cap",
            );
        })
    };
    // Fused: the session reads on after the end (its closing linger).
    let stream = Box::pin(received(recv, greeter.clone()).fuse());
    let sink = Box::pin(sent(
        conn.clone(),
        send,
        outbox.clone(),
        state.metrics.clone(),
    ));
    let writer = ws::sink_writer(&outbox, sink, &state);
    ws::serve_parts(
        writer,
        stream,
        outbox,
        state,
        Some(peer),
        Some(greeter),
        None,
    )
    .await;
    eviction.abort();
    acks.abort();
    drop(permit);
    conn.close(0u32.into(), b"");
}

/// Bytes of datagrams waiting in `conn`'s send buffer (quinn also counts one datagram's
/// bookkeeping when it is empty: less than [`BOOKKEEPING`]).
fn datagrams_waiting(conn: &Connection) -> usize {
    let space = conn.quic_connection().datagram_send_buffer_space();
    DATAGRAM_BUFFER
        .saturating_sub(space)
        .saturating_sub(BOOKKEEPING)
}

/// More than quinn's bookkeeping of one datagram in its send buffer.
const BOOKKEEPING: usize = 64;

/// Keyframe and frame acknowledgements the client sends as datagrams; anything else is
/// ignored.
async fn read_acks(conn: Connection, outbox: Arc<Outbox>, metrics: Arc<Metrics>, greeter: Greeter) {
    while let Ok(datagram) = conn.receive_datagram().await {
        let payload = datagram.payload();
        if let Some(ack) = wire::read_key_ack(&payload) {
            greeter.heard();
            metrics.quic.key_ack();
            outbox.ack_key(ack.scene_num, ack.seq, &ack.avatars);
        } else if let Some(ack) = wire::read_frame_ack(&payload) {
            greeter.heard();
            metrics.quic.frame_ack();
            outbox.ack_frame(ack.scene_num, ack.seq, &ack.avatars);
        } else {
            metrics.quic.ignored();
        }
    }
}

/// The messages of the client's stream, until it ends. A message that breaks the framing
/// ends it with the error a websocket would give (too large, not UTF-8, an unknown kind).
/// Each message marks the session heard (`greeter`: it is not idle).
fn received(
    recv: RecvStream,
    greeter: Greeter,
) -> impl Stream<Item = Result<Message, axum::Error>> + Send {
    futures_util::stream::unfold(Some(recv), move |recv| {
        let greeter = greeter.clone();
        async move {
            let mut recv = recv?;
            let mut header = [0u8; wire::STREAM_HEADER];
            recv.read_exact(&mut header).await.ok()?;
            greeter.heard();
            let (kind, len) = wire::read_header(header);
            let fail = |e: WsError| Some((Err(axum::Error::new(e)), None));
            if len > MAX_CLIENT_MESSAGE_BYTES {
                return fail(WsError::Capacity(CapacityError::MessageTooLong {
                    size: len,
                    max_size: MAX_CLIENT_MESSAGE_BYTES,
                }));
            }
            let mut payload = vec![0u8; len];
            recv.read_exact(&mut payload).await.ok()?;
            let message = match kind {
                wire::TEXT => match String::from_utf8(payload) {
                    Ok(text) => Message::Text(text.into()),
                    Err(e) => return fail(WsError::Utf8(e.to_string())),
                },
                wire::BINARY => Message::Binary(payload.into()),
                wire::PING => Message::Ping(payload.into()),
                wire::PONG => Message::Pong(payload.into()),
                wire::CLOSE => Message::Close(None),
                other => return fail(WsError::Protocol(WsProtocol::InvalidOpcode(other))),
            };
            Some((Ok(message), Some(recv)))
        }
    })
}

/// Sends a frame as datagrams: whole when it fits one, else cut by avatar into frames that
/// each fit (a keyframe cut so is held by the client once it acknowledged every avatar of it).
/// Returns what could not go as a datagram (a frame of a peer without datagrams, an avatar's
/// chunk larger than a datagram, a malformed frame), for the stream.
fn send_datagrams(
    conn: &Connection,
    outbox: &Outbox,
    metrics: &Metrics,
    frame: &[u8],
) -> Vec<Vec<u8>> {
    let Some(max) = conn.max_datagram_size() else {
        return vec![frame.to_vec()];
    };
    // Newest frame wins, as in a websocket's outbox: when QUIC's congestion control holds
    // more than a frame or two waiting, the path is full and this frame is superseded before
    // it could leave (a lost keyframe is sent again before the next delta). Wire v2 frames
    // (protocol version 8) are a few hundred bytes: two of them waiting is a full path, where
    // [`SUPERSEDED_AT`] datagrams of the largest size would be a second of them queued.
    let waiting = datagrams_waiting(conn);
    let full = if frame.first() == Some(&frame2::MAGIC) {
        waiting > V2_SUPERSEDED_AT * frame.len().min(max)
    } else {
        waiting > SUPERSEDED_AT * max
    };
    if full {
        metrics.quic.superseded();
        outbox.dropped_by_link();
        return Vec::new();
    }
    if frame.first() == Some(&frame2::MAGIC) {
        return send_v2_datagrams(conn, outbox, metrics, frame, max);
    }
    if frame.len() <= max {
        if conn.send_datagram(frame).is_ok() {
            metrics.quic.datagram(frame.len());
            return Vec::new();
        }
        return vec![frame.to_vec()];
    }
    let parts = match posecast_proto::frame::split_by_avatar(frame, max) {
        Ok(parts) if parts.len() > 1 => parts,
        _ => return vec![frame.to_vec()],
    };
    metrics.quic.split();
    if let Ok((header, _)) = posecast_proto::frame::read_header(frame)
        && header.kind == posecast_proto::frame::FrameKind::Key
    {
        let avatars: Vec<u32> = parts.iter().flat_map(|(_, a)| a.iter().copied()).collect();
        outbox.sent_split_key(header.scene_num, header.seq, &avatars);
    }
    let mut rest = Vec::new();
    for (part, _) in parts {
        if part.len() <= max && conn.send_datagram(&part).is_ok() {
            metrics.quic.datagram(part.len());
        } else {
            rest.push(part);
        }
    }
    rest
}

/// [`send_datagrams`] for a wire v2 frame (protocol version 8: a keyframe or a delta naming
/// the frames it refers to), whole or cut by avatar, recorded as sent so that its
/// acknowledgements make it a frame later deltas may name.
fn send_v2_datagrams(
    conn: &Connection,
    outbox: &Outbox,
    metrics: &Metrics,
    frame: &[u8],
    max: usize,
) -> Vec<Vec<u8>> {
    let (Ok((header, _)), Ok(parts)) = (
        frame2::read_header(frame),
        frame2::split_by_avatar(frame, max),
    ) else {
        return vec![frame.to_vec()];
    };
    let key = header.kind == posecast_proto::frame::FrameKind::Key;
    if parts.len() > 1 {
        metrics.quic.split();
        let avatars: Vec<u32> = parts.iter().flat_map(|(_, a)| a.iter().copied()).collect();
        outbox.datagram_frame_sent(header.scene_num, header.seq, key, Some(&avatars));
    } else {
        outbox.datagram_frame_sent(header.scene_num, header.seq, key, None);
    }
    let mut rest = Vec::new();
    for (part, _) in parts {
        if part.len() <= max && conn.send_datagram(&part).is_ok() {
            metrics.quic.datagram(part.len());
        } else {
            rest.push(part);
        }
    }
    rest
}

/// Sends the session's messages: frames as datagrams ([`send_datagrams`]), everything else
/// (and what does not fit a datagram) on the stream, in order.
fn sent(
    conn: Connection,
    send: SendStream,
    outbox: Arc<Outbox>,
    metrics: Arc<Metrics>,
) -> impl Sink<Message> + Send {
    futures_util::sink::unfold(
        (conn, send, outbox, metrics),
        |(conn, mut send, outbox, metrics), message: Message| async move {
            let (kind, payload): (u8, Vec<u8>) = match message {
                Message::Binary(frame) => {
                    let mut rest = send_datagrams(&conn, &outbox, &metrics, &frame);
                    let Some(last) = rest.pop() else {
                        return Ok((conn, send, outbox, metrics));
                    };
                    for part in rest {
                        metrics.quic.on_stream();
                        send.write_all(&wire::frame_message(wire::BINARY, &part))
                            .await
                            .map_err(|e| axum::Error::new(e.to_string()))?;
                    }
                    metrics.quic.on_stream();
                    (wire::BINARY, last)
                }
                Message::Text(text) => (wire::TEXT, text.as_bytes().to_vec()),
                Message::Ping(p) => (wire::PING, p.to_vec()),
                Message::Pong(p) => (wire::PONG, p.to_vec()),
                Message::Close(frame) => {
                    let mut payload = Vec::new();
                    if let Some(f) = frame {
                        payload.extend_from_slice(&f.code.to_le_bytes());
                        payload.extend_from_slice(f.reason.as_bytes());
                    }
                    (wire::CLOSE, payload)
                }
            };
            send.write_all(&wire::frame_message(kind, &payload))
                .await
                .map_err(|e| axum::Error::new(e.to_string()))?;
            if kind == wire::CLOSE {
                send.finish().await.ok();
            }
            Ok::<_, axum::Error>((conn, send, outbox, metrics))
        },
    )
}

#[cfg(test)]
mod retry_tests {
    use super::*;

    /// `--quic-retry`: never, from the load threshold on, or always — and never for an
    /// address already proven (a client answering a Retry).
    #[test]
    fn a_retry_is_asked_by_policy_and_load_of_unproven_addresses_only() {
        let busy = QUIC_RETRY_LOAD;
        assert!(!needs_retry(QuicRetry::Never, busy * 10, false));
        assert!(!needs_retry(QuicRetry::UnderLoad, busy - 1, false));
        assert!(needs_retry(QuicRetry::UnderLoad, busy, false));
        assert!(needs_retry(QuicRetry::Always, 0, false));
        for policy in [QuicRetry::Never, QuicRetry::UnderLoad, QuicRetry::Always] {
            assert!(!needs_retry(policy, busy * 10, true), "{policy:?}");
        }
        // The count follows handshakes begun and ended.
        let count = Arc::new(AtomicUsize::new(0));
        let (a, b) = (Handshake::begin(&count), Handshake::begin(&count));
        assert_eq!(count.load(Ordering::Relaxed), 2);
        drop(a);
        drop(b);
        assert_eq!(count.load(Ordering::Relaxed), 0);
    }
}
