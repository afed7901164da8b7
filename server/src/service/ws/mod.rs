//! One websocket connection: a reader that parses client messages and a writer that drains the
//! connection's [`Outbox`]. Bad input gets a typed error and the connection goes on; the
//! connection closes, with the close code `proto/PROTOCOL.md` lists, only on a first message that
//! is not a valid `hello` (1008), a wrong protocol version (1008), an oversized message (1009),
//! invalid UTF-8 (1007), a websocket protocol violation (1002), a client that stops reading
//! (1008), no hello in time or nothing heard for the idle timeout (1008, see
//! [`super::limits::NetLimits`]), server shutdown (1001) or an anonymous hello when anonymous
//! connections hold all but the authenticated clients' headroom of the cap (1013,
//! [`super::admission::Admission::greet`]). Nothing a client sends can affect another
//! connection.

use crate::app::AppState;
use crate::auth::Caller;
use crate::control;
use crate::live::{Drives, JsonPose};
use crate::metrics::net::Timeout;
use crate::scene::unix_micros;
use crate::service::admission::Greeter;
use crate::service::listener::{CLOSE_TRY_AGAIN_LATER, SocketInfo};
use crate::service::ws_liveness::{Due, Liveness};
use axum::extract::ws::{Message, WebSocket, close_code};
use futures_util::{Sink, Stream, StreamExt};
use posecast_core::error::Error;
use posecast_core::quota::{TokenBucket, rate_limited};
use posecast_proto::command::{CommandResult, DriveVia, Driver};
use posecast_proto::msg::{
    ClientMsg, Encoding, ErrorCode, MAX_CLIENT_MESSAGE_BYTES, PROTOCOL_VERSION, ProtocolError,
    SUPPORTED_VERSIONS, SceneId, ServerMsg,
};
use posecast_proto::subset::JointSet;
use posecast_stream::feed::{Subscriber, text};
use posecast_stream::outbox::Outbox;
use posecast_stream::pace::Change;
use posecast_stream::writer::run_writer;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;
use tokio::time::Instant;
use tracing::{Instrument, debug, info, info_span};

pub mod direct;

/// How long the reader waits for the client's answering close frame once the writer has sent
/// the server's. The closing handshake is polite, but a client that never answers must not
/// keep its session (and a server shutdown) waiting.
const CLOSE_LINGER: Duration = Duration::from_secs(1);

/// tungstenite's read buffer per connection. Its default, 128 KiB, is zero-filled up front,
/// so every idle websocket held 128 KiB of resident memory for messages of a few hundred
/// bytes. A larger message grows the buffer as it arrives (up to the 64 KiB message bound).
pub const READ_BUFFER_BYTES: usize = 4 << 10;

/// Bytes tungstenite gathers before writing to the socket (default 128 KiB). The writer
/// flushes after each batch anyway, so this only merges the messages of one batch into
/// fewer writes; the buffer grows to hold one message when a message is larger.
pub const WRITE_BUFFER_BYTES: usize = 8 << 10;

/// Serves one upgraded websocket from `peer` until either side closes; `tcp` is its accepted
/// socket, whose kernel figures the adaptive rate reads with the round trips (`None`: round
/// trips alone).
pub async fn serve(
    socket: WebSocket,
    state: Arc<AppState>,
    peer: Option<SocketAddr>,
    greeter: Option<Greeter>,
    tcp: Option<SocketInfo>,
) {
    serve_paced(socket, state, peer, greeter, tcp).await;
}

/// [`serve`] over any websocket-shaped transport: a stream of received messages and a sink for
/// sent ones (axum's [`WebSocket`] in the server; channels in the unit tests below).
/// `greeter` is the connection's slot under the caps (none in the unit tests): the hello
/// tells it whether the client is authenticated, which decides whether it may be evicted.
#[cfg(test)]
pub async fn serve_on<S>(
    socket: S,
    state: Arc<AppState>,
    peer: Option<SocketAddr>,
    greeter: Option<Greeter>,
) where
    S: Stream<Item = Result<Message, axum::Error>> + Sink<Message> + Send + 'static,
{
    serve_paced(socket, state, peer, greeter, None).await;
}

