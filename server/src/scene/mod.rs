//! Scenes: avatars played on one clock, and the subscribers their frames fan out to.
//!
//! - [`ticker`]: the drift-free tick task of a scene.
//! - `publish`: a frame as per-avatar pieces in both encodings.
//!
//! Every tick a scene samples all its avatars, encodes the frame once per encoding in use
//! (binary always; JSON only while a subscriber wants it) — per avatar chunks first, so
//! subscribers limited to some avatars get the same chunks reassembled — and hands the same
//! bytes to every subscriber's [`Outbox`].

mod publish;
pub mod ticker;

use crate::avatar::Avatar;
use crate::metrics::Metrics;
use crate::stream::outbox::{OutFrame, Outbox, message_len};
use axum::extract::ws::{Message, Utf8Bytes};
use posecast_proto::command::SceneInfo;
use posecast_proto::description::AvatarDescription;
use posecast_proto::frame::{FrameHeader, FrameKind};
use posecast_proto::msg::{AvatarId, Encoding, ErrorCode, ProtocolError, SceneId, ServerMsg};
use publish::{Piece, Published};
use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use tokio::sync::Notify;

/// A connection subscribed to a scene.
#[derive(Debug)]
pub struct Subscriber {
    /// The connection's id (one subscription per connection and scene).
    pub conn: u64,
    /// Where its messages go.
    pub outbox: Arc<Outbox>,
    /// Binary or JSON frames.
    pub encoding: Encoding,
    /// Only these avatars, or all.
    pub filter: Option<Vec<AvatarId>>,
}

impl Subscriber {
    fn wants(&self, avatar: &AvatarId) -> bool {
        self.filter.as_ref().is_none_or(|f| f.contains(avatar))
    }
}

/// What a scene holds, behind its lock.
#[derive(Debug)]
pub struct SceneState {
    /// The avatars, in the order they were added.
    pub avatars: Vec<Avatar>,
    subscribers: Vec<Subscriber>,
    seq: u64,
    /// The scene clock (seconds) at the last tick; avatars added later start on it.
    clock: f64,
    /// Server time of the last tick, µs since the Unix epoch.
    time_us: u64,
    last_key_seq: Option<u64>,
    force_key: bool,
    last_key: Option<Published>,
    last_delta: Option<Published>,
    /// Each avatar's description message, serialised once and shared by every subscriber.
    descriptions: HashMap<AvatarId, (Arc<AvatarDescription>, Message)>,
    /// An avatar was placed since the last tick: the cached frames show the old placement.
    placed: bool,
}

impl SceneState {
    /// The avatar with this id.
    pub fn avatar_mut(&mut self, id: &AvatarId) -> Option<&mut Avatar> {
        self.avatars.iter_mut().find(|a| &a.id == id)
    }

    /// Notes that an avatar was placed: until the next tick, joiners get a keyframe made from
    /// the current poses rather than the cached one.
    pub fn placed(&mut self) {
        self.placed = true;
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
    metrics: Arc<Metrics>,
}

impl Scene {
    /// An empty scene.
    #[must_use]
    pub fn new(id: SceneId, num: u32, metrics: Arc<Metrics>) -> Self {
        Self {
            id,
            num,
            state: Mutex::new(SceneState {
                avatars: Vec::new(),
                subscribers: Vec::new(),
                seq: 0,
                clock: 0.0,
                time_us: 0,
                last_key_seq: None,
                force_key: true,
                last_key: None,
                last_delta: None,
                descriptions: HashMap::new(),
                placed: false,
            }),
            stopped: AtomicBool::new(false),
            stop: Notify::new(),
            metrics,
        }
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
        let mut s = self.lock();
        let msg = text(&ServerMsg::Unsubscribed {
            scene: self.id.clone(),
        });
        for sub in s.subscribers.drain(..) {
            sub.outbox.clear_scene(self.num);
            sub.outbox.push_control(msg.clone());
        }
    }

    /// Whether [`Scene::shut`] was called.
    #[must_use]
    pub fn is_stopped(&self) -> bool {
        self.stopped.load(Ordering::SeqCst)
    }

    /// Adds an avatar; subscribers get its description and the next frame is a keyframe.
    ///
    /// # Errors
    /// [`ErrorCode::Conflict`] when the scene already has an avatar with that id.
    pub fn add_avatar(&self, mut avatar: Avatar) -> Result<(), ProtocolError> {
        let mut s = self.lock();
        avatar.player.set_clock(s.clock);
        if s.avatars.iter().any(|a| a.id == avatar.id) {
            return Err(ProtocolError::new(
                ErrorCode::Conflict,
                format!("scene {} already has avatar {}", self.id, avatar.id),
            ));
        }
        let msg = description_message(&self.id, &mut s.descriptions, &avatar.description);
        for sub in s.subscribers.iter().filter(|sub| sub.wants(&avatar.id)) {
            sub.outbox.push_control(msg.clone());
        }
        s.avatars.push(avatar);
        s.force_key = true;
        Ok(())
    }

