//! A scene ticked here for the cluster: every tick's frame, the avatars' descriptions and
//! their changes go out on the scene's relay subject (through the feed's tap, a bounded queue
//! and one publishing task), and the scene's request subject is answered: commands forwarded
//! by other servers, the current descriptions and frames for a server that starts relaying,
//! the scene's listing.

use super::identity::{Claim, Signer};
use super::{Cluster, IDEMPOTENCY_KEY, KIND, Reply, Task, lock, relay_subject, request_subject};
use crate::control;
use crate::metrics::Metrics;
use crate::scene::Scene;
use crate::state::Services;
use axum::extract::ws::Message;
use bytes::{BufMut, Bytes, BytesMut};
use futures_util::StreamExt;
use posecast_proto::command::Command;
use posecast_proto::description::AvatarDescription;
use posecast_proto::msg::{AvatarId, ErrorCode, ProtocolError, SceneId};
use posecast_stream::feed::{Relayed, Tap};
use serde::{Deserialize, Serialize};
use std::sync::{Arc, Mutex, Weak};
use std::time::Instant;
use tokio::sync::mpsc;
use tracing::{debug, warn};

/// Messages waiting to be published per scene (about 17 s of ticks at 60 Hz): a frame that
/// finds it full is dropped and counted (`posecast_nats_publish_dropped_total`).
const PUBLISH_QUEUE: usize = 1024;

/// A scene ticked here: the revision of its lease (what the next renewal updates) and the
/// tasks publishing it and answering for it (stopped when this is dropped).
#[derive(Debug)]
pub(super) struct Owned {
    /// The revision of the lease this server created: the epoch its relay messages carry.
    pub(super) epoch: u64,
    pub(super) lease_revision: u64,
    /// The revision of the scene's snapshot this server last wrote or restored.
    pub(super) snapshot_revision: u64,
    /// The bytes of a write whose outcome is unknown (NATS did not answer): if they turn up
    /// in the bucket, they are this server's and are overwritten ([`super::commit`]).
    pub(super) unsure: Option<Bytes>,
    /// Until when the lease is surely this server's (its last renewal's request time plus the
    /// lease time): past it, frames are not published, so a paused owner that wakes up never
    /// interleaves its frames with a new owner's while it finds out.
    held_until: Arc<Mutex<Instant>>,
    _tasks: [Task; 3],
}

impl Owned {
    /// Stops publishing and answering for the scene.
    pub(super) fn stop(self) {}

    /// The lease was renewed: surely held until `until`.
    pub(super) fn renewed(&self, until: Instant) {
        *lock(&self.held_until) = until;
    }
}

/// `avatar_changed` news of one avatar, as relayed.
#[derive(Debug, Serialize, Deserialize)]
pub(super) struct Change {
    pub(super) avatar: AvatarId,
    pub(super) text: String,
}

/// What a relay starts from: the owner's epoch, descriptions and cached frames.
///
/// Layout: epoch (u64 LE), descriptions' JSON length (u32 LE) and JSON array, frame count
/// (u32 LE), then each frame's length (u32 LE) and bytes ([`posecast_stream::relay`]).
pub(super) fn encode_sync(epoch: u64, avatars: &[AvatarDescription], frames: &[Bytes]) -> Bytes {
    let json = serde_json::to_vec(avatars).unwrap_or_else(|_| b"[]".to_vec());
    let mut out = BytesMut::new();
    out.put_u64_le(epoch);
    out.put_u32_le(json.len() as u32);
    out.put_slice(&json);
    out.put_u32_le(frames.len() as u32);
    for f in frames {
        out.put_u32_le(f.len() as u32);
        out.put_slice(f);
    }
    out.freeze()
}

