//! Scenes: avatars played on one clock ([`posecast_sim::avatar`]), published to their subscribers
//! ([`crate::stream::feed`]), under one lock so a joiner's first frames and the next tick are
//! in order.
//!
//! - this module: [`Scene`] — a tick moves every avatar to the scene clock, then the feed
//!   encodes and fans out the frame.
//! - `ticker`: the drift-free tick task of a scene.
//! - [`answers`]: the answers of its latest commands that carried an idempotency key.

pub mod answers;
pub(crate) mod ticker;

use crate::metrics::Metrics;
use crate::stream::feed::{Feed, RelayRefused, Subscriber, Tap, TickStamp};
use axum::extract::ws::Message;
use bytes::Bytes;
use posecast_core::error::Error;
use posecast_proto::command::SceneInfo;
use posecast_proto::description::AvatarDescription;
use posecast_proto::msg::{AvatarId, SceneId};
use posecast_sim::avatar::Avatar;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Mutex, MutexGuard};
use tokio::sync::Notify;

/// What a scene holds, behind its lock.
#[derive(Debug)]
pub struct SceneState {
    /// The avatars, in the order they were added.
    pub avatars: Vec<Avatar>,
    /// Its subscribers and the frames they share.
    pub feed: Feed,
    /// The last tick.
    last: TickStamp,
    /// The scene clock (seconds) at the last tick; avatars added later start on it.
    clock: f64,
}

impl SceneState {
    /// The avatar with this id.
    pub fn avatar_mut(&mut self, id: &AvatarId) -> Option<&mut Avatar> {
        self.avatars.iter_mut().find(|a| &a.id == id)
    }

    /// Whether the scene has avatar `id` (ticked here, or relayed from its owner).
    #[must_use]
    pub fn has_avatar(&self, id: &AvatarId) -> bool {
        self.avatars.iter().any(|a| &a.id == id)
            || self.feed.relayed_avatars().iter().any(|d| &d.id == id)
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
}

impl Scene {
    /// An empty scene ticking at `tick_rate` (the rate subscriptions divide).
    #[must_use]
    pub fn new(id: SceneId, num: u32, metrics: std::sync::Arc<Metrics>, tick_rate: f32) -> Self {
        Self {
            state: Mutex::new(SceneState {
                avatars: Vec::new(),
                feed: Feed::new(id.clone(), num, metrics, tick_rate),
                last: TickStamp::default(),
                clock: 0.0,
            }),
            id,
            num,
            stopped: AtomicBool::new(false),
            stop: Notify::new(),
            ticks: tokio::sync::watch::Sender::new(0),
            ticker_generation: tokio::sync::watch::Sender::new(0),
            keyed: tokio::sync::Mutex::new(()),
            answers: Mutex::new(answers::Recent::new()),
        }
    }

    /// The answers of its latest keyed commands ([`answers`]). Held briefly (no awaits).
    pub fn answers(&self) -> MutexGuard<'_, answers::Recent> {
        self.answers
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// Locks the scene. Critical sections are short (no awaits, no I/O), and every update
    /// leaves the state consistent, so a poisoned lock is still usable.
    pub fn lock(&self) -> MutexGuard<'_, SceneState> {
        self.state
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// Stops the ticker and ends every subscription.
    pub fn shut(&self) {
        self.stopped.store(true, Ordering::SeqCst);
        self.stop.notify_waiters();
        self.lock().feed.close();
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
        s.feed.avatar_added(&avatar);
        s.avatars.push(avatar);
        let s = &mut *s;
        s.feed.tap_avatars(&s.avatars);
        Ok(())
    }

    /// Removes an avatar; subscribers are told.
    pub fn remove_avatar(&self, id: &AvatarId) -> Option<Avatar> {
        let mut s = self.lock();
        let index = s.avatars.iter().position(|a| &a.id == id)?;
        let avatar = s.avatars.remove(index);
        s.feed.avatar_removed(&avatar);
        let s = &mut *s;
        s.feed.tap_avatars(&s.avatars);
        Some(avatar)
    }

    /// Subscribes a connection ([`Feed::subscribe`]: its first frames come at once).
    ///
    /// # Errors
    /// `unknown_avatar` when the filter names an avatar not in the scene.
    pub fn subscribe(&self, sub: Subscriber) -> Result<(), Error> {
        let mut guard = self.lock();
        let s = &mut *guard;
        s.feed.subscribe(&mut s.avatars, s.last, sub)
    }

    /// Ends a connection's subscription. Returns whether it had one.
    pub fn unsubscribe(&self, conn: u64) -> bool {
        self.lock().feed.unsubscribe(conn)
    }

    /// Number of subscribers.
    #[must_use]
    pub fn subscriber_count(&self) -> usize {
        self.lock().feed.len()
    }

    /// The listing shown to clients.
    #[must_use]
    pub fn info(&self) -> SceneInfo {
        let s = self.lock();
        SceneInfo {
            scene: self.id.clone(),
            avatars: s.avatars.iter().map(|a| a.state(&self.id)).collect(),
            subscribers: s.feed.len(),
            owner: None,
        }
    }

    /// One tick: move every avatar to scene clock `clock` (seconds, derived from `seq` by the
    /// ticker, never accumulated), then publish the frame of tick `seq`
    /// ([`Feed::publish`], a keyframe at least every `key_interval` ticks).
    pub fn tick(&self, seq: u64, clock: f64, server_time_us: u64, key_interval: u64) {
        let mut guard = self.lock();
        let s = &mut *guard;
        if s.feed.is_relay() {
            // Ticked elsewhere now; this tick task is about to end.
            return;
        }
        s.last = TickStamp {
            seq,
            server_time_us,
        };
        s.clock = clock;
        for a in &mut s.avatars {
            a.tick(clock);
        }
        s.feed.publish(&s.avatars, s.last, key_interval);
        drop(guard);
        self.ticks.send_replace(seq);
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
        self.lock().feed.is_relay()
    }

    /// Hands every tick's frame and the avatars' descriptions to `tap` ([`Feed::set_tap`]).
    pub fn set_tap(&self, tap: Option<Tap>) {
        self.lock().feed.set_tap(tap);
    }

    /// The cached keyframe and delta as relayed frames ([`Feed::cached_frames`]).
    #[must_use]
    pub fn cached_frames(&self) -> Vec<Bytes> {
        self.lock().feed.cached_frames()
    }

    /// A relayed scene's avatars changed ([`Feed::relay_avatars`]): the avatars gone, with
    /// the connections told.
    pub fn relay_avatars(&self, avatars: Vec<AvatarDescription>) -> Vec<(AvatarId, Vec<u64>)> {
        self.lock().feed.relay_avatars(avatars)
    }

    /// A relayed scene's frame ([`Feed::relay_frame`]).
    ///
    /// # Errors
    /// As [`Feed::relay_frame`].
    pub fn relay_frame(&self, bytes: &[u8]) -> Result<(), RelayRefused> {
        self.lock().feed.relay_frame(bytes)
    }

    /// News of a relayed avatar for the subscribers covering it. Returns their connections.
    pub fn relay_change(&self, avatar: &AvatarId, message: &Message) -> Vec<u64> {
        self.lock().feed.push_change(avatar, message)
    }

    /// A relayed scene's frames now come from a new owner: cached frames are dropped and
    /// subscribers wait for its first keyframe.
    pub fn restart_frames(&self) {
        self.lock().feed.restart_frames();
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