    /// Removes an avatar; subscribers are told.
    pub fn remove_avatar(&self, id: &AvatarId) -> Option<Avatar> {
        let mut s = self.lock();
        let index = s.avatars.iter().position(|a| &a.id == id)?;
        let avatar = s.avatars.remove(index);
        s.descriptions.remove(id);
        let msg = text(&ServerMsg::AvatarRemoved {
            scene: self.id.clone(),
            avatar: id.clone(),
        });
        for sub in s.subscribers.iter().filter(|sub| sub.wants(id)) {
            sub.outbox.push_control(msg.clone());
        }
        s.force_key = true;
        Some(avatar)
    }

    /// Subscribes a connection (replacing its previous subscription to this scene). It gets,
    /// in order: `subscribed`, every covered avatar's description, then at once a keyframe
    /// holding every one of them — the current pose, before the next tick: the scene's cached
    /// last keyframe and the newest delta after it, or, when avatars were added, removed or
    /// changed since that keyframe, one made now from their current poses. (Before the scene's
    /// first tick there is none; that tick is a keyframe of every avatar.)
    ///
    /// # Errors
    /// [`ErrorCode::UnknownAvatar`] when the filter names an avatar not in the scene.
    pub fn subscribe(&self, sub: Subscriber) -> Result<(), ProtocolError> {
        let mut guard = self.lock();
        let s = &mut *guard;
        if let Some(filter) = &sub.filter
            && let Some(missing) = filter
                .iter()
                .find(|id| !s.avatars.iter().any(|a| &a.id == *id))
        {
            return Err(ProtocolError::new(
                ErrorCode::UnknownAvatar,
                format!("scene {} has no avatar {missing}", self.id),
            ));
        }
        s.subscribers.retain(|old| old.conn != sub.conn);
        sub.outbox.clear_scene(self.num);
        sub.outbox.push_control(text(&ServerMsg::Subscribed {
            scene: self.id.clone(),
            scene_num: self.num,
        }));
        // Exempt from the outbox's stall bound: a scene of many avatars is not a slow client.
        let descriptions: Vec<Message> = s
            .avatars
            .iter()
            .filter(|a| sub.wants(&a.id))
            .map(|a| description_message(&self.id, &mut s.descriptions, &a.description))
            .collect();
        sub.outbox.push_snapshot(self.num, descriptions);
        self.first_frames(s, &sub);
        s.subscribers.push(sub);
        Ok(())
    }

    /// Hands a new subscriber its first frames (see [`Scene::subscribe`]).
    fn first_frames(&self, s: &mut SceneState, sub: &Subscriber) {
        let filter = sub.filter.as_deref();
        let json = sub.encoding == Encoding::Json;
        let Some(key) = &mut s.last_key else {
            return;
        };
        let wanted = s.avatars.iter().filter(|a| sub.wants(&a.id));
        if !s.placed && key.covers(wanted, |id| sub.wants(id)) {
            if json {
                let mut made = key.ensure_json();
                made += s.last_delta.as_mut().map_or(0, Published::ensure_json);
                self.metrics.json_encoded(made);
            }
            let message = key.message(&self.id, sub.encoding, filter);
            sub.outbox
                .push_frame(self.num, OutFrame { message, key: true });
            if let Some(delta) = &s.last_delta {
                let message = delta.message(&self.id, sub.encoding, filter);
                sub.outbox.push_frame(
                    self.num,
                    OutFrame {
                        message,
                        key: false,
                    },
                );
            }
            return;
        }
        // The cached keyframe predates a change of avatars: a keyframe of the current poses, for
        // this subscriber only, labelled with the last tick.
        let pieces: Vec<Piece> = s
            .avatars
            .iter_mut()
            .filter(|a| sub.wants(&a.id))
            .map(|a| Piece::fresh_key(a, json))
            .collect();
        if json {
            self.metrics.json_encoded(pieces.len() as u64);
        } else {
            // The next tick's deltas would refer to the scene's keyframe, which this subscriber
            // never got: make the next tick a keyframe. (A change of avatars already forces one;
            // this keeps it so whatever the reason the cache was stale.)
            s.force_key = true;
        }
        let fresh = Published {
            header: FrameHeader {
                kind: FrameKind::Key,
                scene_num: self.num,
                seq: s.seq,
                server_time_us: s.time_us,
                base_seq: s.seq,
            },
            pieces,
        };
        let message = fresh.message(&self.id, sub.encoding, filter);
        sub.outbox
            .push_frame(self.num, OutFrame { message, key: true });
    }

