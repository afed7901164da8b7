//! A scene ticked by another server, relayed here: its owner's frames, descriptions and
//! avatar changes fanned out to this server's subscribers through the scene's feed (the same
//! bytes and outbox rules as on the owner, [`posecast_stream::feed::Feed::relay_frame`]).
//!
//! A relay starts by subscribing to the scene's relay subject, then asks the owner for its
//! descriptions and cached keyframe and delta (so a joiner here gets the current pose at once,
//! as on the owner); live frames not newer than those are skipped. Every message carries the
//! owner's epoch: an older owner's are ignored, a newer owner's first drops the frames kept
//! from the old one (its first frame is a keyframe). A frame naming an avatar not described
//! here (descriptions lost when the owner's queue to NATS was full) makes the relay ask the
//! owner for its descriptions again.
//!
//! **Who is believed** (issue 36): a message counts only if its MAC holds under the cluster
//! secret (when one is set), it names the node that holds the scene's lease, and its epoch is
//! one that lease can have made — not above the lease's revision (an epoch of 2^63 would
//! otherwise make the relay ignore the real owner for good). When a message fails the check
//! the lease is read again (at most every [`LEASE_RECHECK`]: an owner that just took over is
//! believed within that), then it is dropped and counted
//! (`posecast_cluster_relay_refused_total`). `deleted` is believed from the lease holder only
//! once the scene's key is gone from the scenes bucket.

use super::identity::{Claim, Refused, Signer};
use super::owner::{Change, decode_sync};
use super::{Cluster, KIND, REQUEST_TIMEOUT, Task, key, lock, relay_subject, request_subject};
use crate::metrics::Metrics;
use crate::scene::Scene;
use crate::state::Services;
use async_nats::jetstream::kv;
use axum::extract::ws::{Message, Utf8Bytes};
use bytes::Bytes;
use futures_util::StreamExt;
use posecast_proto::description::AvatarDescription;
use posecast_proto::msg::{AvatarId, SceneId, ServerMsg};
use posecast_stream::feed::RelayRefused;
use posecast_stream::feed::text;
use posecast_stream::relay::peek_seq;
use std::sync::{Arc, Weak};
use std::time::{Duration, Instant};
use tracing::{debug, warn};

/// How often a relay asks again for an owner that did not answer its first request.
const SYNC_RETRY: Duration = Duration::from_millis(200);
/// How often, at most, a relay asks the owner again for descriptions it missed.
const RESYNC_INTERVAL: Duration = Duration::from_secs(1);
/// How often, at most, a relay reads a scene's lease again for a message it does not believe.
const LEASE_RECHECK: Duration = Duration::from_millis(200);

/// The lease of a relayed scene as this server last read it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(super) struct LeaseView {
    /// The node holding it.
    pub(super) owner: String,
    /// Its latest revision (an owner's epoch is the revision it created it at: never more).
    pub(super) revision: u64,
}

impl LeaseView {
    /// Whether `claim` comes from this lease's holder with an epoch it can have made.
    fn believes(&self, claim: &Claim) -> Result<(), Refused> {
        if claim.node != self.owner {
            return Err(Refused::NotOwner);
        }
        if claim.epoch > self.revision {
            return Err(Refused::Epoch);
        }
        Ok(())
    }
}

/// A scene relayed here: who owns it, and the task relaying it (stopped when dropped).
#[derive(Debug)]
pub(super) struct Relayed {
    pub(super) owner: String,
    view: Arc<std::sync::Mutex<LeaseView>>,
    _task: Task,
}

impl Relayed {
    /// Stops relaying (the scene itself stays in the world).
    pub(super) fn stop(self) {}
}