/// [`serve_on`], with the accepted socket whose kernel figures pace the frames, if known.
async fn serve_paced<S>(
    socket: S,
    state: Arc<AppState>,
    peer: Option<SocketAddr>,
    greeter: Option<Greeter>,
    tcp: Option<SocketInfo>,
) where
    S: Stream<Item = Result<Message, axum::Error>> + Sink<Message> + Send + 'static,
{
    let (sink, stream) = socket.split();
    let outbox = Arc::new(Outbox::new());
    let writer = sink_writer(&outbox, sink, &state);
    serve_parts(writer, stream, outbox, state, peer, greeter, tcp).await;
}

/// A connection's writer task: drains `outbox` into `sink` ([`run_writer`]).
pub(super) fn sink_writer<Si>(outbox: &Arc<Outbox>, sink: Si, state: &AppState) -> Writer
where
    Si: Sink<Message> + Unpin + Send + 'static,
{
    let outbox = outbox.clone();
    let metrics = state.metrics.clone();
    Box::pin(async move { run_writer(&outbox, sink, &*metrics).await })
}

/// The task that writes a connection's outbox out (spawned by [`serve_parts`]).
pub(super) type Writer = std::pin::Pin<Box<dyn Future<Output = ()> + Send>>;

/// A session of the protocol over a stream of received messages and a `writer` that sends
/// what `outbox` holds (a websocket's halves, its socket written directly: [`direct`], or a
/// WebTransport session's stream and datagrams: `super::quic`).
pub(super) async fn serve_parts<St>(
    writer: Writer,
    mut stream: St,
    outbox: Arc<Outbox>,
    state: Arc<AppState>,
    peer: Option<SocketAddr>,
    greeter: Option<Greeter>,
    tcp: Option<SocketInfo>,
) where
    St: Stream<Item = Result<Message, axum::Error>> + Unpin + Send,
{
    // A WebTransport session is paced by QUIC, not by the adaptive rate: it stays off the
    // paths, whose shared cuts give equal shares of their connections' mean rate.
    if outbox.datagrams() {
        // Its base round trip is shared with the other sessions of its address, though:
        // their frames' acknowledgements, a path of their own.
        outbox
            .pace()
            .share_base(state.datagram_paths.join(peer.map(|p| p.ip())));
    } else {
        outbox
            .pace()
            .set_path(state.paths.join(peer.map(|p| p.ip())));
    }
    let conn = state.register_connection(&outbox);
    let peer = peer.map_or_else(|| "-".to_owned(), |p| p.to_string());
    let span = info_span!("ws", conn, peer = %peer, caller = tracing::field::Empty);
    async move {
        state.metrics.connection_opened();
        info!("websocket opened");
        let mut writer = tokio::spawn(writer);
        let mut session = Session {
            conn,
            state: state.clone(),
            outbox: outbox.clone(),
            encoding: None,
            version: PROTOCOL_VERSION,
            scenes: Vec::new(),
            caller: Caller::Anonymous,
            commands: TokenBucket::new(state.config.command_rate),
            drives: Drives::new(conn),
            greeter,
            tcp,
        };
        let mut writer_done = false;
        let mut client_closed = false;
        let mut liveness = Liveness::new(&state.config.net);
        state.metrics.pace.opened();
        // The adaptive rate's probes (only while subscribed: frames flow then), every
        // `PROBE_INTERVAL` on the server's one probe clock: a reading of the socket's kernel
        // figures and a round-trip ping. They run inside this loop, while `stream` holds the
        // websocket and so the socket `tcp` names.
        let mut probe = state.probes.subscribe(conn);
        // Resolves when the connection's minted token expires or is revoked.
        let mut token_end: Option<TokenEnd> = None;
        loop {
            if token_end.is_none() {
                token_end = TokenEnd::watch(&session);
            }
            let message = tokio::select! {
                m = stream.next() => m,
                e = async {
                    match token_end.as_mut() {
                        Some(end) => end.0.as_mut().await,
                        None => std::future::pending().await,
                    }
                } => {
                    info!(reason = %e, "token no longer valid; closing");
                    session.refuse(e, close_code::POLICY, "token no longer valid");
                    break;
                }
                Ok(()) = probe.changed(), if !session.scenes.is_empty() => {
                    session.probe();
                    continue;
                }
                _ = &mut writer => {
                    writer_done = true;
                    None
                }
                due = liveness.due(session.encoding.is_some()) => {
                    if session.on_due(due) {
                        continue;
                    }
                    break;
                }
            };
            let Some(message) = message else {
                break;
            };
            liveness.heard();
            let keep_going = match message {
                Ok(Message::Text(t)) => session.on_text(t.as_str()).await,
                Ok(Message::Binary(b)) => {
                    // Binary client messages are live poses only (`proto/src/live.rs`).
                    if let Err(e) = session.drives.binary_pose(&session.state, &b) {
                        session.error(e);
                    }
                    true
                }
                Ok(Message::Close(_)) => {
                    client_closed = true;
                    false
                }
                Ok(Message::Pong(payload)) => {
                    session.pong(&payload);
                    true
                }
                Ok(Message::Ping(_)) => true,
                Err(e) => {
                    if let Some((error, code, reason)) = read_failure(e) {
                        session.error(error);
                        outbox.close_with(code, reason);
                    }
                    false
                }
            };
            // Handling may have waited (start-up restore, a bake queue) longer than the idle
            // timeout: the client was not silent, the server was busy.
            liveness.heard();
            if !keep_going {
                break;
            }
        }
        session.leave_all();
        outbox.close();
        if !writer_done {
            // Give the writer a moment to deliver the last error and the close frame.
            let abort = writer.abort_handle();
            if tokio::time::timeout(Duration::from_secs(2), writer)
                .await
                .is_err()
            {
                abort.abort();
            }
        }
        if !client_closed {
            // The server's close frame is out: what the client still sends is not acted on.
            // Wait briefly for its answering close, which completes the closing handshake (a
            // stream that failed or ended yields nothing, so this returns at once).
            let linger = tokio::time::Instant::now() + CLOSE_LINGER;
            while let Ok(Some(Ok(m))) = tokio::time::timeout_at(linger, stream.next()).await {
                if matches!(m, Message::Close(_)) {
                    break;
                }
            }
        }
        outbox.detach_direct();
        state.unregister_connection(conn);
        state.metrics.connection_closed(outbox.dropped_frames());
        state.metrics.pace.closed(outbox.pace().level());
        info!(
            frames_dropped = outbox.dropped_frames(),
            client_closed, "websocket closed"
        );
    }
    .instrument(span)
    .await;
}

