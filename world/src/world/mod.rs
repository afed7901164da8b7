//! The world: every scene and the rigs avatars are made of — what commands act on.
//!
//! - this module: [`World`] — scenes by id, the rig [`Library`], the retargeting cache, unique
//!   scene numbers and avatar ids, and the scene and avatar quotas.
//! - [`command`]: the control commands, one handler each — what each needs, where it runs,
//!   what it announces, and its change to the world (the same code behind REST, the websocket
//!   and restoring stored scenes).
//!
//! The world knows nothing of connections, tokens or the data folder: those are services
//! built on it (`posecast_services::auth`, `posecast_services::store`, `posecast_services::state`).

pub mod command;
pub mod replays;

use crate::metrics::Metrics;
use crate::scene::{Scene, TickChanges, ticker};
use posecast_core::error::Error;
use posecast_core::quota::{Quota, Quotas};
use posecast_proto::msg::{AvatarId, SceneId, check_id};
use posecast_proto::placement::Placement;
use posecast_rigs::clip::Clip;
use posecast_rigs::library::Library;
use posecast_sim::avatar::Avatar;
use posecast_sim::bake::RetargetCache;
use std::collections::BTreeMap;
use std::sync::atomic::{AtomicBool, AtomicU32, Ordering};
use std::sync::{Arc, Mutex, RwLock};

/// Every scene, and the rigs their avatars are made of.
#[derive(Debug)]
pub struct World {
    /// Loaded rigs.
    pub library: Library,
    /// Baked retargeted clips (`play … from_asset`), see [`posecast_sim::bake`].
    pub retargets: RetargetCache,
    /// Counters (ticks, quota refusals).
    pub metrics: Arc<Metrics>,
    quotas: Quotas,
    tick_rate: f32,
    scenes: RwLock<BTreeMap<SceneId, Arc<Scene>>>,
    next_scene_num: AtomicU32,
    next_avatar_num: AtomicU32,
    /// Held from the "is this avatar id free?" check to the insertion, so two scenes cannot
    /// both take one id.
    avatar_ids: Mutex<()>,
    /// Scene and avatar numbers derived from their ids (servers of a cluster agree on them).
    numbers_from_ids: AtomicBool,
    /// Every scene's ticks report the avatars they changed by themselves here
    /// ([`World::take_tick_changes`]).
    tick_changes: TickChanges,
    tick_changes_rx: Mutex<Option<TickChangesRx>>,
}

/// What [`World::take_tick_changes`] hands out: `(scene, avatar)` for each avatar a tick
/// changed by itself ([`crate::scene::TickChanges`]).
pub type TickChangesRx = tokio::sync::mpsc::UnboundedReceiver<(SceneId, AvatarId)>;

/// A number for a binary frame derived from an id: 32-bit FNV-1a, never 0. Servers of a
/// cluster derive the same numbers for the same scenes and avatars without asking each other,
/// so frames and descriptions are the same bytes on every server and after a failover.
#[must_use]
pub fn number_of(id: &str) -> u32 {
    let mut h: u32 = 0x811c_9dc5;
    for b in id.bytes() {
        h ^= u32::from(b);
        h = h.wrapping_mul(0x0100_0193);
    }
    h.max(1)
}

impl World {
    /// An empty world whose scenes tick at `tick_rate` Hz, within `quotas`.
    #[must_use]
    pub fn new(tick_rate: f32, quotas: Quotas, metrics: Arc<Metrics>) -> Self {
        let (tick_changes, rx) = tokio::sync::mpsc::unbounded_channel();
        Self {
            tick_changes,
            tick_changes_rx: Mutex::new(Some(rx)),
            library: Library::new(),
            retargets: RetargetCache::default(),
            metrics,
            quotas,
            tick_rate,
            scenes: RwLock::new(BTreeMap::new()),
            next_scene_num: AtomicU32::new(1),
            next_avatar_num: AtomicU32::new(1),
            avatar_ids: Mutex::new(()),
            numbers_from_ids: AtomicBool::new(false),
        }
    }

    /// The avatars scenes' ticks change by themselves (once: the server's
    /// announcer takes it at start, `posecast_services::changes::announce_tick_changes`; later calls get
    /// `None`).
    pub fn take_tick_changes(&self) -> Option<TickChangesRx> {
        self.tick_changes_rx
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .take()
    }

    /// From now on scenes and avatars are numbered by [`number_of`] their id (cluster mode);
    /// an id whose number another scene or avatar holds is refused as a conflict.
    pub fn number_from_ids(&self) {
        self.numbers_from_ids.store(true, Ordering::SeqCst);
    }

