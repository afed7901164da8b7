//! The transport's state ([`AppState`]): the services' shared [`Services`] (reached through
//! `Deref`) plus what only sockets need — the open connections, the paths' round trips, the
//! probe clock and the WebTransport endpoint. Only `service` and `startup` take it; the
//! services never do (`posecast-services` cannot name it).

use crate::config::Config;
use crate::state::Services;
use posecast_stream::outbox::Outbox;
use posecast_stream::pace::Paths;
use std::collections::HashMap;
use std::sync::{Arc, Mutex, OnceLock, Weak};
use tokio::sync::Notify;

/// Close code of every websocket at server shutdown (RFC 6455 1001, Going Away).
pub const CLOSE_GOING_AWAY: u16 = 1001;
const GOING_AWAY_REASON: &str = "server shutting down";

/// The transport's state: the [`Services`] (reached through `Deref`) plus what only sockets
/// need.
#[derive(Debug)]
pub struct AppState {
    /// What the services share; handed to them on their own (`&state.services`).
    pub services: Arc<Services>,
    connections: Mutex<Connections>,
    /// Notified whenever a connection is unregistered (a shutdown waits on it).
    connection_closed: Notify,
    /// Round trips shared by connections from one address (the adaptive rate's base).
    pub paths: Paths,
    /// The base round trip shared by datagram sessions from one address (nothing else of
    /// theirs is: QUIC paces them).
    pub datagram_paths: Paths,
    /// The clock every subscribed connection's round-trip probes follow (no timer each).
    pub probes: std::sync::Arc<posecast_stream::probes::ProbeClock>,
    /// The WebTransport endpoint (`--quic-listen`), once bound: what `GET /api/quic` tells.
    pub quic: OnceLock<QuicInfo>,
}

impl std::ops::Deref for AppState {
    type Target = Services;
    fn deref(&self) -> &Services {
        &self.services
    }
}
/// Where the WebTransport endpoint listens and how a client trusts it.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize)]
pub struct QuicInfo {
    /// Its UDP port (on the HTTP server's host).
    pub port: u16,
    /// The SHA-256 of its certificate (hex): a browser given it as `serverCertificateHashes`
    /// trusts the self-signed certificate.
    pub cert_sha256: String,
    /// Whether the certificate is the self-signed one made at start (else `--quic-cert`).
    pub self_signed: bool,
}

/// The open websockets' outboxes, and whether the server is shutting down (in one lock, so a
/// connection registered during a shutdown is closed too).
#[derive(Debug, Default)]
struct Connections {
    open: HashMap<u64, Weak<Outbox>>,
    closing: bool,
}

impl AppState {
    /// Empty state: no rigs, no scenes.
    #[must_use]
    pub fn new(config: Config) -> Arc<Self> {
        Arc::new(Self {
            services: Services::new(config),
            connections: Mutex::new(Connections::default()),
            connection_closed: Notify::new(),
            paths: Paths::default(),
            datagram_paths: Paths::default(),
            probes: posecast_stream::probes::ProbeClock::new(),
            quic: OnceLock::new(),
        })
    }

    /// Registers a connection's outbox; returns its id. A connection whose upgrade completes
    /// while the server shuts down is closed at once (1001).
    pub fn register_connection(&self, outbox: &Arc<Outbox>) -> u64 {
        let id = self.services.new_driver_id();
        let mut connections = self.connections_lock();
        connections.open.insert(id, Arc::downgrade(outbox));
        if connections.closing {
            outbox.close_with(CLOSE_GOING_AWAY, GOING_AWAY_REASON);
        }
        id
    }

    /// Forgets a closed connection.
    pub fn unregister_connection(&self, id: u64) {
        self.connections_lock().open.remove(&id);
        self.connection_closed.notify_waiters();
    }

    /// Websockets registered and not yet closed.
    #[must_use]
    pub fn open_connections(&self) -> usize {
        self.connections_lock().open.len()
    }

    /// Waits until every websocket session has ended (its close frame sent, the client's
    /// answer received or given up on), or until `deadline`. Returns how many are still open.
    pub async fn wait_connections_closed(&self, deadline: tokio::time::Instant) -> usize {
        loop {
            // Registered before the count is read, so an unregister in between still wakes it.
            let closed = self.connection_closed.notified();
            let open = self.open_connections();
            if open == 0 || tokio::time::timeout_at(deadline, closed).await.is_err() {
                return open;
            }
        }
    }

    fn connections_lock(&self) -> std::sync::MutexGuard<'_, Connections> {
        self.connections
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// The largest number of frames any connection has waiting, and the most replaced
    /// (dropped) frames on any open connection: the fan-out's memory bound made visible.
    #[must_use]
    pub fn outbox_extremes(&self) -> (usize, u64) {
        self.connections_lock()
            .open
            .values()
            .filter_map(Weak::upgrade)
            .fold((0, 0), |(p, d), o| {
                (p.max(o.pending_frames()), d.max(o.dropped_frames()))
            })
    }

    /// Closes every websocket with a close frame 1001 Going Away (graceful shutdown), and
    /// every one that registers from now on.
    pub fn close_connections(&self) {
        let mut connections = self.connections_lock();
        connections.closing = true;
        for outbox in connections.open.values().filter_map(Weak::upgrade) {
            outbox.close_with(CLOSE_GOING_AWAY, GOING_AWAY_REASON);
        }
    }

    /// Stops every scene and closes every websocket (graceful shutdown); a start-up still
    /// loading gives up.
    pub fn shutdown(&self) {
        self.readiness.stop();
        self.world.shut();
        self.close_connections();
    }
}
