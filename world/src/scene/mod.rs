//! Scenes: avatars played on one clock ([`posecast_sim::avatar`]), published to their
//! subscribers ([`posecast_stream::feed`]).
//!
//! - this module: [`Scene`] — a tick moves every avatar to the scene clock under the scene
//!   lock and copies their poses; the feed encodes and fans out the frame after that lock is
//!   released, under its own.
//! - `ticker`: the drift-free tick task of a scene.
//! - [`answers`]: the answers of its latest commands that carried an idempotency key.

pub mod answers;
pub mod replay;
pub(crate) mod ticker;
pub use ticker::unix_micros;

// Two locks, always taken in this order: the scene's (`Scene::lock`: avatars, clock), then the
// feed's (`Scene::feed`: subscribers, cached frames, encoders). A tick takes the feed's before
// it lets go of the scene's, so anything that needs both (a joiner's first frames, an avatar
// added or removed) sees a tick either wholly before or wholly after it, while commands that
// need only the scene lock run during the tick's encoding and fan-out.

use crate::metrics::Metrics;
use axum::extract::ws::Message;
use bytes::Bytes;
use posecast_core::error::Error;
use posecast_proto::command::SceneInfo;
use posecast_proto::description::AvatarDescription;
use posecast_proto::msg::{AvatarId, SceneId};
use posecast_sim::avatar::Avatar;
use posecast_stream::Snapshot;
use posecast_stream::feed::{Feed, RelayRefused, Subscriber, Tap, TickStamp};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Mutex, MutexGuard};
use std::time::{Duration, Instant};
use tokio::sync::Notify;

/// What a scene holds, behind its lock.
#[derive(Debug)]
pub struct SceneState {
    /// The avatars, in the order they were added.
    pub avatars: Vec<Avatar>,
    /// The last tick.
    last: TickStamp,
    /// The scene clock (seconds) at the last tick; avatars added later start on it.
    clock: f64,
    /// The take it replays, if it is a replay ([`replay`]).
    pub replay: Option<replay::Replay>,
}

impl SceneState {
    /// The avatar with this id.
    pub fn avatar_mut(&mut self, id: &AvatarId) -> Option<&mut Avatar> {
        self.avatars.iter_mut().find(|a| &a.id == id)
    }

    /// The number of the last tick (0 before the first): avatars' clip times are at it.
    #[must_use]
    pub fn last_seq(&self) -> u64 {
        self.last.seq
    }

    /// The scene clock (seconds) at the last tick: `last_seq / tick rate`.
    #[must_use]
    pub fn clock(&self) -> f64 {
        self.clock
    }
}

/// A scene.
#[derive(Debug)]
pub struct Scene {
    /// Its id.
    pub id: SceneId,
    /// Its number in binary frames.
    pub num: u32,
    state: Mutex<SceneState>,
    /// Its subscribers and the frames they share; taken after `state` when both are needed.
    feed: Mutex<Feed>,
    stopped: AtomicBool,
    stop: Notify,
    /// The number of the last tick run, for services that act once per tick (VMC out).
    ticks: tokio::sync::watch::Sender<u64>,
    /// Changed whenever the scene stops being ticked here ([`Scene::stop_ticking`]): its tick
    /// task ends.
    ticker_generation: tokio::sync::watch::Sender<u64>,
    /// Held by a keyed command on a server on its own from before its key is looked up until
    /// its answer is remembered and stored, so two tries of one key never both apply.
    pub keyed: tokio::sync::Mutex<()>,
    /// The answers of its latest keyed commands ([`answers`]), in its snapshot.
    answers: Mutex<answers::Recent>,
    /// A `viewers` message to its watchers is on its way (`posecast_services::changes::viewers_changed`).
    pub viewers_pending: AtomicBool,
    /// Where its ticks report avatars they changed by themselves ([`Scene::report_tick_changes`]).
    tick_changes: std::sync::OnceLock<TickChanges>,
}

/// Avatars a tick changed by itself, which the server announces (`avatar_changed`, or
/// `avatar_removed` for one no longer in the scene): a live driver gone silent past the drive
/// timeout (its `driver` gone, as for a driver that disconnects), and a replay's avatars coming
/// on or going off stage with its take ([`replay`]).
pub type TickChanges = tokio::sync::mpsc::UnboundedSender<(SceneId, AvatarId)>;

