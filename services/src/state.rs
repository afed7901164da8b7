//! What the services that run commands share ([`Services`]): configuration, the [`World`],
//! the data folder, takes, start-up progress, the scene-list watchers, counters and the
//! cluster. `control`, `ingest`, `changes`, `live`, `vmc`, `restore` and `cluster` take it (or
//! less: a function that reads only the world takes the [`World`]); none of them sees a socket,
//! a path's pacing or the connection table — those are the transport's (`posecast-server`'s
//! `app::AppState`, which holds the services).

use crate::auth::{AccessConfig, Caller};
use crate::config::Config;
use crate::metrics::Metrics;
use crate::readiness::Readiness;
use crate::store::Store;
use crate::world::World;
use axum::extract::ws::Message;
use futures_util::future::BoxFuture;
use posecast_core::error::Error;
use posecast_proto::command::{Command, CommandResult, SceneInfo};
use posecast_proto::msg::SceneId;
use posecast_rigs::import::files::FileSet;
use posecast_rigs::rig::PipelineOptions;
use posecast_stream::outbox::Outbox;
use std::sync::OnceLock;

use std::collections::HashMap;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Mutex, Weak};

/// What the services that run commands share (the module doc says who takes it).
#[derive(Debug)]
pub struct Services {
    /// How the server runs.
    pub config: Config,
    /// The scenes and rigs (the domain every command acts on).
    pub world: World,
    /// Counters (shared with the world).
    pub metrics: Arc<Metrics>,
    /// Connection and live-driver ids: one space, so a VMC input's driver id is never a
    /// connection's.
    next_id: AtomicU64,
    /// The data folder (or none) and the lock ordering writes to it.
    pub store: Store,
    /// Takes of whole scenes, stored and being recorded ([`crate::takes`]).
    pub takes: Arc<crate::takes::Takes>,
    /// Whether what is loaded at start is loaded yet ([`crate::readiness`]).
    pub readiness: Readiness,
    /// The connections watching the scene list ([`crate::changes`]).
    pub watchers: Watchers,
    /// The cluster this server is part of (`--nats`), once joined.
    cluster: OnceLock<Arc<dyn Cluster>>,
}

/// How a command [`Cluster::commit`] runs failed.
#[derive(Debug)]
pub enum RunError {
    /// Refused: nothing was changed.
    Refused(Error),
    /// Applied in memory, then not stored in the data folder (the commit undoes it).
    NotStored(Error),
}

impl RunError {
    /// The error to answer with.
    #[must_use]
    pub fn into_error(self) -> Error {
        match self {
            Self::Refused(e) | Self::NotStored(e) => e,
        }
    }
}