/// The error to report and the close frame to send when reading failed, or `None` when the
/// connection is simply gone (no answer can reach the client).
///
/// axum wraps the `tungstenite` error of the version it was built with, so this downcasts to
/// that version's type (`axum-tungstenite` in `server/Cargo.toml`); a mismatched version would
/// silently classify nothing (the end-to-end test of oversized messages guards it).
fn read_failure(e: axum::Error) -> Option<(ProtocolError, u16, &'static str)> {
    use axum_tungstenite::error::{Error, ProtocolError as WsProtocolError};
    let inner = e.into_inner();
    match inner.downcast_ref::<Error>()? {
        Error::Capacity(_) => Some((
            ProtocolError::new(
                ErrorCode::MessageTooLarge,
                format!("messages are limited to {MAX_CLIENT_MESSAGE_BYTES} bytes"),
            ),
            close_code::SIZE,
            "message too big",
        )),
        Error::Utf8(_) => Some((
            ProtocolError::new(ErrorCode::BadMessage, "a text message was not valid UTF-8"),
            close_code::INVALID,
            "invalid UTF-8",
        )),
        // A dropped TCP connection surfaces as a protocol error too; nobody is left to tell.
        Error::Protocol(WsProtocolError::ResetWithoutClosingHandshake) => None,
        Error::Protocol(p) => Some((
            ProtocolError::new(
                ErrorCode::BadMessage,
                format!("websocket protocol violation: {p}"),
            ),
            close_code::PROTOCOL,
            "protocol violation",
        )),
        _ => None,
    }
}