impl Scene {
    /// An empty scene ticking at `tick_rate` (the rate subscriptions divide).
    #[must_use]
    pub fn new(id: SceneId, num: u32, metrics: std::sync::Arc<Metrics>, tick_rate: f32) -> Self {
        Self {
            state: Mutex::new(SceneState {
                avatars: Vec::new(),
                last: TickStamp::default(),
                clock: 0.0,
                replay: None,
            }),
            feed: Mutex::new(Feed::new(id.clone(), num, metrics, tick_rate)),
            id,
            num,
            stopped: AtomicBool::new(false),
            stop: Notify::new(),
            ticks: tokio::sync::watch::Sender::new(0),
            ticker_generation: tokio::sync::watch::Sender::new(0),
            keyed: tokio::sync::Mutex::new(()),
            answers: Mutex::new(answers::Recent::new()),
            viewers_pending: AtomicBool::new(false),
            tick_changes: std::sync::OnceLock::new(),
        }
    }

    /// The answers of its latest keyed commands ([`answers`]). Held briefly (no awaits).
    pub fn answers(&self) -> MutexGuard<'_, answers::Recent> {
        self.answers
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// Locks the scene: its avatars and clock. Critical sections are short (no awaits, no
    /// I/O), and every update leaves the state consistent, so a poisoned lock is still usable.
    pub fn lock(&self) -> MutexGuard<'_, SceneState> {
        self.state
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// Locks the scene's feed: its subscribers and cached frames. Alone, or while holding
    /// [`Scene::lock`]'s guard — never the scene lock while holding this one (a tick takes
    /// them in that order).
    pub fn feed(&self) -> MutexGuard<'_, Feed> {
        self.feed
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// Whether the scene has avatar `id` (ticked here, or relayed from its owner).
    #[must_use]
    pub fn has_avatar(&self, id: &AvatarId) -> bool {
        let s = self.lock();
        s.avatars.iter().any(|a| &a.id == id)
            || s.replay.as_ref().is_some_and(|r| r.has_offstage(id))
            || self.feed().relayed_avatars().iter().any(|d| &d.id == id)
    }

    /// Stops the ticker and ends every subscription.
    pub fn shut(&self) {
        self.stopped.store(true, Ordering::SeqCst);
        self.stop.notify_waiters();
        self.feed().close();
    }

    /// Whether [`Scene::shut`] was called.
    #[must_use]
    pub fn is_stopped(&self) -> bool {
        self.stopped.load(Ordering::SeqCst)
    }

    /// Adds an avatar; subscribers get its description and the next frame is a keyframe.
    ///
    /// # Errors
    /// `conflict` when the scene already has an avatar with that id.
    pub fn add_avatar(&self, mut avatar: Avatar) -> Result<(), Error> {
        let mut s = self.lock();
        avatar.player.set_clock(s.clock);
        if s.avatars.iter().any(|a| a.id == avatar.id) {
            return Err(Error::Conflict(format!(
                "scene {} already has avatar {}",
                self.id, avatar.id
            )));
        }
        let mut feed = self.feed();
        feed.avatar_added(&avatar);
        s.avatars.push(avatar);
        feed.tap_avatars(s.avatars.iter().map(|a| &a.description));
        Ok(())
    }

    /// Removes an avatar; subscribers are told.
    pub fn remove_avatar(&self, id: &AvatarId) -> Option<Avatar> {
        let mut s = self.lock();
        let index = s.avatars.iter().position(|a| &a.id == id)?;
        let avatar = s.avatars.remove(index);
        let mut feed = self.feed();
        feed.avatar_removed(&avatar);
        feed.tap_avatars(s.avatars.iter().map(|a| &a.description));
        Some(avatar)
    }

    /// Subscribes a connection ([`Feed::subscribe`]: its first frames come at once).
    ///
    /// # Errors
    /// `unknown_avatar` when the filter names an avatar not in the scene.
    pub fn subscribe(&self, sub: Subscriber) -> Result<(), Error> {
        let mut s = self.lock();
        let last = s.last;
        self.feed().subscribe(&mut s.avatars, last, sub)
    }

    /// Ends a connection's subscription. Returns whether it had one.
    pub fn unsubscribe(&self, conn: u64) -> bool {
        self.feed().unsubscribe(conn)
    }

    /// Number of subscribers.
    #[must_use]
    pub fn subscriber_count(&self) -> usize {
        self.feed().len()
    }