    /// Adds a scene ticked on another server, relayed here ([`Scene::is_relay`]): no ticker,
    /// no quota. It takes the number its owner gives it ([`number_of`]).
    ///
    /// # Errors
    /// Invalid id, or `conflict` when it exists.
    pub fn insert_relay(&self, id: SceneId) -> Result<Arc<Scene>, Error> {
        self.insert(id, false, false)
    }

    /// Makes a relayed scene one ticked here (its owner is gone and this server took it over):
    /// its subscribers stay, and get a keyframe at its first tick here. Returns it.
    ///
    /// # Errors
    /// `unknown_scene`; `conflict` when the scene is already ticked here.
    pub fn promote(&self, id: &SceneId) -> Result<Arc<Scene>, Error> {
        let scene = self.scene(id)?;
        {
            let mut feed = scene.feed();
            if !feed.is_relay() {
                return Err(Error::Conflict(format!(
                    "scene {id} is ticked here already"
                )));
            }
            feed.end_relay();
        }
        tokio::spawn(ticker::run(
            scene.clone(),
            self.tick_rate,
            self.metrics.clone(),
        ));
        Ok(scene)
    }

    /// The limits the world enforces (and the services on it: uploads, retargeting).
    #[must_use]
    pub fn quotas(&self) -> &Quotas {
        &self.quotas
    }