    /// Ends a connection's subscription. Returns whether it had one.
    pub fn unsubscribe(&self, conn: u64) -> bool {
        let mut s = self.lock();
        let before = s.subscribers.len();
        s.subscribers.retain(|sub| {
            if sub.conn == conn {
                sub.outbox.clear_scene(self.num);
            }
            sub.conn != conn
        });
        before != s.subscribers.len()
    }

    /// Number of subscribers.
    #[must_use]
    pub fn subscriber_count(&self) -> usize {
        self.lock().subscribers.len()
    }

    /// The listing shown to clients.
    #[must_use]
    pub fn info(&self) -> SceneInfo {
        let s = self.lock();
        SceneInfo {
            scene: self.id.clone(),
            avatars: s.avatars.iter().map(|a| a.state(&self.id)).collect(),
            subscribers: s.subscribers.len(),
        }
    }

    /// One tick: move every avatar to scene clock `clock` (seconds, derived from `seq` by the
    /// ticker, never accumulated), encode the frame for tick `seq` once per encoding, and offer
    /// it to every subscriber. A keyframe when forced (new avatar, new subscriber state) or
    /// when `key_interval` ticks have passed since the last one.
    pub fn tick(&self, seq: u64, clock: f64, server_time_us: u64, key_interval: u64) {
        let mut guard = self.lock();
        let s = &mut *guard;
        s.seq = seq;
        s.clock = clock;
        s.time_us = server_time_us;
        s.placed = false;
        let key = s.force_key
            || s.last_key_seq
                .is_none_or(|k| seq.saturating_sub(k) >= key_interval)
            || s.avatars
                .iter()
                .any(|a| !a.encoder.has_key(a.pose().rotations.len()));
        let kind = if key {
            FrameKind::Key
        } else {
            FrameKind::Delta
        };
        let header = FrameHeader {
            kind,
            scene_num: self.num,
            seq,
            server_time_us,
            base_seq: if key {
                seq
            } else {
                s.last_key_seq.unwrap_or(seq)
            },
        };
        // JSON only while someone reads it; a JSON late joiner gets it made from the cached
        // poses (`first_frames`).
        let json = s
            .subscribers
            .iter()
            .any(|sub| sub.encoding == Encoding::Json);
        let mut pieces = Vec::with_capacity(s.avatars.len());
        for a in &mut s.avatars {
            a.tick(clock);
            pieces.push(Piece::encode(a, kind, json));
        }
        if json {
            self.metrics.json_encoded(pieces.len() as u64);
        }
        let published = Published { header, pieces };
        // Encode once per (encoding, filter); with no filters that is once per encoding.
        let mut cache: HashMap<(Encoding, Option<&[AvatarId]>), Message> = HashMap::new();
        let mut bytes_out = 0u64;
        for sub in &s.subscribers {
            let filter = sub.filter.as_deref();
            let message = cache
                .entry((sub.encoding, filter))
                .or_insert_with(|| published.message(&self.id, sub.encoding, filter))
                .clone();
            bytes_out += message_len(&message) as u64;
            sub.outbox.push_frame(self.num, OutFrame { message, key });
        }
        self.metrics
            .frames_offered(s.subscribers.len() as u64, bytes_out);
        if key {
            s.last_key = Some(published);
            s.last_delta = None;
            s.last_key_seq = Some(seq);
            s.force_key = false;
        } else {
            s.last_delta = Some(published);
        }
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

/// An avatar's description message, from the cache while the description is the same one.
fn description_message(
    scene: &SceneId,
    cache: &mut HashMap<AvatarId, (Arc<AvatarDescription>, Message)>,
    description: &Arc<AvatarDescription>,
) -> Message {
    if let Some((d, m)) = cache.get(&description.id)
        && Arc::ptr_eq(d, description)
    {
        return m.clone();
    }
    let message = text(&ServerMsg::Description {
        scene: scene.clone(),
        avatar: Box::new((**description).clone()),
    });
    cache.insert(
        description.id.clone(),
        (description.clone(), message.clone()),
    );
    message
}

/// A server message as a websocket text message.
#[must_use]
pub fn text(msg: &ServerMsg) -> Message {
    // Serialising these types cannot fail (no maps with non-string keys, no failing Serialize
    // impls); an empty object is sent rather than panicking if that ever changes.
    Message::Text(Utf8Bytes::from(
        serde_json::to_string(msg).unwrap_or_else(|_| "{}".into()),
    ))
}