/// What a cluster of servers (scale-out through NATS, `crate::cluster`) does for the services
/// that run commands: set once the server has joined ([`Services::join_cluster`]).
pub trait Cluster: Send + Sync + std::fmt::Debug {
    /// `Some` when `command` acts on a scene ticked by another server: the future sends it
    /// there (with the client's idempotency `key`) and answers with that server's answer.
    fn forward<'a>(
        &'a self,
        command: &'a Command,
        key: Option<&'a str>,
    ) -> Option<BoxFuture<'a, Result<CommandResult, Error>>>;
    /// Runs `run` — `command` applied here to scene `scene` and stored in this server's data
    /// folder — and stores the scene where every server reads it, before the command is
    /// acknowledged (`create_scene` claims the id cluster-wide first). Commands on one scene
    /// commit one at a time, and the write to the cluster is conditioned on this server still
    /// owning the scene (fencing): a command that cannot be stored, for a stale owner's sake or
    /// NATS's, is undone here and answered with an error — it changes nothing, then or later.
    /// `key`, the client's idempotency key: a key the scene's latest commands carried is
    /// answered with that command's result, without running `run` again.
    ///
    /// # Errors
    /// `run`'s error; `unavailable` when the scene is not ticked here (any longer) or could not
    /// be stored; `conflict` for a key used by another kind of command.
    fn commit<'a>(
        &'a self,
        command: &'a Command,
        scene: &'a SceneId,
        key: Option<&'a str>,
        run: BoxFuture<'a, Result<CommandResult, RunError>>,
    ) -> BoxFuture<'a, Result<CommandResult, Error>>;
    /// The scene list of the whole cluster, from this server's own `local` listing.
    fn listing(&self, local: Vec<SceneInfo>) -> BoxFuture<'_, Vec<SceneInfo>>;
    /// Whether the connection to NATS is lost (local scenes are still served).
    fn degraded(&self) -> bool;
    /// Tells every server of the cluster that minted token `id` is revoked until `until`
    /// (Unix seconds), before the revocation is acknowledged; each server refuses it from then
    /// on and closes the connections holding it.
    ///
    /// # Errors
    /// `unavailable` when it could not be stored (it is revoked on this server all the same).
    fn revoke_token<'a>(&'a self, id: &'a str, until: u64) -> BoxFuture<'a, Result<(), Error>>;
    /// Stores uploaded asset `name` (its files and pipeline options) where every server can
    /// read it, before the upload (or its new clips or options) is acknowledged; every server
    /// imports it from there.
    ///
    /// # Errors
    /// `unavailable` when it could not be stored.
    fn share_asset<'a>(
        &'a self,
        name: &'a str,
        files: &'a FileSet,
        options: &'a PipelineOptions,
    ) -> BoxFuture<'a, Result<(), Error>>;
    /// Removes asset `name` from the cluster's store (an upload that failed here after it
    /// was shared).
    fn unshare_asset<'a>(&'a self, name: &'a str) -> BoxFuture<'a, ()>;
    /// The files of uploaded asset `name` as the cluster stores them (`None`: not there).
    ///
    /// # Errors
    /// `unavailable` when NATS cannot be read; `internal` when the stored copy is unusable.
    fn shared_asset<'a>(&'a self, name: &'a str) -> BoxFuture<'a, Result<Option<FileSet>, Error>>;
    /// Stores recorded clip `clip` of rig `rig` (`glb`: the file `DIR/recordings` holds)
    /// where every server can read it, before `stop_recording` is acknowledged; every server
    /// puts it on its rig from there.
    ///
    /// # Errors
    /// `unavailable` when it could not be stored.
    fn share_recording<'a>(
        &'a self,
        rig: &'a str,
        clip: &'a str,
        glb: Vec<u8>,
    ) -> BoxFuture<'a, Result<(), Error>>;
    /// Removes recorded clip `clip` of rig `rig` from the cluster's store (`delete_clip`),
    /// best effort: a server restoring it later finds it gone.
    fn unshare_recording<'a>(&'a self, rig: &'a str, clip: &'a str) -> BoxFuture<'a, ()>;
    /// The takes in the cluster's store, described as they were put.
    ///
    /// # Errors
    /// `unavailable` when NATS cannot be read.
    fn shared_takes(&self) -> BoxFuture<'_, Result<Vec<posecast_proto::command::TakeInfo>, Error>>;
    /// Whether the cluster's store has take `take`.
    ///
    /// # Errors
    /// `unavailable` when NATS cannot be read.
    fn has_take<'a>(&'a self, take: &'a str) -> BoxFuture<'a, Result<bool, Error>>;
    /// Puts take `take`, ended here, into the cluster's store (before `stop_recording_scene`
    /// answers; the lease loop retries what fails).
    ///
    /// # Errors
    /// `unavailable` when it could not be stored.
    fn share_take<'a>(&'a self, take: &'a str) -> BoxFuture<'a, Result<(), Error>>;
    /// Makes this server's copy of take `take` the cluster's current one (read, or deleted
    /// when the cluster no longer has it); returns whether the cluster has it.
    ///
    /// # Errors
    /// `unavailable` (NATS), `quota_exceeded` (no room here for the copy).
    fn fetch_take<'a>(&'a self, take: &'a str) -> BoxFuture<'a, Result<bool, Error>>;
    /// Removes take `take` from the cluster's store; returns whether it was there.
    ///
    /// # Errors
    /// `unavailable` when NATS cannot be reached.
    fn delete_take<'a>(&'a self, take: &'a str) -> BoxFuture<'a, Result<bool, Error>>;
    /// Sends `drive` (`command`) for an avatar of scene `scene`, ticked elsewhere, to the
    /// scene's owner, which drives the avatar for connection `conn` of this server; answers
    /// with the owner's answer.
    fn drive<'a>(
        &'a self,
        scene: &'a SceneId,
        conn: u64,
        command: &'a Command,
    ) -> BoxFuture<'a, Result<CommandResult, Error>>;
    /// Passes a live pose of connection `conn` (a [`posecast_proto::live::BinaryPose`],
    /// checked here) to the owner of `scene`. Dropped and counted when the queue to NATS is
    /// full.
    fn pose(&self, scene: &SceneId, conn: u64, pose: Vec<u8>);
    /// Connection `conn` left: the owner of `scene` releases the avatars it drives there.
    fn release(&self, scene: &SceneId, conn: u64);
}

