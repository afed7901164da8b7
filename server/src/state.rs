//! The server's shared state: configuration, loaded rigs, scenes, counters.

use crate::auth::AccessConfig;
use crate::bake::RetargetCache;
use crate::library::Library;
use crate::metrics::Metrics;
use crate::quota::Quota;
use crate::readiness::Readiness;
use crate::scene::avatar::Avatar;
use crate::scene::{Scene, ticker};
use crate::service::limits::NetLimits;
use crate::store::Store;
use crate::stream::outbox::Outbox;
use posecast_proto::msg::{AvatarId, ErrorCode, ProtocolError, SceneId, check_id};
use posecast_proto::placement::Placement;
use std::collections::BTreeMap;
use std::collections::HashMap;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::atomic::{AtomicU32, AtomicU64, Ordering};
use std::sync::{Arc, RwLock};
use std::sync::{Mutex, Weak};
use std::time::Duration;
use tokio::sync::Notify;

/// How the server runs (built by `main` from flags and environment).
#[derive(Debug, Clone)]
pub struct Config {
    /// Listen address.
    pub listen: SocketAddr,
    /// Pose frames per second of every scene.
    pub tick_rate: f32,
    /// Folders whose assets are loaded at start.
    pub asset_dirs: Vec<PathBuf>,
    /// Whether to load the built-in avatar into a `default` scene playing `idle`.
    pub builtin: bool,
    /// Tokens and what they allow ([`crate::auth`]).
    pub access: AccessConfig,
    /// The data folder scenes and uploads are stored in (see [`crate::store`]); `None` keeps
    /// everything in memory only.
    pub data_dir: Option<PathBuf>,
    /// Largest upload request body, bytes.
    pub max_upload_bytes: usize,
    /// Limits on scenes, avatars, rig and clip sizes, upload bytes ([`crate::quota`]).
    pub quotas: crate::quota::Quotas,
    /// Commands per second per connection ([`crate::quota::CommandRate`]).
    pub command_rate: crate::quota::CommandRate,
    /// How long a graceful shutdown waits, at most, for HTTP requests to finish and for every
    /// websocket's close frame to be sent (and answered) before the server stops regardless.
    pub shutdown_drain: Duration,

    // --- Live driving (issue 16) ---
    /// How long a live driver may stay silent before its avatar returns to its clip (or holds
    /// its last pose, as the `drive` asked).
    pub drive_timeout: Duration,
    /// Network timeouts and connection caps ([`crate::service::limits`]).
    pub net: NetLimits,
}

/// Default [`Config::max_upload_bytes`]: 32 MiB.
pub const DEFAULT_MAX_UPLOAD_BYTES: usize = 32 << 20;

/// Default [`Config::shutdown_drain`]: 2 s.
pub const DEFAULT_SHUTDOWN_DRAIN: Duration = Duration::from_secs(2);

/// Default [`Config::drive_timeout`]: 2 s.
pub const DEFAULT_DRIVE_TIMEOUT: Duration = Duration::from_secs(2);

/// Close code of every websocket at server shutdown (RFC 6455 1001, Going Away).
pub const CLOSE_GOING_AWAY: u16 = 1001;
const GOING_AWAY_REASON: &str = "server shutting down";

impl Default for Config {
    fn default() -> Self {
        Self {
            listen: SocketAddr::from(([127, 0, 0, 1], 8080)),
            tick_rate: 60.0,
            asset_dirs: Vec::new(),
            builtin: true,
            access: AccessConfig::default(),
            data_dir: None,
            max_upload_bytes: DEFAULT_MAX_UPLOAD_BYTES,
            quotas: crate::quota::Quotas::default(),
            command_rate: crate::quota::CommandRate::default(),
            shutdown_drain: DEFAULT_SHUTDOWN_DRAIN,
            drive_timeout: DEFAULT_DRIVE_TIMEOUT,
            net: NetLimits::default(),
        }
    }
}

