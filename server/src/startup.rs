//! Starting and stopping a server: bind and serve at once, load rigs and restore scenes in
//! the background (`restore`).

use crate::app::AppState;
use crate::config::Config;
use crate::restore::{self, data_folder_error};
use crate::service::{app, listener};
use std::net::SocketAddr;
use std::sync::Arc;
use tokio::sync::oneshot;
use tokio::task::JoinHandle;
use tokio::time::Instant;
use tracing::warn;

pub use crate::restore::{DEFAULT_AVATAR, DEFAULT_SCENE};

/// Starts the thread that loads what a server loads at start ahead of [`Server::start`], which
/// then hands it the rest of its work: the built-in avatar, the longest step of a start, is
/// imported while the runtime starts and the server binds instead of after that. A binary
/// calls this first thing; the import is wasted (and dropped) if the server is configured
/// without the built-in avatar.
///
/// # Errors
/// The thread cannot be started (then [`Server::start`] starts one, as without this).
pub fn prepare() -> std::io::Result<()> {
    restore::prepare()
}

/// A running server.
#[derive(Debug)]
pub struct Server {
    /// Where it listens.
    pub addr: SocketAddr,
    /// Its state.
    pub state: Arc<AppState>,
    shutdown: Option<oneshot::Sender<()>>,
    task: JoinHandle<std::io::Result<()>>,
    /// The VMC inputs and outputs ([`crate::vmc`]).
    pub vmc: crate::vmc::Running,
    /// The WebTransport endpoint's accept loop (`--quic-listen`).
    quic: Option<JoinHandle<()>>,
}

impl Server {
    /// Opens the data folder, binds and starts serving at once; the configured rigs (the
    /// built-in avatar, then every asset folder, then the uploads stored in the data folder)
    /// and the stored scenes are loaded in the background (`restore`). Returning means
    /// *listening*: until [`Server::ready`], `/healthz` answers 503 with the progress and
    /// requests that need scenes or assets wait (see [`crate::readiness`]). On a first start
    /// (no data folder, or a new one) the built-in avatar goes into scene `default` playing
    /// `idle` once the rest is loaded, and that is stored. Port 0 picks a free port.
    ///
    /// # Errors
    /// Binding fails, or the data folder cannot be created or written (the error names it).
    pub async fn start(mut config: Config) -> std::io::Result<Self> {
        // Minted tokens: its key is chosen once the data folder is open (below).
        let minter = config
            .access
            .mint
            .get_or_insert_with(|| Arc::new(crate::auth::Minter::new()))
            .clone();
        let state = AppState::new(config.clone());
        tokio::spawn(crate::changes::announce_tick_changes(Arc::downgrade(
            &state.services,
        )));
        // The address first: a busy port is reported as such, and the data folder (maybe
        // another server's) is not touched.
        let listener = tokio::net::TcpListener::bind(config.listen)
            .await
            .map_err(|e| {
                std::io::Error::new(e.kind(), format!("cannot listen on {}: {e}", config.listen))
            })?;
        let addr = listener.local_addr()?;
        // Bound before serving (and before the data folder), so a busy UDP port fails the
        // start like a busy TCP one; a packet that arrives before its avatar is restored waits
        // (`vmc::input`).
        // NATS before anything is served or loaded: an unreachable cluster fails the start,
        // naming the URLs. In a cluster, scene and avatar numbers come from their ids, so
        // every server writes the same frames.
        let cluster = if config.nats.is_empty() {
            None
        } else {
            state.world.number_from_ids();
            Some(crate::cluster::connect(&config, addr.port()).await?)
        };
        let vmc = crate::vmc::start(&state.services).await?;
        let quic = match crate::service::quic::start(&state).await {
            Ok(q) => q,
            Err(e) => {
                vmc.abort();
                return Err(e);
            }
        };
        let abort_quic = || {
            if let Some(q) = &quic {
                q.abort();
            }
        };
        let first_start = match open_data_folder(&state) {
            Ok(first) => first,
            Err(e) => {
                vmc.abort();
                abort_quic();
                return Err(e);
            }
        };
        let key = minter.open(
            config.token_key.as_ref(),
            config.cluster_secret.as_ref(),
            state.store.root(),
        );
        let mut cluster = cluster;
        if let Some(conn) = &mut cluster {
            conn.apply_revocations(&minter);
        }
        match key {
            Ok(source) => tracing::info!(key = ?source, "minted tokens' signing key"),
            Err(e) => {
                vmc.abort();
                abort_quic();
                return Err(e);
            }
        }
        let plan = restore::Plan::new(&state, first_start);
        state.readiness.begin(plan.len());
        // Loading first: it is what `/healthz` waits for, and it goes on while the router is
        // built (until the accept loop runs, a connection waits in the listen backlog).
        if let Err(e) = restore::spawn(state.services.clone(), plan) {
            vmc.abort();
            abort_quic();
            return Err(e);
        }
        let (tx, rx) = oneshot::channel::<()>();
        let router = app(state.clone());
        let task = tokio::spawn(serve(listener, router, state.clone(), rx));
        if let Some(conn) = cluster {
            crate::cluster::start(&state.services, conn);
        }
        Ok(Self {
            addr,
            state,
            shutdown: Some(tx),
            task,
            vmc,
            quic,
        })
    }