impl Services {
    /// Empty services: no rigs, no scenes.
    #[must_use]
    pub fn new(config: Config) -> Arc<Self> {
        let metrics = Arc::new(Metrics::new());
        let takes = Arc::new(
            crate::takes::Takes::new(config.data_dir.as_deref())
                .counting(metrics.takes.written(), metrics.takes.ended()),
        );
        Arc::new(Self {
            world: World::new(config.tick_rate, config.quotas.clone(), metrics.clone()),
            metrics,
            next_id: AtomicU64::new(1),
            store: Store::new(config.data_dir.clone()),
            takes,
            readiness: Readiness::default(),
            watchers: Watchers::default(),
            cluster: OnceLock::new(),
            config,
        })
    }

    /// The cluster this server has joined, if any.
    #[must_use]
    pub fn cluster(&self) -> Option<&Arc<dyn Cluster>> {
        self.cluster.get()
    }

    /// Joins a cluster (once: a second call is ignored and returns `false`).
    pub fn join_cluster(&self, cluster: Arc<dyn Cluster>) -> bool {
        self.cluster.set(cluster).is_ok()
    }

    /// A new live-driver id that no connection has (VMC inputs drive avatars with one).
    pub fn new_driver_id(&self) -> u64 {
        self.next_id.fetch_add(1, Ordering::Relaxed)
    }
}

/// The connections that asked for scene-list changes (`watch_scenes`), with who they are (a
/// token limited to some scenes hears only of those, when views are private).
#[derive(Debug, Default)]
pub struct Watchers {
    watching: Mutex<HashMap<u64, Watcher>>,
}

#[derive(Debug)]
struct Watcher {
    outbox: Weak<Outbox>,
    caller: Caller,
}

impl Watchers {
    fn lock(&self) -> std::sync::MutexGuard<'_, HashMap<u64, Watcher>> {
        // Every update is one insert or remove: a poisoned lock is still consistent.
        self.watching
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// Connection `conn` watches the scene list from now on (again: no change).
    pub fn watch(&self, conn: u64, outbox: &Arc<Outbox>, caller: Caller) {
        self.lock().insert(
            conn,
            Watcher {
                outbox: Arc::downgrade(outbox),
                caller,
            },
        );
    }

    /// Connection `conn` stops watching (it asked, or it closed).
    pub fn unwatch(&self, conn: u64) {
        self.lock().remove(&conn);
    }

    /// How many connections watch.
    #[must_use]
    pub fn len(&self) -> usize {
        self.lock().len()
    }

    /// Whether nobody watches.
    #[must_use]
    pub fn is_empty(&self) -> bool {
        self.lock().is_empty()
    }

    /// Hands `message` about `scene` to every watcher that may watch it, except the
    /// connections in `told`.
    pub(crate) fn push(
        &self,
        access: &AccessConfig,
        scene: &SceneId,
        message: &Message,
        told: &[u64],
    ) {
        for (conn, w) in self.lock().iter() {
            if told.contains(conn) || access.authorize_view(&w.caller, scene).is_err() {
                continue;
            }
            if let Some(outbox) = w.outbox.upgrade() {
                outbox.push_control(message.clone());
            }
        }
    }
}