impl Cluster {
    /// Relays scene `id`, owned by `owner`, to this server's subscribers (from now on, if it
    /// is not relayed yet).
    pub(super) fn relay(&self, state: &Arc<Services>, id: &SceneId, owner: String, revision: u64) {
        let view = LeaseView {
            owner: owner.clone(),
            revision,
        };
        let missing = state.world.scene(id).is_err();
        {
            let mut relays = lock(&self.relays);
            if let Some(r) = relays.get_mut(id) {
                if !missing {
                    r.owner = owner;
                    *lock(&r.view) = view;
                    return;
                }
                // Registered, but its scene went meanwhile (deleted here while the cluster
                // kept it): relayed afresh below, or the scene would be missing here for good.
                warn!(scene = %id, "a relayed scene was missing here: relaying it again");
                if let Some(stale) = relays.remove(id) {
                    stale.stop();
                }
            }
        }
        let scene = match state.world.scene(id) {
            Ok(scene) if scene.is_relay() => scene,
            Ok(_) => {
                warn!(scene = %id, owner, "scene ticked here is leased to another server: giving it up");
                self.give_up(&state.world, id);
                return;
            }
            Err(_) => match state.world.insert_relay(id.clone()) {
                Ok(scene) => {
                    // Scene-list watchers here hear of it as of one created here.
                    let msg = text(&ServerMsg::SceneCreated { scene: id.clone() });
                    state.watchers.push(&state.config.access, id, &msg, &[]);
                    scene
                }
                Err(e) => {
                    warn!(scene = %id, error = %e, "cannot relay the scene");
                    return;
                }
            },
        };
        let view = Arc::new(std::sync::Mutex::new(view));
        let task = tokio::spawn(run(
            self.conn.client.clone(),
            scene,
            state.metrics.clone(),
            Arc::downgrade(state),
            Trust {
                signer: self.conn.signer.clone(),
                view: view.clone(),
                leases: self.conn.leases.clone(),
                scenes: self.conn.scenes.clone(),
            },
        ));
        lock(&self.relays).insert(
            id.clone(),
            Relayed {
                owner,
                view,
                _task: Task(task),
            },
        );
    }

    /// Stops relaying a scene the cluster no longer has, and removes it here.
    pub(super) fn drop_relay(&self, state: &Services, id: &SceneId) {
        if let Some(r) = lock(&self.relays).remove(id) {
            r.stop();
            if state.world.delete_scene(id).is_ok() {
                deleted(state, id);
            }
        }
    }
}

/// Tells this server's scene-list watchers that a relayed scene is gone.
fn deleted(state: &Services, id: &SceneId) {
    let msg = text(&ServerMsg::SceneDeleted { scene: id.clone() });
    state.watchers.push(&state.config.access, id, &msg, &[]);
}

/// Tells this server's scene-list watchers that avatars of a relayed scene left (those
/// subscribed to it were told by its feed).
fn removed(state: &Weak<Services>, id: &SceneId, gone: Vec<(AvatarId, Vec<u64>)>) {
    let Some(state) = state.upgrade() else { return };
    for (avatar, told) in gone {
        let msg = text(&ServerMsg::AvatarRemoved {
            scene: id.clone(),
            avatar,
        });
        state.watchers.push(&state.config.access, id, &msg, &told);
    }
}

/// What a relay checks its messages against.
struct Trust {
    signer: Signer,
    view: Arc<std::sync::Mutex<LeaseView>>,
    leases: kv::Store,
    scenes: kv::Store,
}

impl Trust {
    /// The claim of `msg` if it is believed (see the module doc); `last_read` rate-limits
    /// reading the lease again.
    async fn check(
        &self,
        id: &SceneId,
        msg: &async_nats::Message,
        last_read: &mut Option<Instant>,
    ) -> Result<Claim, Refused> {
        let claim = self.signer.check(msg)?;
        if lock(&self.view).believes(&claim).is_err()
            && last_read.is_none_or(|t| t.elapsed() >= LEASE_RECHECK)
        {
            *last_read = Some(Instant::now());
            if let Ok(Some(entry)) = self.leases.entry(key(id)).await
                && entry.operation == kv::Operation::Put
            {
                *lock(&self.view) = LeaseView {
                    owner: String::from_utf8_lossy(&entry.value).into_owned(),
                    revision: entry.revision,
                };
            }
        }
        lock(&self.view).believes(&claim)?;
        if claim.kind == "deleted" {
            match self.scenes.entry(key(id)).await {
                Ok(None) => {}
                Ok(Some(entry)) if entry.operation != kv::Operation::Put => {}
                _ => return Err(Refused::NotDeleted),
            }
        }
        Ok(claim)
    }
}

/// Asks the owner for its epoch, descriptions and cached frames.
async fn ask_sync(
    client: &async_nats::Client,
    scene: &Scene,
    metrics: &Metrics,
) -> Option<(u64, Vec<AvatarDescription>, Vec<Bytes>)> {
    let mut headers = async_nats::HeaderMap::new();
    headers.insert(KIND, "sync");
    let asked = client.request_with_headers(request_subject(&scene.id), headers, Bytes::new());
    let reply = tokio::time::timeout(REQUEST_TIMEOUT, asked)
        .await
        .ok()?
        .ok()?;
    metrics.cluster.received(reply.payload.len());
    decode_sync(&reply.payload)
}