/// Shared by every task of the server.
#[derive(Debug)]
pub struct AppState {
    /// How the server runs.
    pub config: Config,
    /// Loaded rigs.
    pub library: Library,
    /// Counters.
    pub metrics: Arc<Metrics>,
    scenes: RwLock<BTreeMap<SceneId, Arc<Scene>>>,
    next_scene_num: AtomicU32,
    next_avatar_num: AtomicU32,
    next_conn: AtomicU64,
    connections: Mutex<Connections>,
    /// Notified whenever a connection is unregistered (a shutdown waits on it).
    connection_closed: Notify,
    /// Held from the "is this avatar id free?" check to the insertion, so two scenes cannot
    /// both take one id.
    avatar_ids: Mutex<()>,
    /// The data folder (or none) and the lock ordering writes to it.
    pub store: Store,
    /// Baked retargeted clips (`play … from_asset`), see [`crate::bake`].
    pub retargets: RetargetCache,
    /// Whether what is loaded at start is loaded yet ([`crate::readiness`]).
    pub readiness: Readiness,
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
            library: Library::new(),
            metrics: Arc::new(Metrics::new()),
            scenes: RwLock::new(BTreeMap::new()),
            next_scene_num: AtomicU32::new(1),
            next_avatar_num: AtomicU32::new(1),
            next_conn: AtomicU64::new(1),
            connections: Mutex::new(Connections::default()),
            connection_closed: Notify::new(),
            avatar_ids: Mutex::new(()),
            store: Store::new(config.data_dir.clone()),
            retargets: RetargetCache::default(),
            readiness: Readiness::default(),
            config,
        })
    }

    /// Registers a connection's outbox; returns its id. A connection whose upgrade completes
    /// while the server shuts down is closed at once (1001).
    pub fn register_connection(&self, outbox: &Arc<Outbox>) -> u64 {
        let id = self.next_conn.fetch_add(1, Ordering::Relaxed);
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

    /// A scene by id.
    ///
    /// # Errors
    /// [`ErrorCode::UnknownScene`].
    pub fn scene(&self, id: &SceneId) -> Result<Arc<Scene>, ProtocolError> {
        self.scenes
            .read()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .get(id)
            .cloned()
            .ok_or_else(|| ProtocolError::new(ErrorCode::UnknownScene, format!("no scene {id}")))
    }

    /// Every scene.
    #[must_use]
    pub fn scenes(&self) -> Vec<Arc<Scene>> {
        self.scenes
            .read()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .values()
            .cloned()
            .collect()
    }

    /// Creates a scene and starts its tick task (must run inside a tokio runtime).
    ///
    /// # Errors
    /// Invalid id, [`ErrorCode::Conflict`] when it exists, or `quota_exceeded` past
    /// [`crate::quota::Quotas::max_scenes`].
    pub fn create_scene(&self, id: SceneId) -> Result<Arc<Scene>, ProtocolError> {
        self.insert_scene(id, true)
    }

    /// [`AppState::create_scene`] without the scene quota: restoring what was stored.
    ///
    /// # Errors
    /// Invalid id, or [`ErrorCode::Conflict`] when it exists.
    pub fn restore_scene(&self, id: SceneId) -> Result<Arc<Scene>, ProtocolError> {
        self.insert_scene(id, false)
    }

    fn insert_scene(&self, id: SceneId, quota: bool) -> Result<Arc<Scene>, ProtocolError> {
        check_id("scene", &id.0)?;
        let mut scenes = self
            .scenes
            .write()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        if scenes.contains_key(&id) {
            return Err(ProtocolError::new(
                ErrorCode::Conflict,
                format!("scene {id} exists"),
            ));
        }
        let max = self.config.quotas.max_scenes;
        if quota && scenes.len() >= max {
            return Err(self.metrics.refuse_quota(
                Quota::Scenes,
                format!("scene {id} would be scene {}", scenes.len() + 1),
                max,
            ));
        }
        let num = self.next_scene_num.fetch_add(1, Ordering::Relaxed);
        let scene = Arc::new(Scene::new(id.clone(), num, self.metrics.clone()));
        scenes.insert(id, scene.clone());
        tokio::spawn(ticker::run(
            scene.clone(),
            self.config.tick_rate,
            self.metrics.clone(),
        ));
        Ok(scene)
    }

    /// Deletes a scene: its ticker stops and its subscribers are unsubscribed.
    ///
    /// # Errors
    /// [`ErrorCode::UnknownScene`].
    pub fn delete_scene(&self, id: &SceneId) -> Result<(), ProtocolError> {
        let scene = self
            .scenes
            .write()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .remove(id)
            .ok_or_else(|| ProtocolError::new(ErrorCode::UnknownScene, format!("no scene {id}")))?;
        scene.shut();
        Ok(())
    }

    /// Adds an avatar of rig `asset` to a scene. Returns its id.
    ///
    /// # Errors
    /// Unknown scene or rig, invalid or duplicate id, or `quota_exceeded` past
    /// [`crate::quota::Quotas::max_avatars_per_scene`].
    pub fn add_avatar(
        &self,
        scene: &SceneId,
        asset: &str,
        id: Option<AvatarId>,
    ) -> Result<(Arc<Scene>, AvatarId), ProtocolError> {
        self.insert_avatar(scene, asset, id, true, Placement::IDENTITY)
    }

    /// [`AppState::add_avatar`] (with its quota when `quota`, as restoring has none) standing
    /// at `placement` from its first frame on.
    ///
    /// # Errors
    /// As [`AppState::add_avatar`].
    pub fn add_avatar_at(
        &self,
        scene: &SceneId,
        asset: &str,
        id: Option<AvatarId>,
        placement: Placement,
        quota: bool,
    ) -> Result<(Arc<Scene>, AvatarId), ProtocolError> {
        self.insert_avatar(scene, asset, id, quota, placement)
    }

    /// [`AppState::add_avatar`] without the avatar quota: restoring what was stored.
    ///
    /// # Errors
    /// Unknown scene or rig, invalid or duplicate id.
    pub fn restore_avatar(
        &self,
        scene: &SceneId,
        asset: &str,
        id: Option<AvatarId>,
    ) -> Result<(Arc<Scene>, AvatarId), ProtocolError> {
        self.insert_avatar(scene, asset, id, false, Placement::IDENTITY)
    }

    fn insert_avatar(
        &self,
        scene: &SceneId,
        asset: &str,
        id: Option<AvatarId>,
        quota: bool,
        placement: Placement,
    ) -> Result<(Arc<Scene>, AvatarId), ProtocolError> {
        let scene = self.scene(scene)?;
        let rig = self.library.require(asset)?;
        let num = self.next_avatar_num.fetch_add(1, Ordering::Relaxed);
        let id = id.unwrap_or_else(|| AvatarId(format!("{}-{num}", rig.name)));
        check_id("avatar", &id.0)?;
        let mut avatar = Avatar::new(id.clone(), num, rig);
        avatar.place(placement, 0.0);
        // Ids are unique across scenes, and each scene checks only its own: the check of every
        // scene and the insertion must not interleave with another add.
        let _adding = self
            .avatar_ids
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        if self.find_avatar(&id).is_ok() {
            return Err(ProtocolError::new(
                ErrorCode::Conflict,
                format!("avatar {id} exists"),
            ));
        }
        // Checked under the same lock as the insertion: concurrent adds cannot overshoot.
        let max = self.config.quotas.max_avatars_per_scene;
        let count = scene.lock().avatars.len();
        if quota && count >= max {
            return Err(self.metrics.refuse_quota(
                Quota::AvatarsPerScene,
                format!("scene {} has {count} avatars", scene.id),
                max,
            ));
        }
        scene.add_avatar(avatar)?;
        Ok((scene, id))
    }

    /// The scene holding an avatar.
    ///
    /// # Errors
    /// [`ErrorCode::UnknownAvatar`].
    pub fn find_avatar(&self, id: &AvatarId) -> Result<Arc<Scene>, ProtocolError> {
        self.scenes()
            .into_iter()
            .find(|s| s.lock().avatars.iter().any(|a| &a.id == id))
            .ok_or_else(|| ProtocolError::new(ErrorCode::UnknownAvatar, format!("no avatar {id}")))
    }

    /// Stops every scene and closes every websocket (graceful shutdown); a start-up still
    /// loading gives up.
    pub fn shutdown(&self) {
        self.readiness.stop();
        for scene in self.scenes() {
            scene.shut();
        }
        self.close_connections();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::builtin::BUILTIN_ASSET;

    /// Many adds of one id into different scenes at the same moment: exactly one wins, every
    /// other one is a conflict, and the id ends up in one scene only.
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn concurrent_adds_of_one_avatar_id_into_different_scenes_take_it_once() {
        const SCENES: usize = 8;
        let state = AppState::new(Config {
            tick_rate: 1.0,
            ..Config::default()
        });
        state.library.insert(crate::builtin::rig().unwrap());
        let scene = |i: usize| SceneId(format!("s{i}"));
        for i in 0..SCENES {
            state.create_scene(scene(i)).unwrap();
        }
        for round in 0..40 {
            let id = AvatarId(format!("racer-{round}"));
            let barrier = Arc::new(std::sync::Barrier::new(SCENES));
            let threads: Vec<_> = (0..SCENES)
                .map(|i| {
                    let (state, id, barrier) = (state.clone(), id.clone(), barrier.clone());
                    std::thread::spawn(move || {
                        barrier.wait();
                        state
                            .add_avatar(&scene(i), BUILTIN_ASSET, Some(id))
                            .map(|_| ())
                    })
                })
                .collect();
            let results: Vec<_> = threads.into_iter().map(|t| t.join().unwrap()).collect();
            let won = results.iter().filter(|r| r.is_ok()).count();
            assert_eq!(won, 1, "round {round}: {results:?}");
            assert!(
                results
                    .iter()
                    .filter_map(|r| r.as_ref().err())
                    .all(|e| e.code == ErrorCode::Conflict),
                "{results:?}"
            );
            let holders = state
                .scenes()
                .iter()
                .filter(|s| s.lock().avatars.iter().any(|a| a.id == id))
                .count();
            assert_eq!(holders, 1, "round {round}");
        }
        for s in state.scenes() {
            s.shut();
        }
    }
}