    /// Waits until everything loaded at start is loaded and every stored scene restored.
    ///
    /// # Errors
    /// Start-up failed (e.g. a first start could not store the default scene: the error
    /// names the data folder), or the server was shut down first.
    pub async fn ready(&self) -> std::io::Result<()> {
        self.state
            .readiness
            .wait()
            .await
            .map_err(|e| std::io::Error::other(e.to_string()))
    }

    /// The websocket URL.
    #[must_use]
    pub fn ws_url(&self) -> String {
        format!("ws://{}/ws", self.addr)
    }

    /// The HTTP root URL.
    #[must_use]
    pub fn http_url(&self) -> String {
        format!("http://{}", self.addr)
    }

    /// Gracefully stops: scenes end, websockets get close frames, the listener closes.
    pub async fn stop(mut self) {
        self.vmc.abort();
        if let Some(q) = self.quic.take() {
            q.abort();
        }
        if let Some(tx) = self.shutdown.take() {
            tx.send(()).ok();
        }
        self.state.close_connections();
        // The task itself gives up after the drain time; this only guards against a hang.
        let bound = self.state.config.shutdown_drain + std::time::Duration::from_secs(3);
        match tokio::time::timeout(bound, &mut self.task).await {
            Ok(Ok(Err(e))) => warn!(error = %e, "server ended with an error"),
            Ok(_) => {}
            Err(_) => self.task.abort(),
        }
        // Every acknowledged change is on disk: another server may have the folder now.
        self.state.store.release();
    }

    /// Waits until the server task ends.
    ///
    /// # Errors
    /// The server failed.
    pub async fn wait(self) -> std::io::Result<()> {
        match self.task.await {
            Ok(r) => r,
            Err(e) => Err(std::io::Error::other(e)),
        }
    }

    /// A handle that triggers graceful shutdown.
    pub fn take_shutdown(&mut self) -> Option<oneshot::Sender<()>> {
        self.shutdown.take()
    }
}

/// Serves until `shutdown` fires (or its sender is dropped), then shuts down within
/// `Config::shutdown_drain`: every websocket is closed with 1001 Going Away, the accept loop
/// stops and finishes the HTTP requests in flight, and the websocket sessions get the rest
/// of the drain time to send their close frames and receive the answers. Upgraded websockets are
/// not part of the HTTP graceful shutdown, so without that wait a process that returns from
/// `main` would drop them with their close frames still unsent.
async fn serve(
    listener: tokio::net::TcpListener,
    router: axum::Router,
    state: Arc<AppState>,
    shutdown: oneshot::Receiver<()>,
) -> std::io::Result<()> {
    let (began_tx, began) = oneshot::channel::<Instant>();
    let closing = state.clone();
    let serving = listener::serve(
        listener,
        router,
        state.config.net.clone(),
        state.metrics.clone(),
        async move {
            shutdown.await.ok();
            began_tx.send(Instant::now()).ok();
            closing.shutdown();
        },
    );
    tokio::pin!(serving);
    let mut began = began;
    let (began, served) = tokio::select! {
        biased;
        at = &mut began => (at.unwrap_or_else(|_| Instant::now()), false),
        result = &mut serving => match began.try_recv() {
            // With no HTTP request in flight the accept loop ends in the same poll that saw
            // the signal; the websockets still get their drain time below.
            Ok(at) => {
                result?;
                (at, true)
            }
            Err(_) => return result,
        },
    };
    let deadline = began + state.config.shutdown_drain;
    if !served {
        match tokio::time::timeout_at(deadline, &mut serving).await {
            Ok(result) => result?,
            Err(_) => warn!("HTTP requests still running after the shutdown drain time; dropped"),
        }
    }
    let open = state.wait_connections_closed(deadline).await;
    if open > 0 {
        warn!(
            open,
            "websockets still open after the shutdown drain time; dropped"
        );
    }
    Ok(())
}

/// Opens (creates) the data folder and checks that it can be written, so a server that could
/// not store anything refuses to start instead of failing every later command.
fn open_data_folder(state: &AppState) -> std::io::Result<bool> {
    let first_start = state
        .store
        .open()
        .map_err(|e| data_folder_error(state, &e))?;
    if let Some(scenes) = state.store.scenes_dir() {
        let probe = scenes.join(".posecast-write-test.tmp");
        std::fs::write(&probe, b"")
            .and_then(|()| std::fs::remove_file(&probe))
            .map_err(|e| data_folder_error(state, &e))?;
    }
    Ok(first_start)
}