/// A subscription's `precision`: in range, and asked by a connection whose frames can carry
/// it (binary, protocol version 5 or later: wire v2 keyframes with grid steps).
fn check_precision(
    precision: Option<&posecast_proto::precision::Precision>,
    encoding: Encoding,
    version: u32,
) -> Result<(), Error> {
    let Some(p) = precision else {
        return Ok(());
    };
    p.validate().map_err(|e| Error::invalid(e.to_string()))?;
    if p.is_finest() {
        return Ok(());
    }
    if encoding != Encoding::Binary || version < 5 {
        return Err(Error::invalid(format!(
            "precision applies to binary frames of protocol version 5 or later; this \
             connection speaks {encoding:?} frames of version {version}"
        )));
    }
    Ok(())
}

/// Which ticks a subscription asking for `rate` frames per second gets: every
/// `round(tick_rate / rate)`-th, at least every one (a rate that is not finite and positive, or
/// above the tick rate, gets every tick).
fn every_nth_tick(tick_rate: f32, rate: Option<f32>) -> u32 {
    match rate {
        Some(r) if r.is_finite() && r > 0.0 && tick_rate.is_finite() && tick_rate > 0.0 => {
            (f64::from(tick_rate) / f64::from(r))
                .round()
                .clamp(1.0, 1_000.0) as u32
        }
        _ => 1,
    }
}

/// A message that does not parse, as a `bad_message` error that carries the command's id when
/// the text is a JSON object `{"type":"command","id":N,…}`: a client waiting for command N's
/// answer gets one instead of waiting for ever.
fn unparsable(text: &str, e: &serde_json::Error) -> ProtocolError {
    let error = ProtocolError::new(ErrorCode::BadMessage, format!("not a valid message: {e}"));
    match command_id(text) {
        Some(id) => error.for_command(id),
        None => error,
    }
}

fn command_id(text: &str) -> Option<u64> {
    let value: serde_json::Value = serde_json::from_str(text).ok()?;
    if value.get("type")?.as_str()? != "command" {
        return None;
    }
    value.get("id")?.as_u64()
}

/// A connection's minted token running out (expired or revoked).
struct TokenEnd(std::pin::Pin<Box<dyn std::future::Future<Output = Error> + Send>>);

impl TokenEnd {
    /// Set once the session holds a minted token.
    fn watch(session: &Session) -> Option<Self> {
        let info = session.caller.minted()?.clone();
        let mint = session.state.config.access.mint.clone()?;
        Some(Self(Box::pin(async move { mint.ended(&info).await })))
    }
}

struct Session {
    conn: u64,
    state: Arc<AppState>,
    outbox: Arc<Outbox>,
    encoding: Option<Encoding>,
    /// The protocol version the hello asked for (1 until then).
    version: u32,
    scenes: Vec<SceneId>,
    caller: Caller,
    /// The connection's command rate limit.
    commands: TokenBucket,
    /// The avatars this connection drives live.
    drives: Drives,
    /// The connection's slot under the caps, told of the hello.
    greeter: Option<Greeter>,
    /// The accepted socket, for the kernel's figures (the adaptive rate's signals).
    tcp: Option<SocketInfo>,
}