    /// A scene by id.
    ///
    /// # Errors
    /// `unknown_scene`.
    pub fn scene(&self, id: &SceneId) -> Result<Arc<Scene>, Error> {
        self.scenes
            .read()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .get(id)
            .cloned()
            .ok_or_else(|| Error::UnknownScene(id.clone()))
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
    /// Invalid id, `conflict` when it exists, or `quota_exceeded` past
    /// [`posecast_core::quota::Quotas::max_scenes`].
    pub fn create_scene(&self, id: SceneId) -> Result<Arc<Scene>, Error> {
        self.insert_scene(id, true)
    }

    /// [`World::create_scene`] without the scene quota: restoring what was stored.
    ///
    /// # Errors
    /// Invalid id, or `conflict` when it exists.
    pub fn restore_scene(&self, id: SceneId) -> Result<Arc<Scene>, Error> {
        self.insert_scene(id, false)
    }

    /// Makes a scene ticked here a relayed one (another server owns it now): its tick task
    /// ends and its avatars leave this server, while its subscribers stay subscribed (the
    /// descriptions they hold are kept, so the owner's, the same, are not sent again).
    ///
    /// # Errors
    /// `unknown_scene`; `conflict` when the scene is relayed already.
    pub fn demote(&self, id: &SceneId) -> Result<Arc<Scene>, Error> {
        let scene = self.scene(id)?;
        {
            let mut s = scene.lock();
            let mut feed = scene.feed();
            if feed.is_relay() {
                return Err(Error::Conflict(format!("scene {id} is relayed already")));
            }
            let described = s.avatars.iter().map(|a| a.description.clone()).collect();
            s.avatars.clear();
            // A take of it ends here (it is shared as it is); a replay goes on where the
            // scene's new server resumes it.
            drop(feed.record(None));
            s.replay = None;
            feed.begin_relay(described);
        }
        scene.stop_ticking();
        Ok(scene)
    }

    fn insert_scene(&self, id: SceneId, quota: bool) -> Result<Arc<Scene>, Error> {
        self.insert(id, quota, true)
    }

    /// Whether scene `id` could be created here now: what [`World::create_scene`] would refuse
    /// before making anything. A cluster asks before it claims the id cluster-wide, so that a
    /// refusal here is never seen by the other servers.
    ///
    /// # Errors
    /// As [`World::create_scene`].
    pub fn room_for_scene(&self, id: &SceneId) -> Result<(), Error> {
        let scenes = self
            .scenes
            .read()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        self.check_new_scene(&scenes, id, true)
    }

    fn check_new_scene(
        &self,
        scenes: &BTreeMap<SceneId, Arc<Scene>>,
        id: &SceneId,
        quota: bool,
    ) -> Result<(), Error> {
        check_id("scene", &id.0).map_err(|e| Error::invalid_field("scene", e.message))?;
        if scenes.contains_key(id) {
            return Err(Error::Conflict(format!("scene {id} exists")));
        }
        let max = self.quotas.max_scenes;
        if quota && scenes.len() >= max {
            return Err(self.metrics.refuse_quota(
                Quota::Scenes,
                format!("scene {id} would be scene {}", scenes.len() + 1),
                max,
            ));
        }
        Ok(())
    }

    fn insert(&self, id: SceneId, quota: bool, ticked: bool) -> Result<Arc<Scene>, Error> {
        let mut scenes = self
            .scenes
            .write()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        self.check_new_scene(&scenes, &id, quota)?;
        let num = if self.numbers_from_ids.load(Ordering::SeqCst) {
            let num = number_of(&id.0);
            if let Some(other) = scenes.values().find(|s| s.num == num) {
                return Err(Error::Conflict(format!(
                    "scene {id} would share frame number {num} with scene {}: choose another id",
                    other.id
                )));
            }
            num
        } else {
            self.next_scene_num.fetch_add(1, Ordering::Relaxed)
        };
        let scene = Arc::new(Scene::new(
            id.clone(),
            num,
            self.metrics.clone(),
            self.tick_rate,
        ));
        scene.report_tick_changes(self.tick_changes.clone());
        if !ticked {
            scene.feed().begin_relay(Vec::new());
        }
        scenes.insert(id, scene.clone());
        if ticked {
            tokio::spawn(ticker::run(
                scene.clone(),
                self.tick_rate,
                self.metrics.clone(),
            ));
        }
        Ok(scene)
    }

    /// Deletes a scene: its ticker stops and its subscribers are unsubscribed.
    ///
    /// # Errors
    /// `unknown_scene`.
    pub fn delete_scene(&self, id: &SceneId) -> Result<(), Error> {
        let scene = self
            .scenes
            .write()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .remove(id)
            .ok_or_else(|| Error::UnknownScene(id.clone()))?;
        scene.shut();
        Ok(())
    }

    /// Adds an avatar of rig `asset` to a scene. Returns its id.
    ///
    /// # Errors
    /// Unknown scene or rig, invalid or duplicate id, or `quota_exceeded` past
    /// [`posecast_core::quota::Quotas::max_avatars_per_scene`].
    pub fn add_avatar(
        &self,
        scene: &SceneId,
        asset: &str,
        id: Option<AvatarId>,
    ) -> Result<(Arc<Scene>, AvatarId), Error> {
        self.insert_avatar(scene, asset, id, true, Placement::IDENTITY)
    }

    /// [`World::add_avatar`] (with its quota when `quota`, as restoring has none) standing
    /// at `placement` from its first frame on.
    ///
    /// # Errors
    /// As [`World::add_avatar`].
    pub fn add_avatar_at(
        &self,
        scene: &SceneId,
        asset: &str,
        id: Option<AvatarId>,
        placement: Placement,
        quota: bool,
    ) -> Result<(Arc<Scene>, AvatarId), Error> {
        self.insert_avatar(scene, asset, id, quota, placement)
    }

    /// [`World::add_avatar`] without the avatar quota: restoring what was stored.
    ///
    /// # Errors
    /// Unknown scene or rig, invalid or duplicate id.
    pub fn restore_avatar(
        &self,
        scene: &SceneId,
        asset: &str,
        id: Option<AvatarId>,
    ) -> Result<(Arc<Scene>, AvatarId), Error> {
        self.insert_avatar(scene, asset, id, false, Placement::IDENTITY)
    }

    fn insert_avatar(
        &self,
        scene: &SceneId,
        asset: &str,
        id: Option<AvatarId>,
        quota: bool,
        placement: Placement,
    ) -> Result<(Arc<Scene>, AvatarId), Error> {
        let scene = self.scene(scene)?;
        let rig = self.library.require(asset)?;
        let seq = self.next_avatar_num.fetch_add(1, Ordering::Relaxed);
        let id = id.unwrap_or_else(|| AvatarId(format!("{}-{seq}", rig.name)));
        check_id("avatar", &id.0).map_err(|e| Error::invalid_field("avatar", e.message))?;
        let by_id = self.numbers_from_ids.load(Ordering::SeqCst);
        let num = if by_id { number_of(&id.0) } else { seq };
        let mut avatar = Avatar::new(id.clone(), num, rig);
        avatar.place(placement, 0.0);
        // Ids are unique across scenes, and each scene checks only its own: the check of every
        // scene and the insertion must not interleave with another add.
        let _adding = self
            .avatar_ids
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        if self.find_avatar(&id).is_ok() {
            return Err(Error::Conflict(format!("avatar {id} exists")));
        }
        if by_id
            && let Some(other) = self.scenes().iter().find_map(|scene| {
                let s = scene.lock();
                s.avatars
                    .iter()
                    .map(|a| a.description.clone())
                    .chain(scene.feed().relayed_avatars().iter().cloned())
                    .find(|d| d.num == num)
                    .map(|d| d.id.clone())
            })
        {
            return Err(Error::Conflict(format!(
                "avatar {id} would share frame number {num} with avatar {other}: choose another id"
            )));
        }
        // Checked under the same lock as the insertion: concurrent adds cannot overshoot.
        let max = self.quotas.max_avatars_per_scene;
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
    /// `unknown_avatar`.
    pub fn find_avatar(&self, id: &AvatarId) -> Result<Arc<Scene>, Error> {
        self.scenes()
            .into_iter()
            .find(|s| s.has_avatar(id))
            .ok_or_else(|| Error::UnknownAvatar(id.clone()))
    }

    /// Adds `clip` to rig `rig` ([`Library::add_clip`]) and moves every avatar of that rig
    /// onto the new one, so each of them can play it at once. Returns the new rig.
    ///
    /// # Errors
    /// As [`Library::add_clip`].
    pub fn add_clip(&self, rig: &str, clip: Clip) -> Result<Arc<posecast_rigs::rig::Rig>, Error> {
        self.add_clips(rig, vec![clip])
    }

    /// [`World::add_clip`] for several clips at once (restoring a rig's recordings).
    ///
    /// # Errors
    /// As [`Library::add_clips`].
    pub fn add_clips(
        &self,
        rig: &str,
        clips: Vec<Clip>,
    ) -> Result<Arc<posecast_rigs::rig::Rig>, Error> {
        let new = self.library.add_clips(rig, clips)?;
        self.move_avatars_to(&new);
        Ok(new)
    }

    /// Takes clip `clip` off rig `rig` and moves every avatar of the rig onto the new one.
    /// With `unless_playing`, refuses (`conflict`, naming the avatar) while an avatar plays
    /// it — on its own rig or retargeted (`from_asset`) — and changes nothing.
    ///
    /// # Errors
    /// `unknown_asset`, `unknown_clip`, or `conflict`.
    pub fn remove_clip(&self, rig: &str, clip: &str, unless_playing: bool) -> Result<(), Error> {
        if unless_playing && let Some(avatar) = self.playing(rig, Some(clip)) {
            return Err(Error::Conflict(format!(
                "avatar {avatar} plays clip {clip} of rig {rig}: stop it first"
            )));
        }
        let new = self.library.remove_clip(rig, clip)?;
        self.move_avatars_to(&new);
        Ok(())
    }

    /// An avatar that plays `clip` of rig `rig` (any clip of it when `None`) or, for `None`,
    /// is made of the rig: what `delete_clip` and `delete_asset` refuse to take away.
    #[must_use]
    pub fn playing(&self, rig: &str, clip: Option<&str>) -> Option<AvatarId> {
        let retargeted = clip.map(|c| format!("{rig}:{c}"));
        for scene in self.scenes() {
            let s = scene.lock();
            for a in &s.avatars {
                if clip.is_none() && a.rig.name == rig {
                    return Some(a.id.clone());
                }
                let Some(layer) = a.player.current() else {
                    continue;
                };
                let name = layer.clip.name();
                let plays = match (&layer.source_asset, clip) {
                    (Some(src), None) => src == rig,
                    (Some(src), Some(_)) => src == rig && Some(name) == retargeted.as_deref(),
                    (None, Some(c)) => a.rig.name == rig && name == c,
                    (None, None) => false,
                };
                if plays {
                    return Some(a.id.clone());
                }
            }
        }
        None
    }

    fn move_avatars_to(&self, new: &Arc<posecast_rigs::rig::Rig>) {
        for scene in self.scenes() {
            for a in scene.lock().avatars.iter_mut() {
                if a.rig.name == new.name {
                    a.rig = new.clone();
                }
            }
        }
    }

    /// Stops every scene's ticker and ends its subscriptions.
    pub fn shut(&self) {
        for scene in self.scenes() {
            scene.shut();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use posecast_proto::msg::ErrorCode;
    use posecast_rigs::builtin::BUILTIN_ASSET;

    /// Many adds of one id into different scenes at the same moment: exactly one wins, every
    /// other one is a conflict, and the id ends up in one scene only.
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn concurrent_adds_of_one_avatar_id_into_different_scenes_take_it_once() {
        const SCENES: usize = 8;
        let state = Arc::new(World::new(1.0, Quotas::default(), Arc::new(Metrics::new())));
        state.library.insert(posecast_rigs::builtin::rig().unwrap());
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
                    .all(|e| e.code() == ErrorCode::Conflict),
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