    /// The listing shown to clients.
    #[must_use]
    pub fn info(&self) -> SceneInfo {
        let s = self.lock();
        let avatars = s.avatars.iter().map(|a| a.state(&self.id)).collect();
        // One look at the feed (its lock is not reentrant).
        let feed = self.feed();
        SceneInfo {
            scene: self.id.clone(),
            avatars,
            subscribers: feed.len(),
            owner: None,
            viewers: feed.viewers(),
        }
    }

    /// One tick: move every avatar to scene clock `clock` (seconds, derived from `seq` by the
    /// ticker, never accumulated) and copy their poses, under the scene lock; then publish the
    /// frame of tick `seq` ([`Feed::publish`], a keyframe at least every `key_interval`
    /// ticks) under the feed's lock only. Returns how long the scene lock was held.
    pub fn tick(&self, seq: u64, clock: f64, server_time_us: u64, key_interval: u64) -> Duration {
        let mut s = self.lock();
        let held = Instant::now();
        let mut feed = self.feed();
        if feed.is_relay() {
            // Ticked elsewhere now; this tick task is about to end.
            return held.elapsed();
        }
        s.last = TickStamp {
            seq,
            server_time_us,
        };
        s.clock = clock;
        let state = &mut *s;
        let mut changed = Vec::new();
        if let Some(replay) = &mut state.replay {
            replay.step(clock, &mut state.avatars, &mut feed, &mut changed);
        }
        // Avatars with goals relative to joints tick after the others, their goals' frames
        // taken from the poses of this tick (a hand on a walking avatar's shoulder stays on it).
        let follows = |a: &Avatar| a.goals.references().next().is_some();
        for a in s.avatars.iter_mut().filter(|a| !follows(a)) {
            if a.tick(clock) {
                changed.push(a.id.clone());
            }
        }
        if s.avatars.iter().any(follows) {
            follow_joints(&mut s.avatars);
            for a in s.avatars.iter_mut().filter(|a| follows(a)) {
                if a.tick(clock) {
                    changed.push(a.id.clone());
                }
            }
        }
        if feed.is_recording() {
            feed.note_drivers(
                s.avatars
                    .iter()
                    .filter_map(|a| {
                        let live = a.live.as_ref().filter(|l| l.driver.is_some())?;
                        Some((a.id.clone(), live.by.clone()?))
                    })
                    .collect(),
            );
        }
        let snapshots: Vec<Snapshot> = s.avatars.iter().map(Snapshot::of).collect();
        let at = s.last;
        // The feed's lock was taken before the poses moved, so nothing that needs both locks
        // comes between the poses and their frame; commands on the avatars go on from here.
        drop(s);
        let held = held.elapsed();
        feed.publish(snapshots, at, key_interval);
        drop(feed);
        self.ticks.send_replace(seq);
        if let Some(tell) = self.tick_changes.get() {
            for avatar in changed {
                // The receiver lives as long as the server; after it, nobody is left to tell.
                tell.send((self.id.clone(), avatar)).ok();
            }
        }
        held
    }

    /// Where its ticks report the avatars they changed by themselves ([`TickChanges`])
    /// (set once, by the world that made it; [`crate::world::World::take_tick_changes`]).
    pub fn report_tick_changes(&self, to: TickChanges) {
        self.tick_changes.set(to).ok();
    }

    /// Ends the scene's tick task (the scene goes on, relayed: [`crate::world::World::demote`]).
    pub fn stop_ticking(&self) {
        self.ticker_generation.send_modify(|g| *g += 1);
    }

    /// Changes when the tick task must end ([`Scene::stop_ticking`]).
    #[must_use]
    pub fn ticker_generation(&self) -> tokio::sync::watch::Receiver<u64> {
        self.ticker_generation.subscribe()
    }

    /// Whether the scene is ticked on another server and only relayed here.
    #[must_use]
    pub fn is_relay(&self) -> bool {
        self.feed().is_relay()
    }

    /// Hands every tick's frame and the avatars' descriptions to `tap` ([`Feed::set_tap`]).
    pub fn set_tap(&self, tap: Option<Tap>) {
        self.feed().set_tap(tap);
    }

    /// The cached keyframe and delta as relayed frames ([`Feed::cached_frames`]).
    #[must_use]
    pub fn cached_frames(&self) -> Vec<Bytes> {
        self.feed().cached_frames()
    }