/// Relays until stopped or the scene is deleted.
async fn run(
    client: async_nats::Client,
    scene: Arc<Scene>,
    metrics: Arc<Metrics>,
    state: Weak<Services>,
    trust: Trust,
) {
    let mut live = match client.subscribe(relay_subject(&scene.id)).await {
        Ok(s) => s,
        Err(e) => {
            warn!(scene = %scene.id, error = %e, "cannot relay the scene");
            return;
        }
    };
    let mut epoch: u64;
    let mut last_seq: Option<u64> = None;
    // What the owner has now; live messages wait in the subscription meanwhile.
    loop {
        if let Some((e, avatars, frames)) = ask_sync(&client, &scene, &metrics).await {
            epoch = e;
            removed(&state, &scene.id, scene.relay_avatars(avatars));
            for f in frames {
                if scene.relay_frame(&f).is_ok() {
                    last_seq = peek_seq(&f);
                }
            }
            break;
        }
        tokio::time::sleep(SYNC_RETRY).await;
    }
    let mut last_resync: Option<Instant> = None;
    let mut last_lease_read: Option<Instant> = None;
    while let Some(msg) = live.next().await {
        metrics.cluster.received(msg.payload.len());
        let claim = match trust.check(&scene.id, &msg, &mut last_lease_read).await {
            Ok(claim) => claim,
            Err(why) => {
                metrics.cluster.relay_refused(why.label());
                debug!(scene = %scene.id, reason = why.label(), "relay message not believed: dropped");
                continue;
            }
        };
        let kind = claim.kind;
        if kind == "deleted" {
            if let Some(state) = state.upgrade()
                && state.world.delete_scene(&scene.id).is_ok()
            {
                deleted(&state, &scene.id);
            }
            return;
        }
        let e = claim.epoch;
        if e < epoch {
            // A previous owner's, still in flight: never interleaved with the new one's.
            continue;
        }
        if e > epoch {
            epoch = e;
            last_seq = None;
            scene.restart_frames();
        }
        match kind.as_str() {
            "avatars" => match serde_json::from_slice::<Vec<AvatarDescription>>(&msg.payload) {
                Ok(avatars) => removed(&state, &scene.id, scene.relay_avatars(avatars)),
                Err(e) => debug!(scene = %scene.id, error = %e, "unreadable descriptions"),
            },
            "frame" => {
                let Some(seq) = peek_seq(&msg.payload) else {
                    continue;
                };
                if last_seq.is_some_and(|l| seq <= l) {
                    continue;
                }
                match scene.relay_frame(&msg.payload) {
                    Ok(()) => last_seq = Some(seq),
                    // Descriptions missed (the owner's queue to NATS was full): asked for
                    // again, at most once a second.
                    Err(RelayRefused::UnknownAvatar(avatar))
                        if last_resync.is_none_or(|t| t.elapsed() >= RESYNC_INTERVAL) =>
                    {
                        debug!(scene = %scene.id, %avatar, "descriptions missed: asking the owner");
                        last_resync = Some(Instant::now());
                        if let Some((e, avatars, _)) = ask_sync(&client, &scene, &metrics).await
                            && e == epoch
                        {
                            removed(&state, &scene.id, scene.relay_avatars(avatars));
                            if scene.relay_frame(&msg.payload).is_ok() {
                                last_seq = Some(seq);
                            }
                        }
                    }
                    Err(e) => debug!(scene = %scene.id, error = %e, "frame not relayed"),
                }
            }
            "change" => match serde_json::from_slice::<Change>(&msg.payload) {
                Ok(c) => {
                    let msg = Message::Text(Utf8Bytes::from(c.text));
                    let told = scene.relay_change(&c.avatar, &msg);
                    // Watchers hear of it too, as of a change made here.
                    if let Some(state) = state.upgrade() {
                        state
                            .watchers
                            .push(&state.config.access, &scene.id, &msg, &told);
                    }
                }
                Err(e) => debug!(scene = %scene.id, error = %e, "unreadable change"),
            },
            _ => {}
        }
    }
}