impl Session {
    fn send(&self, msg: &ServerMsg) {
        if !self.outbox.push_control(text(msg)) {
            debug!("outbox full or closed; connection is being closed");
        }
    }

    /// A command's ack: its result tagged with its kind from protocol version 3 on, the bare
    /// value before.
    fn send_ack(&self, id: u64, result: CommandResult) {
        let message = if self.version >= 3 {
            text(&ServerMsg::Ack { id, result })
        } else {
            Message::Text(ServerMsg::ack_bare(id, &result).into())
        };
        if !self.outbox.push_control(message) {
            debug!("outbox full or closed; connection is being closed");
        }
    }

    fn error(&self, e: impl Into<ProtocolError>) {
        let e = e.into();
        match e.code {
            ErrorCode::Unauthorized => self.state.metrics.refused(false),
            ErrorCode::Forbidden => self.state.metrics.refused(true),
            _ => {}
        }
        self.state.metrics.protocol_error();
        self.send(&ServerMsg::Error(e));
    }

    /// Ends the connection after `e`: the error, then a close frame with `code`.
    fn refuse(&self, e: impl Into<ProtocolError>, code: u16, reason: &'static str) -> bool {
        self.error(e);
        self.outbox.close_with(code, reason);
        false
    }

    /// Samples the connection for the adaptive rate: the socket's kernel figures (unsent
    /// bytes, bytes acknowledged, the kernel's round trip: the queues that stand), then the
    /// round trip: a ping carrying the server's time (as the liveness pings do), unless one is
    /// unanswered — which counts as late by its age. With the figures, round trips are judged
    /// by their trend, so a reader that is only late to answer is not cut
    /// (`posecast_stream::pace`).
    fn probe(&self) {
        let pace = self.outbox.pace();
        if self.outbox.datagrams() {
            self.probe_datagrams();
            return;
        }
        if let Some(figures) = self.tcp.as_ref().and_then(SocketInfo::figures) {
            let change = pace.socket(Instant::now(), figures);
            self.rate_changed(change);
        }
        let (send, change) = pace.probe(Instant::now(), self.outbox.dropped_while_held());
        self.rate_changed(change);
        if send {
            let payload = unix_micros().to_le_bytes().to_vec();
            self.outbox.push_control(Message::Ping(payload.into()));
            self.state.metrics.pace.pinged();
        }
    }

    /// [`Self::probe`] over datagrams (WebTransport). Round trips over a lossy path are not
    /// pongs on the stream (they wait for its retransmissions: not a queue to cut the rate
    /// for). In protocol version 8 the client acknowledges every frame, and the least time
    /// from sending one to its acknowledgement since the last probe is the round trip: a
    /// queue raises it, a lost datagram or acknowledgement does not. Frames awaiting their
    /// acknowledgement stand for an unanswered ping (none coming back for long counts as
    /// late), and frames the link could not take (QUIC's congestion control held frames
    /// already) as superseded ones. Before version 8 (acknowledged keyframes only) QUIC's
    /// congestion control alone paces.
    fn probe_datagrams(&self) {
        let pace = self.outbox.pace();
        let now = Instant::now();
        if let Some(rtt) = self.outbox.take_frame_rtt_floor() {
            let change = pace.answered(now, rtt);
            self.rate_changed(change);
        }
        if self.outbox.frames_in_flight() {
            let (_, change) = pace.probe(now, 0);
            self.rate_changed(change);
        }
    }

    /// A pong: if it answers one of the server's pings (8 bytes, the server's time when it
    /// was sent), its round trip goes to the adaptive rate.
    fn pong(&self, payload: &[u8]) {
        let Ok(sent) = <[u8; 8]>::try_from(payload) else {
            return;
        };
        let now = unix_micros();
        let sent = u64::from_le_bytes(sent);
        if sent > now {
            return;
        }
        let rtt = Duration::from_micros(now - sent);
        let change = self.outbox.pace().answered(Instant::now(), rtt);
        self.rate_changed(change);
    }

