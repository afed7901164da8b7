//! One websocket connection: a reader that parses client messages and a writer that drains the
//! connection's [`Outbox`]. Bad input gets a typed error and the connection goes on; the
//! connection closes, with the close code `proto/PROTOCOL.md` lists, only on a first message that
//! is not a valid `hello` (1008), a wrong protocol version (1008), an oversized message (1009),
//! invalid UTF-8 (1007), a websocket protocol violation (1002), a client that stops reading
//! (1008), no hello in time or nothing heard for the idle timeout (1008, see
//! [`super::limits::NetLimits`]) or server shutdown (1001). Nothing a client sends can affect
//! another connection.

use crate::auth::Caller;
use crate::control;
use crate::live::Drives;
use crate::metrics::net::Timeout;
use crate::quota::{TokenBucket, rate_limited};
use crate::scene::ticker::unix_micros;
use crate::service::ws_liveness::{Due, Liveness};
use crate::state::AppState;
use crate::stream::feed::{Subscriber, text};
use crate::stream::outbox::Outbox;
use crate::stream::writer::run_writer;
use axum::extract::ws::{Message, WebSocket, close_code};
use futures_util::{Sink, Stream, StreamExt};
use posecast_proto::msg::{
    ClientMsg, Encoding, ErrorCode, MAX_CLIENT_MESSAGE_BYTES, PROTOCOL_VERSION, ProtocolError,
    SceneId, ServerMsg,
};
use std::sync::Arc;
use std::time::Duration;
use tracing::{Instrument, debug, info_span};

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

/// Serves one upgraded websocket until either side closes.
pub async fn serve(socket: WebSocket, state: Arc<AppState>) {
    serve_on(socket, state).await;
}