/// Reads [`encode_sync`]'s bytes.
pub(super) fn decode_sync(b: &[u8]) -> Option<(u64, Vec<AvatarDescription>, Vec<Bytes>)> {
    let u32_at = |at: usize| -> Option<usize> {
        Some(u32::from_le_bytes(b.get(at..at + 4)?.try_into().ok()?) as usize)
    };
    let epoch = u64::from_le_bytes(b.get(0..8)?.try_into().ok()?);
    let n = u32_at(8)?;
    let avatars = serde_json::from_slice(b.get(12..12usize.checked_add(n)?)?).ok()?;
    let mut at = 12 + n;
    let count = u32_at(at)?;
    at += 4;
    let mut frames = Vec::new();
    for _ in 0..count {
        let len = u32_at(at)?;
        at += 4;
        frames.push(Bytes::copy_from_slice(b.get(at..at.checked_add(len)?)?));
        at += len;
    }
    Some((epoch, avatars, frames))
}

impl Cluster {
    /// Starts ticking `scene` for the cluster under the lease created at `revision` (its
    /// epoch), its state being the snapshot of revision `snapshot`: its frames are published
    /// from the next tick on and its requests answered.
    pub(super) fn adopt(
        &self,
        state: &Arc<Services>,
        scene: &Arc<Scene>,
        revision: u64,
        snapshot: u64,
    ) {
        let (tx, rx) = mpsc::channel::<(&'static str, Bytes)>(PUBLISH_QUEUE);
        let metrics = state.metrics.clone();
        let tap = Tap(Arc::new(move |relayed: Relayed| {
            let item = match relayed {
                Relayed::Avatars(avatars) => {
                    let avatars: Vec<&AvatarDescription> = avatars.iter().map(|d| &**d).collect();
                    match serde_json::to_vec(&avatars) {
                        Ok(json) => ("avatars", Bytes::from(json)),
                        Err(_) => return,
                    }
                }
                Relayed::Frame(bytes) => ("frame", bytes),
                Relayed::Change { avatar, message } => {
                    let Message::Text(text) = message else { return };
                    let change = Change {
                        avatar,
                        text: text.as_str().to_owned(),
                    };
                    match serde_json::to_vec(&change) {
                        Ok(json) => ("change", Bytes::from(json)),
                        Err(_) => return,
                    }
                }
            };
            if tx.try_send(item).is_err() {
                metrics.cluster.publish_dropped();
            }
        }));
        let held_until = Arc::new(Mutex::new(Instant::now() + self.conn.lease));
        let publisher = tokio::spawn(publish(
            self.conn.client.clone(),
            relay_subject(&scene.id),
            (self.conn.signer.clone(), self.conn.node.clone(), revision),
            rx,
            held_until.clone(),
            state.metrics.clone(),
        ));
        let responder = tokio::spawn(answer(
            self.conn.client.clone(),
            scene.id.clone(),
            revision,
            Arc::downgrade(state),
            self.drivers.clone(),
        ));
        let poses = tokio::spawn(super::drive::serve_poses(
            self.conn.client.clone(),
            scene.id.clone(),
            self.drivers.clone(),
            Arc::downgrade(state),
        ));
        scene.set_tap(Some(tap));
        lock(&self.owned).insert(
            scene.id.clone(),
            Owned {
                epoch: revision,
                lease_revision: revision,
                snapshot_revision: snapshot,
                unsure: None,
                held_until,
                _tasks: [Task(publisher), Task(responder), Task(poses)],
            },
        );
    }
}

/// Publishes what the tap queued, in order, with the owner's epoch — while the lease is surely
/// held (`held_until`); past that, what comes is dropped until a renewal (or a giving up).
/// Every message names this node and its epoch, signed under the cluster secret if any
/// ([`super::identity`]).
async fn publish(
    client: async_nats::Client,
    subject: String,
    (signer, node, epoch): (Signer, String, u64),
    mut rx: mpsc::Receiver<(&'static str, Bytes)>,
    held_until: Arc<Mutex<Instant>>,
    metrics: Arc<Metrics>,
) {
    while let Some((kind, payload)) = rx.recv().await {
        if Instant::now() > *lock(&held_until) {
            debug!(subject, "lease not renewed in time: not published");
            continue;
        }
        let claim = Claim {
            kind: kind.to_owned(),
            epoch,
            node: node.clone(),
        };
        let headers = signer.headers(&subject, &claim, &payload);
        let n = payload.len();
        match client
            .publish_with_headers(subject.clone(), headers, payload)
            .await
        {
            Ok(()) => metrics.cluster.published(n),
            // Disconnected: the client buffers, then refuses; relays resynchronise from the
            // next keyframe.
            Err(e) => debug!(subject, error = %e, "frame not published"),
        }
    }
}

/// Answers the scene's requests until stopped.
async fn answer(
    client: async_nats::Client,
    id: SceneId,
    epoch: u64,
    state: Weak<Services>,
    drivers: super::drive::Drivers,
) {
    let mut requests = match client.subscribe(request_subject(&id)).await {
        Ok(s) => s,
        Err(e) => {
            warn!(scene = %id, error = %e, "cannot answer for the scene");
            return;
        }
    };
    while let Some(msg) = requests.next().await {
        let Some(state) = state.upgrade() else { return };
        state.metrics.cluster.received(msg.payload.len());
        let Some(reply) = msg.reply.clone() else {
            continue;
        };
        let kind = msg
            .headers
            .as_ref()
            .and_then(|h| h.get(KIND))
            .map(|v| v.as_str().to_owned())
            .unwrap_or_default();
        let client = client.clone();
        let id = id.clone();
        let drivers = drivers.clone();
        // Each on its own: a command waiting for its write does not hold up a joiner.
        tokio::spawn(async move {
            let answer = match kind.as_str() {
                "command" => {
                    let key = msg
                        .headers
                        .as_ref()
                        .and_then(|h| h.get(IDEMPOTENCY_KEY))
                        .map(|v| v.as_str().to_owned());
                    let reply = match serde_json::from_slice::<Command>(&msg.payload) {
                        Ok(command) => {
                            match control::execute_here(&state, &command, key.as_deref()).await {
                                Ok(result) => Reply::Ok(result),
                                // Given up meanwhile (another server took the scene over and
                                // got this request too): that server answers, not this one,
                                // whose "not applied" could arrive first and be untrue there.
                                Err(_) if !state.world.scene(&id).is_ok_and(|s| !s.is_relay()) => {
                                    return;
                                }
                                Err(e) => Reply::Error(e.into()),
                            }
                        }
                        Err(e) => Reply::Error(ProtocolError::new(
                            ErrorCode::BadMessage,
                            format!("not a valid command: {e}"),
                        )),
                    };
                    Bytes::from(serde_json::to_vec(&reply).unwrap_or_default())
                }
                "drive" => {
                    let driver = super::drive::driver_of(&msg);
                    let reply = super::drive::answer_drive(&state, &drivers, driver, &msg.payload);
                    Bytes::from(serde_json::to_vec(&reply).unwrap_or_default())
                }
                "sync" => {
                    let Ok(scene) = state.world.scene(&id) else {
                        return;
                    };
                    let s = scene.lock();
                    let avatars: Vec<AvatarDescription> =
                        s.avatars.iter().map(|a| (*a.description).clone()).collect();
                    let frames = scene.feed().cached_frames();
                    drop(s);
                    encode_sync(epoch, &avatars, &frames)
                }
                "info" => {
                    let Ok(scene) = state.world.scene(&id) else {
                        return;
                    };
                    Bytes::from(serde_json::to_vec(&scene.info()).unwrap_or_default())
                }
                _ => return,
            };
            let n = answer.len();
            match client.publish(reply, answer).await {
                Ok(()) => state.metrics.cluster.published(n),
                Err(e) => debug!(error = %e, "answer not sent"),
            }
        });
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The start of a relay reads back what the owner wrote, and refuses a cut message.
    #[test]
    fn sync_round_trips_and_refuses_truncation() {
        let frames = vec![Bytes::from_static(b"key"), Bytes::from_static(b"delta!")];
        let bytes = encode_sync(42, &[], &frames);
        let (epoch, avatars, back) = decode_sync(&bytes).unwrap();
        assert_eq!((epoch, avatars.len(), back), (42, 0, frames));
        for cut in 0..bytes.len() {
            assert!(decode_sync(&bytes[..cut]).is_none(), "cut at {cut}");
        }
    }
}