    fn rate_changed(&self, change: Option<Change>) {
        if let Some(c) = change {
            self.state.metrics.pace.changed(c);
            debug!(
                per_60_ticks = posecast_stream::pace::STEPS[c.to],
                "adaptive frame rate changed"
            );
        }
    }

    /// Acts on a liveness deadline ([`Liveness`]); `false` ends the connection: no hello in
    /// time (`timeout` error, close 1008, like any other bad first message), or nothing heard
    /// for the idle timeout (close 1008 without an error: a peer that answers nothing would
    /// not read it).
    fn on_due(&self, due: Due) -> bool {
        let net = &self.state.config.net;
        match due {
            Due::Ping => {
                // The payload (the server's time) gives the ping bytes, so pings a client
                // never reads count towards its outbox bound like any other message.
                let payload = unix_micros().to_le_bytes().to_vec();
                self.outbox.push_control(Message::Ping(payload.into()))
            }
            Due::HelloTimeout => {
                self.state.metrics.net.timed_out(Timeout::Hello);
                self.refuse(
                    ProtocolError::new(
                        ErrorCode::Timeout,
                        format!(
                            "no hello within {} s of connecting",
                            net.hello_timeout.as_secs_f64()
                        ),
                    ),
                    close_code::POLICY,
                    "hello timeout",
                )
            }
            Due::Idle => {
                self.state.metrics.net.timed_out(Timeout::Idle);
                debug!(
                    idle_s = net.ws_idle_timeout.as_secs_f64(),
                    "nothing heard, not even a pong; closing"
                );
                self.outbox.close_with(close_code::POLICY, "idle timeout");
                false
            }
        }
    }

    /// Handles the first message, which must be a `hello` of this protocol version; anything
    /// else gets an error and a close (1008). `false` ends the connection.
    fn on_first(&mut self, msg: Result<ClientMsg, serde_json::Error>) -> bool {
        let (version, encoding, token) = match msg {
            Ok(ClientMsg::Hello {
                version,
                encoding,
                token,
                ..
            }) => (version, encoding, token),
            Ok(_) => {
                return self.refuse(
                    ProtocolError::new(ErrorCode::NotAllowedNow, "the first message must be hello"),
                    close_code::POLICY,
                    "expected hello",
                );
            }
            Err(e) => {
                return self.refuse(
                    ProtocolError::new(
                        ErrorCode::BadMessage,
                        format!("the first message must be hello: {e}"),
                    ),
                    close_code::POLICY,
                    "expected hello",
                );
            }
        };
        if !SUPPORTED_VERSIONS.contains(&version) {
            return self.refuse(
                ProtocolError::new(
                    ErrorCode::UnsupportedVersion,
                    format!("protocol version {version} is not supported; this server speaks {SUPPORTED_VERSIONS:?}"),
                ),
                close_code::POLICY,
                "unsupported protocol version",
            );
        }
        self.encoding = Some(encoding);
        self.version = version;
        // An unknown token leaves the connection anonymous (it may still watch when
        // views are open) and is reported right after the welcome.
        let access = &self.state.config.access;
        let refused = match access.identify(token.as_deref()) {
            Ok(caller) => {
                self.caller = caller;
                None
            }
            Err(e) => Some(e),
        };
        let authenticated = !matches!(self.caller, Caller::Anonymous);
        if let Some(greeter) = &self.greeter
            && greeter.greet(authenticated).is_err()
        {
            return self.refuse(
                ProtocolError::new(
                    ErrorCode::Unavailable,
                    "the server holds as many anonymous connections as it allows; \
                     try again later, or with a token",
                ),
                CLOSE_TRY_AGAIN_LATER,
                "try again later",
            );
        }
        tracing::Span::current().record("caller", self.caller.name());
        self.drives.identify(Driver {
            name: self.caller.name().to_owned(),
            via: DriveVia::Websocket,
        });
        info!(?encoding, token = self.caller.name(), "hello");
        self.send(&ServerMsg::Welcome {
            version,
            encoding,
            server: format!("posecast {}", env!("CARGO_PKG_VERSION")),
            tick_rate: self.state.config.tick_rate,
            server_time_us: unix_micros(),
            access: access.access(&self.caller),
        });
        if let Some(e) = refused {
            self.error(e);
        }
        // The adaptive rate's first round trip, before any subscription's descriptions.
        self.probe();
        true
    }

