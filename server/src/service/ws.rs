//! One websocket connection: a reader that parses client messages and a writer that drains the
//! connection's [`Outbox`]. Bad input gets a typed error; only a wrong protocol version, a
//! message before `hello`, an oversized message or a client that stops reading closes the
//! connection, and nothing a client sends can affect another connection.

use crate::auth::Caller;
use crate::control;
use crate::scene::ticker::unix_micros;
use crate::scene::{Subscriber, text};
use crate::state::AppState;
use crate::stream::outbox::Outbox;
use crate::stream::writer::run_writer;
use axum::extract::ws::{Message, WebSocket};
use futures_util::StreamExt;
use posecast_proto::msg::{
    ClientMsg, Encoding, ErrorCode, MAX_CLIENT_MESSAGE_BYTES, PROTOCOL_VERSION, ProtocolError,
    SceneId, ServerMsg,
};
use std::sync::Arc;
use tracing::{Instrument, debug, info_span};

/// Serves one upgraded websocket until either side closes.
pub async fn serve(socket: WebSocket, state: Arc<AppState>) {
    let outbox = Arc::new(Outbox::new());
    let conn = state.register_connection(&outbox);
    let span = info_span!("ws", conn, caller = tracing::field::Empty);
    async move {
        state.metrics.connection_opened();
        let (sink, mut stream) = socket.split();
        let writer = {
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
        };
        while let Some(message) = stream.next().await {
            let keep_going = match message {
                Ok(Message::Text(t)) => session.on_text(t.as_str()).await,
                Ok(Message::Binary(_)) => {
                    session.error(ProtocolError::new(
                        ErrorCode::UnexpectedBinary,
                        "clients send JSON text messages only",
                    ));
                    true
                }
                Ok(Message::Close(_)) => false,
                Ok(Message::Ping(_) | Message::Pong(_)) => true,
                Err(e) => {
                    let oversized = e
                        .into_inner()
                        .downcast_ref::<tokio_tungstenite::tungstenite::Error>()
                        .is_some_and(|e| {
                            matches!(e, tokio_tungstenite::tungstenite::Error::Capacity(_))
                        });
                    if oversized {
                        session.error(ProtocolError::new(
                            ErrorCode::MessageTooLarge,
                            format!("messages are limited to {MAX_CLIENT_MESSAGE_BYTES} bytes"),
                        ));
                    }
                    false
                }
            };
            if !keep_going {
                break;
            }
        }
        session.leave_all();
        outbox.close();
        // Give the writer a moment to deliver the last error and the close frame.
        let abort = writer.abort_handle();
        if tokio::time::timeout(std::time::Duration::from_secs(2), writer)
            .await
            .is_err()
        {
            abort.abort();
        }
        state.unregister_connection(conn);
        state.metrics.connection_closed(outbox.dropped_frames());
    }
    .instrument(span)
    .await;
}

struct Session {
    conn: u64,
    state: Arc<AppState>,
    outbox: Arc<Outbox>,
    encoding: Option<Encoding>,
    scenes: Vec<SceneId>,
    caller: Caller,
}

impl Session {
    fn send(&self, msg: &ServerMsg) {
        if !self.outbox.push_control(text(msg)) {
            debug!("outbox full or closed; connection is being closed");
        }
    }

    fn error(&self, e: ProtocolError) {
        match e.code {
            ErrorCode::Unauthorized => self.state.metrics.refused(false),
            ErrorCode::Forbidden => self.state.metrics.refused(true),
            _ => {}
        }
        self.state.metrics.protocol_error();
        self.send(&ServerMsg::Error(e));
    }

    /// Handles one text message; `false` ends the connection.
    async fn on_text(&mut self, text: &str) -> bool {
        let msg: ClientMsg = match serde_json::from_str(text) {
            Ok(m) => m,
            Err(e) => {
                self.error(ProtocolError::new(
                    ErrorCode::BadMessage,
                    format!("not a valid message: {e}"),
                ));
                return true;
            }
        };
        match (self.encoding, msg) {
            (
                None,
                ClientMsg::Hello {
                    version,
                    encoding,
                    token,
                    ..
                },
            ) => {
                if version != PROTOCOL_VERSION {
                    self.error(ProtocolError::new(
                        ErrorCode::UnsupportedVersion,
                        format!("protocol version {version} is not supported; this server speaks {PROTOCOL_VERSION}"),
                    ));
                    return false;
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
            (None, _) => {
                self.error(ProtocolError::new(
                    ErrorCode::NotAllowedNow,
                    "the first message must be hello",
                ));
                false
            }
            (Some(_), ClientMsg::Hello { .. }) => {
                self.error(ProtocolError::new(
                    ErrorCode::NotAllowedNow,
                    "hello was already received",
                ));
                true
            }
            (Some(encoding), ClientMsg::Subscribe { scene, avatars }) => {
                let result = self
                    .state
                    .config
                    .access
                    .authorize_view(&self.caller, &scene)
                    .and_then(|()| self.state.scene(&scene))
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
            (Some(_), ClientMsg::Unsubscribe { scene }) => {
                let had = self
                    .state
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
            (Some(_), ClientMsg::Ping { id, client_time_us }) => {
                self.send(&ServerMsg::Pong {
                    id,
                    client_time_us,
                    server_time_us: unix_micros(),
                });
                true
            }
            (Some(_), ClientMsg::Command { id, command }) => {
                let authorized =
                    self.state
                        .config
                        .access
                        .authorize(&self.caller, &self.state, &command);
                let result = match authorized {
                    Ok(()) => control::execute_durable(&self.state, &command).await,
                    Err(e) => Err(e),
                };
                match result {
                    Ok(result) => {
                        let result =
                            self.state
                                .config
                                .access
                                .visible(&self.caller, &command, result);
                        self.send(&ServerMsg::Ack { id, result });
                    }
                    Err(e) => self.error(e.for_command(id)),
                }
                true
            }
        }
    }

    fn leave_all(&mut self) {
        for scene in self.scenes.drain(..) {
            if let Ok(s) = self.state.scene(&scene) {
                s.unsubscribe(self.conn);
            }
        }
    }
}