    /// A relayed scene's avatars changed ([`Feed::relay_avatars`]): the avatars gone, with
    /// the connections told.
    pub fn relay_avatars(&self, avatars: Vec<AvatarDescription>) -> Vec<(AvatarId, Vec<u64>)> {
        self.feed().relay_avatars(avatars)
    }

    /// A relayed scene's frame ([`Feed::relay_frame`]).
    ///
    /// # Errors
    /// As [`Feed::relay_frame`].
    pub fn relay_frame(&self, bytes: &[u8]) -> Result<(), RelayRefused> {
        self.feed().relay_frame(bytes)
    }

    /// News of a relayed avatar for the subscribers covering it. Returns their connections.
    pub fn relay_change(&self, avatar: &AvatarId, message: &Message) -> Vec<u64> {
        self.feed().push_change(avatar, message)
    }

    /// A relayed scene's frames now come from a new owner: cached frames are dropped and
    /// subscribers wait for its first keyframe.
    pub fn restart_frames(&self) {
        self.feed().restart_frames();
    }

    /// Tick numbers as ticks run (each change: a tick has run and its poses are set).
    #[must_use]
    pub fn ticks(&self) -> tokio::sync::watch::Receiver<u64> {
        self.ticks.subscribe()
    }

    /// Waits until the scene is shut.
    pub async fn stopped(&self) {
        let notified = self.stop.notified();
        if self.is_stopped() {
            return;
        }
        notified.await;
    }
}

/// Sets every goal frame given relative to a joint to that joint's scene-space matrix now
/// (`P · W_j` of its avatar). A goal whose avatar or joint is gone keeps its last frame.
fn follow_joints(avatars: &mut [Avatar]) {
    let mut frames = Vec::new();
    for (i, a) in avatars.iter().enumerate() {
        for (k, r) in a.goals.references() {
            frames.push((i, k, r.avatar.clone(), r.joint.clone()));
        }
    }
    for (i, k, other, joint) in frames {
        let Some(o) = avatars.iter().position(|a| a.id == other) else {
            continue;
        };
        let Some(j) = avatars[o].rig.joint(&joint) else {
            continue;
        };
        let frame = avatars[o].scene_matrix(j);
        avatars[i].goals.set_frame(k, frame);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use posecast_proto::msg::Encoding;
    use posecast_stream::feed::Relayed;
    use posecast_stream::outbox::Outbox;
    use std::sync::Arc;
    use std::sync::atomic::AtomicUsize;

    /// A tick publishes outside the scene lock: while its frame is being fanned out (the tap
    /// sees each frame from inside `Feed::publish`), the scene lock is free for a command,
    /// and the feed's lock is the one held.
    #[test]
    fn the_frame_is_published_with_the_scene_lock_free() {
        let rig = Arc::new(posecast_rigs::builtin::rig().unwrap());
        let scene = Arc::new(Scene::new(
            SceneId("s".into()),
            1,
            Arc::new(Metrics::new()),
            60.0,
        ));
        let mut avatar = Avatar::new(AvatarId("a".into()), 1, rig.clone());
        let walk = rig.clip("walk").unwrap().clone();
        avatar.play(
            posecast_sim::avatar::playback::Layer::new(walk, None, 0.0, 1.0, true),
            0.0,
        );
        scene.add_avatar(avatar).unwrap();
        let outbox = Arc::new(Outbox::new());
        scene
            .subscribe(Subscriber::new(7, outbox, Encoding::Binary, None, 1))
            .unwrap();
        let frames = Arc::new(AtomicUsize::new(0));
        let free = Arc::new(AtomicUsize::new(0));
        let seen = scene.clone();
        let (f, fr) = (frames.clone(), free.clone());
        scene.set_tap(Some(Tap(Arc::new(move |relayed| {
            if let Relayed::Frame(_) = relayed {
                f.fetch_add(1, Ordering::SeqCst);
                let scene_free = seen.state.try_lock().is_ok();
                let feed_held = seen.feed.try_lock().is_err();
                if scene_free && feed_held {
                    fr.fetch_add(1, Ordering::SeqCst);
                }
            }
        }))));
        for seq in 1..=5u64 {
            let held = scene.tick(seq, seq as f64 / 60.0, seq, 60);
            assert!(held < Duration::from_secs(5));
        }
        scene.set_tap(None);
        assert_eq!(frames.load(Ordering::SeqCst), 5, "a frame per tick");
        assert_eq!(
            free.load(Ordering::SeqCst),
            5,
            "every frame fanned out with the scene lock free and the feed's held"
        );
    }
}