    /// Handles one text message; `false` ends the connection.
    async fn on_text(&mut self, text: &str) -> bool {
        let parsed = serde_json::from_str::<ClientMsg>(text);
        let Some(encoding) = self.encoding else {
            return self.on_first(parsed);
        };
        let msg = match parsed {
            Ok(m) => m,
            Err(e) => {
                self.error(unparsable(text, &e));
                return true;
            }
        };
        // While the server is starting, a subscribe or command waits until the stored scenes
        // are restored (this connection's later messages wait behind it, in order): a client
        // reconnecting after a restart then gets its scene, not `unknown_scene`.
        if !matches!(msg, ClientMsg::Ping { .. } | ClientMsg::Hello { .. })
            && let Err(e) = self.state.readiness.wait().await
        {
            self.error(match msg {
                ClientMsg::Command { id, .. } => e.for_command(id),
                _ => e.into(),
            });
            return true;
        }
        match msg {
            ClientMsg::Hello { .. } => {
                self.error(ProtocolError::new(
                    ErrorCode::NotAllowedNow,
                    "hello was already received",
                ));
                true
            }
            ClientMsg::Subscribe {
                scene,
                avatars,
                rate,
                joints,
                morph_weights,
                precision,
            } => {
                // A subscription costs the scene work under its lock (descriptions, a
                // keyframe): it is charged to the same rate limit as commands.
                if let Err(wait) = self.commands.take() {
                    self.state.metrics.rate_limited();
                    self.error(rate_limited(wait));
                    return true;
                }
                // Precisions that differ by a hair share their frames: rounded (towards finer)
                // to the R10 series, and echoed so in `subscribed`.
                // (Only a valid one: an invalid one is refused as asked, below.)
                let precision = precision.map(|p| {
                    if p.validate().is_ok() {
                        p.canonical()
                    } else {
                        p
                    }
                });
                // Each filter entry is checked against the scene every tick: no repeats.
                let avatars = avatars.map(|mut ids| {
                    ids.sort();
                    ids.dedup();
                    ids
                });
                let result = joints
                    .as_ref()
                    .map_or(Ok(()), JointSet::validate)
                    .map_err(|e| Error::invalid(e.to_string()))
                    .and_then(|()| check_precision(precision.as_ref(), encoding, self.version))
                    .and_then(|()| {
                        self.state
                            .config
                            .access
                            .authorize_view(&self.caller, &scene)
                    })
                    .and_then(|()| self.state.world.scene(&scene))
                    .and_then(|s| {
                        crate::changes::viewers_changed(&self.state.services, &s);
                        s.subscribe(
                            Subscriber::new(
                                self.conn,
                                self.outbox.clone(),
                                encoding,
                                avatars,
                                every_nth_tick(self.state.config.tick_rate, rate),
                            )
                            .with_joints(joints)
                            .with_morph_weights(morph_weights.unwrap_or(true))
                            .with_precision(precision)
                            .with_version(self.version)
                            .with_name(self.caller.owner()),
                        )
                    });
                match result {
                    Ok(()) => {
                        if !self.scenes.contains(&scene) {
                            self.scenes.push(scene);
                        }
                    }
                    Err(e) => self.error(e),
                }
                true
            }
            ClientMsg::Unsubscribe { scene } => {
                let had = self.state.world.scene(&scene).is_ok_and(|s| {
                    let had = s.unsubscribe(self.conn);
                    if had {
                        crate::changes::viewers_changed(&self.state.services, &s);
                    }
                    had
                });
                self.scenes.retain(|s| s != &scene);
                if had {
                    self.send(&ServerMsg::Unsubscribed { scene });
                } else {
                    self.error(ProtocolError::new(
                        ErrorCode::UnknownScene,
                        format!("not subscribed to {scene}"),
                    ));
                }
                true
            }
            ClientMsg::WatchScenes => {
                // The listing walks every scene under its lock: charged like a subscribe.
                if let Err(wait) = self.commands.take() {
                    self.state.metrics.rate_limited();
                    self.error(rate_limited(wait));
                    return true;
                }
                let access = &self.state.config.access;
                if let Err(e) = access.authorize_read(&self.caller) {
                    self.error(e);
                    return true;
                }
                // Watching first, listing second: no change is missed. One made while the list
                // is being made may come before it (and the list may or may not hold it):
                // clients apply such changes after the list (PROTOCOL.md).
                self.state
                    .watchers
                    .watch(self.conn, &self.outbox, self.caller.clone());
                let scenes = self
                    .state
                    .world
                    .scenes()
                    .iter()
                    .map(|s| s.info())
                    .filter(|s| access.authorize_view(&self.caller, &s.scene).is_ok())
                    .collect();
                // In a cluster, scenes ticked elsewhere with their avatars, as their owners
                // have them (and every scene with its owner), as `list_scenes` answers.
                let scenes = match self.state.cluster() {
                    Some(cluster) => cluster.listing(scenes).await,
                    None => scenes,
                };
                self.send(&ServerMsg::Scenes { scenes });
                true
            }
            ClientMsg::UnwatchScenes => {
                self.state.watchers.unwatch(self.conn);
                true
            }
            ClientMsg::Pose {
                avatar,
                rotations,
                root_position,
                time_us,
                weights,
                trackers,
            } => {
                // Not acknowledged (up to 120 a second): errors only.
                let pose = JsonPose {
                    rotations: &rotations,
                    root_position,
                    time_us,
                    weights: &weights,
                    trackers: &trackers,
                };
                if let Err(e) = self.drives.json_pose(&self.state, &avatar, &pose) {
                    self.error(e);
                }
                true
            }
            ClientMsg::Ping { id, client_time_us } => {
                self.send(&ServerMsg::Pong {
                    id,
                    client_time_us,
                    server_time_us: unix_micros(),
                });
                true
            }
            ClientMsg::Command {
                id,
                command,
                idempotency_key,
            } => {
                if let Err(wait) = self.commands.take() {
                    self.state.metrics.rate_limited();
                    self.error(rate_limited(wait).for_command(id));
                    return true;
                }
                let authorized = control::authorize(&self.state, &self.caller, &command);
                let result = match authorized {
                    Ok(()) => match self.drives.command_remote(&self.state, &command).await {
                        Some(result) => result,
                        None => match self.drives.command(&self.state, &command) {
                            Some(result) => result,
                            None => {
                                control::execute_as(
                                    &self.state,
                                    &self.caller,
                                    &command,
                                    idempotency_key.as_deref(),
                                )
                                .await
                            }
                        },
                    },
                    Err(e) => Err(e),
                };
                match result {
                    Ok(result) => {
                        let result = self.state.config.access.visible(&self.caller, result);
                        self.send_ack(id, result);
                    }
                    Err(e) => self.error(e.for_command(id)),
                }
                true
            }
        }
    }

    fn leave_all(&mut self) {
        self.state.watchers.unwatch(self.conn);
        self.drives.leave(&self.state);
        for scene in self.scenes.drain(..) {
            if let Ok(s) = self.state.world.scene(&scene)
                && s.unsubscribe(self.conn)
            {
                crate::changes::viewers_changed(&self.state.services, &s);
            }
        }
    }
}

#[cfg(test)]
mod tests;