/// [`serve`] over any websocket-shaped transport: a stream of received messages and a sink for
/// sent ones (axum's [`WebSocket`] in the server; channels in the unit tests below).
pub async fn serve_on<S>(socket: S, state: Arc<AppState>)
where
    S: Stream<Item = Result<Message, axum::Error>> + Sink<Message> + Send + 'static,
{
    let outbox = Arc::new(Outbox::new());
    let conn = state.register_connection(&outbox);
    let span = info_span!("ws", conn, caller = tracing::field::Empty);
    async move {
        state.metrics.connection_opened();
        let (sink, mut stream) = socket.split();
        let mut writer = {
            let outbox = outbox.clone();
            let metrics = state.metrics.clone();
            tokio::spawn(async move { run_writer(&outbox, sink, &metrics).await })
        };
        let mut session = Session {
            conn,
            state: state.clone(),
            outbox: outbox.clone(),
            encoding: None,
            scenes: Vec::new(),
            caller: Caller::Anonymous,
            commands: TokenBucket::new(state.config.command_rate),
            drives: Drives::new(conn),
        };
        let mut writer_done = false;
        let mut client_closed = false;
        let mut liveness = Liveness::new(&state.config.net);
        loop {
            let message = tokio::select! {
                m = stream.next() => m,
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
                    if let Err(e) = session.drives.binary_pose(&b) {
                        session.error(e);
                    }
                    true
                }
                Ok(Message::Close(_)) => {
                    client_closed = true;
                    false
                }
                Ok(Message::Ping(_) | Message::Pong(_)) => true,
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
        state.unregister_connection(conn);
        state.metrics.connection_closed(outbox.dropped_frames());
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

struct Session {
    conn: u64,
    state: Arc<AppState>,
    outbox: Arc<Outbox>,
    encoding: Option<Encoding>,
    scenes: Vec<SceneId>,
    caller: Caller,
    /// The connection's command rate limit.
    commands: TokenBucket,
    /// The avatars this connection drives live.
    drives: Drives,
}

impl Session {
    fn send(&self, msg: &ServerMsg) {
        if !self.outbox.push_control(text(msg)) {
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
        if version != PROTOCOL_VERSION {
            return self.refuse(
                ProtocolError::new(
                    ErrorCode::UnsupportedVersion,
                    format!("protocol version {version} is not supported; this server speaks {PROTOCOL_VERSION}"),
                ),
                close_code::POLICY,
                "unsupported protocol version",
            );
        }
        self.encoding = Some(encoding);
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
        tracing::Span::current().record("caller", self.caller.name());
        self.send(&ServerMsg::Welcome {
            version: PROTOCOL_VERSION,
            encoding,
            server: format!("posecast {}", env!("CARGO_PKG_VERSION")),
            tick_rate: self.state.config.tick_rate,
            server_time_us: unix_micros(),
            access: access.access(&self.caller),
        });
        if let Some(e) = refused {
            self.error(e);
        }
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
            ClientMsg::Subscribe { scene, avatars } => {
                // A subscription costs the scene work under its lock (descriptions, a
                // keyframe): it is charged to the same rate limit as commands.
                if let Err(wait) = self.commands.take() {
                    self.state.metrics.rate_limited();
                    self.error(rate_limited(wait));
                    return true;
                }
                // Each filter entry is checked against the scene every tick: no repeats.
                let avatars = avatars.map(|mut ids| {
                    ids.sort();
                    ids.dedup();
                    ids
                });
                let result = self
                    .state
                    .config
                    .access
                    .authorize_view(&self.caller, &scene)
                    .and_then(|()| self.state.world.scene(&scene))
                    .and_then(|s| {
                        s.subscribe(Subscriber {
                            conn: self.conn,
                            outbox: self.outbox.clone(),
                            encoding,
                            filter: avatars,
                        })
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
                let had = self
                    .state
                    .world
                    .scene(&scene)
                    .map(|s| s.unsubscribe(self.conn))
                    .unwrap_or(false);
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
            ClientMsg::Pose {
                avatar,
                rotations,
                root_position,
                time_us,
            } => {
                // Not acknowledged (up to 120 a second): errors only.
                if let Err(e) = self
                    .drives
                    .json_pose(&avatar, &rotations, root_position, time_us)
                {
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
            ClientMsg::Command { id, command } => {
                if let Err(wait) = self.commands.take() {
                    self.state.metrics.rate_limited();
                    self.error(rate_limited(wait).for_command(id));
                    return true;
                }
                let authorized =
                    self.state
                        .config
                        .access
                        .authorize(&self.caller, &self.state.world, &command);
                let result = match authorized {
                    Ok(()) => match self.drives.command(&self.state, &command) {
                        Some(result) => result,
                        None => control::execute_durable(&self.state, &command).await,
                    },
                    Err(e) => Err(e),
                };
                match result {
                    Ok(result) => {
                        let result = self.state.config.access.visible(&self.caller, result);
                        self.send(&ServerMsg::Ack {
                            id,
                            result: result.to_value(),
                        });
                    }
                    Err(e) => self.error(e.for_command(id)),
                }
                true
            }
        }
    }

    fn leave_all(&mut self) {
        self.drives.leave();
        for scene in self.scenes.drain(..) {
            if let Ok(s) = self.state.world.scene(&scene) {
                s.unsubscribe(self.conn);
            }
        }
    }
}

/// The session driven through channels instead of a TCP socket: message order, refusals,
/// close codes and a slow reader, checked without a network.
#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::Config;
    use std::pin::Pin;
    use std::sync::atomic::{AtomicBool, Ordering};
    use std::task::{Context, Poll, Waker};
    use tokio::sync::mpsc::{UnboundedReceiver, UnboundedSender, unbounded_channel};

    /// Set while the test's end does not read; the sink's waker to call when it reads again.
    #[derive(Default)]
    struct Gate {
        blocked: AtomicBool,
        waker: std::sync::Mutex<Option<Waker>>,
    }

    /// A websocket whose peer is the test: what the test sends arrives as client messages;
    /// what the session sends goes to the test. While the gate is closed, the sink is not
    /// ready (a client that does not read).
    struct ChannelSocket {
        incoming: UnboundedReceiver<Result<Message, axum::Error>>,
        outgoing: UnboundedSender<Message>,
        gate: Arc<Gate>,
    }

    impl Stream for ChannelSocket {
        type Item = Result<Message, axum::Error>;
        fn poll_next(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Option<Self::Item>> {
            self.incoming.poll_recv(cx)
        }
    }

    impl Sink<Message> for ChannelSocket {
        type Error = axum::Error;
        fn poll_ready(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
            if self.gate.blocked.load(Ordering::SeqCst) {
                *self.gate.waker.lock().unwrap() = Some(cx.waker().clone());
                Poll::Pending
            } else {
                Poll::Ready(Ok(()))
            }
        }
        fn start_send(self: Pin<&mut Self>, item: Message) -> Result<(), Self::Error> {
            self.outgoing
                .send(item)
                .map_err(|_| axum::Error::new("the test stopped listening"))
        }
        fn poll_flush(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
            self.poll_ready(cx)
        }
        fn poll_close(self: Pin<&mut Self>, _: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
            Poll::Ready(Ok(()))
        }
    }

    /// The test's end of one session.
    struct Peer {
        send: UnboundedSender<Result<Message, axum::Error>>,
        recv: UnboundedReceiver<Message>,
        gate: Arc<Gate>,
        session: tokio::task::JoinHandle<()>,
    }

    impl Peer {
        fn text(&self, json: &str) {
            self.send
                .send(Ok(Message::Text(json.into())))
                .expect("session gone");
        }

        /// The next message the session sent (5 s at most).
        async fn next(&mut self) -> Message {
            tokio::time::timeout(Duration::from_secs(5), self.recv.recv())
                .await
                .expect("nothing sent within 5 s")
                .expect("the session ended")
        }

        /// The next message, parsed; a binary frame gives `None`.
        async fn next_json(&mut self) -> Option<serde_json::Value> {
            match self.next().await {
                Message::Text(t) => Some(serde_json::from_str(t.as_str()).unwrap()),
                Message::Binary(_) => None,
                other => panic!("expected a text or binary message, got {other:?}"),
            }
        }

        fn set_blocked(&self, blocked: bool) {
            self.gate.blocked.store(blocked, Ordering::SeqCst);
            if !blocked && let Some(w) = self.gate.waker.lock().unwrap().take() {
                w.wake();
            }
        }
    }

    /// A ready server state holding scene `s` with the built-in avatar `a`, ticking at 30 Hz.
    fn state() -> Arc<AppState> {
        let state = AppState::new(Config {
            tick_rate: 30.0,
            ..Config::default()
        });
        state
            .world
            .library
            .insert(crate::builtin::rig().expect("built-in rig"));
        state.readiness.begin(0);
        state.readiness.finish(Ok(()));
        let scene = SceneId("s".into());
        state.world.create_scene(scene.clone()).expect("scene");
        state
            .world
            .add_avatar(
                &scene,
                crate::builtin::BUILTIN_ASSET,
                Some(posecast_proto::msg::AvatarId("a".into())),
            )
            .expect("avatar");
        state
    }

    fn connect(state: &Arc<AppState>) -> Peer {
        let (send, incoming) = unbounded_channel();
        let (outgoing, recv) = unbounded_channel();
        let gate = Arc::new(Gate::default());
        let socket = ChannelSocket {
            incoming,
            outgoing,
            gate: gate.clone(),
        };
        let session = tokio::spawn(serve_on(socket, state.clone()));
        Peer {
            send,
            recv,
            gate,
            session,
        }
    }

    fn close_code_of(m: &Message) -> Option<u16> {
        match m {
            Message::Close(Some(frame)) => Some(frame.code),
            _ => None,
        }
    }

    const HELLO: &str = r#"{"type":"hello","version":1,"encoding":"json"}"#;

    #[tokio::test]
    async fn hello_then_subscribe_gives_welcome_subscribed_description_then_frames() {
        let state = state();
        let mut peer = connect(&state);
        peer.text(HELLO);
        assert_eq!(peer.next_json().await.unwrap()["type"], "welcome");
        peer.text(r#"{"type":"subscribe","scene":"s"}"#);
        let subscribed = peer.next_json().await.unwrap();
        assert_eq!(subscribed["type"], "subscribed", "{subscribed}");
        let description = peer.next_json().await.unwrap();
        assert_eq!(description["type"], "description", "{description}");
        assert_eq!(description["avatar"]["id"], "a");
        let frame = peer.next_json().await.unwrap();
        assert_eq!(frame["type"], "frame", "{frame}");
        assert_eq!(frame["avatars"][0]["avatar"], "a");
        state.shutdown();
    }

    #[tokio::test]
    async fn a_first_message_other_than_hello_is_refused_with_1008() {
        let state = state();
        let mut peer = connect(&state);
        peer.text(r#"{"type":"subscribe","scene":"s"}"#);
        let error = peer.next_json().await.unwrap();
        assert_eq!(error["code"], "not_allowed_now", "{error}");
        assert_eq!(close_code_of(&peer.next().await), Some(1008));
        // The session ends without the client's answering close (after the linger).
        tokio::time::timeout(Duration::from_secs(5), peer.session)
            .await
            .expect("session still running")
            .unwrap();
        assert_eq!(state.open_connections(), 0);
    }

    #[tokio::test]
    async fn a_wrong_version_is_refused_with_1008() {
        let state = state();
        let mut peer = connect(&state);
        peer.text(r#"{"type":"hello","version":99,"encoding":"json"}"#);
        let error = peer.next_json().await.unwrap();
        assert_eq!(error["code"], "unsupported_version", "{error}");
        assert_eq!(close_code_of(&peer.next().await), Some(1008));
    }

    #[tokio::test]
    async fn bad_input_after_hello_gets_an_error_and_the_session_goes_on() {
        let state = state();
        let mut peer = connect(&state);
        peer.text(HELLO);
        peer.next().await;
        peer.text(r#"{"type":"command","id":7,"command":{"op":"no_such_op"}}"#);
        let error = peer.next_json().await.unwrap();
        assert_eq!(
            (error["code"].as_str(), error["id"].as_u64()),
            (Some("bad_message"), Some(7)),
            "{error}"
        );
        peer.send
            .send(Ok(Message::Binary(vec![1, 2, 3].into())))
            .unwrap();
        let error = peer.next_json().await.unwrap();
        assert_eq!(error["code"], "unexpected_binary", "{error}");
        peer.text(r#"{"type":"command","id":8,"command":{"op":"get_avatar","avatar":"a"}}"#);
        let ack = peer.next_json().await.unwrap();
        assert_eq!(
            (ack["type"].as_str(), ack["id"].as_u64()),
            (Some("ack"), Some(8))
        );
        assert_eq!(ack["result"]["avatar"], "a", "{ack}");
        state.shutdown();
    }

    #[tokio::test]
    async fn the_client_closing_gets_a_normal_close_and_shutdown_gets_1001() {
        let state = state();
        let mut peer = connect(&state);
        peer.text(HELLO);
        peer.next().await;
        peer.send.send(Ok(Message::Close(None))).unwrap();
        assert_eq!(close_code_of(&peer.next().await), Some(1000));
        tokio::time::timeout(Duration::from_secs(5), peer.session)
            .await
            .expect("session still running")
            .unwrap();

        let mut peer = connect(&state);
        peer.text(HELLO);
        peer.next().await;
        state.shutdown();
        assert_eq!(close_code_of(&peer.next().await), Some(1001));
    }

    /// A client that stops reading while frames keep coming gets, once it reads again, the
    /// newest frame rather than the backlog: the outbox keeps one frame per scene.
    #[tokio::test]
    async fn a_reader_that_stalls_gets_the_newest_frame_not_a_backlog() {
        let state = state();
        let mut peer = connect(&state);
        peer.text(r#"{"type":"hello","version":1,"encoding":"binary"}"#);
        peer.next().await;
        peer.text(r#"{"type":"subscribe","scene":"s"}"#);
        peer.next().await; // subscribed
        peer.next().await; // description
        assert!(peer.next_json().await.is_none(), "a binary frame");
        peer.set_blocked(true);
        // 30 Hz for half a second: about 15 ticks while nothing is read.
        tokio::time::sleep(Duration::from_millis(500)).await;
        let (pending, dropped) = state.outbox_extremes();
        assert!(pending <= 1, "{pending} frames wait for one scene");
        assert!(
            dropped >= 5,
            "only {dropped} frames replaced in 0.5 s at 30 Hz"
        );
        peer.set_blocked(false);
        // What arrives now is a frame or two, not the ~15 ticked while blocked.
        tokio::time::sleep(Duration::from_millis(20)).await;
        let mut burst = 0;
        while peer.recv.try_recv().is_ok() {
            burst += 1;
        }
        assert!(
            burst <= 2,
            "{burst} messages after the stall ({dropped} replaced)"
        );
        state.shutdown();
    }
}
