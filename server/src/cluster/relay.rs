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

use super::owner::{Change, decode_sync};
use super::{Cluster, EPOCH, KIND, REQUEST_TIMEOUT, Task, lock, relay_subject, request_subject};
use crate::metrics::Metrics;
use crate::scene::Scene;
use crate::state::AppState;
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

/// A scene relayed here: who owns it, and the task relaying it (stopped when dropped).
#[derive(Debug)]
pub(super) struct Relayed {
    pub(super) owner: String,
    _task: Task,
}

impl Relayed {
    /// Stops relaying (the scene itself stays in the world).
    pub(super) fn stop(self) {}
}

impl Cluster {
    /// Relays scene `id`, owned by `owner`, to this server's subscribers (from now on, if it
    /// is not relayed yet).
    pub(super) fn relay(&self, state: &Arc<AppState>, id: &SceneId, owner: String) {
        if let Some(r) = lock(&self.relays).get_mut(id) {
            r.owner = owner;
            return;
        }
        let scene = match state.world.scene(id) {
            Ok(scene) if scene.is_relay() => scene,
            Ok(_) => {
                warn!(scene = %id, owner, "scene ticked here is leased to another server: giving it up");
                self.give_up(state, id);
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
        let task = tokio::spawn(run(
            self.conn.client.clone(),
            scene,
            state.metrics.clone(),
            Arc::downgrade(state),
        ));
        lock(&self.relays).insert(
            id.clone(),
            Relayed {
                owner,
                _task: Task(task),
            },
        );
    }

    /// Stops relaying a scene the cluster no longer has, and removes it here.
    pub(super) fn drop_relay(&self, state: &AppState, id: &SceneId) {
        if let Some(r) = lock(&self.relays).remove(id) {
            r.stop();
            if state.world.delete_scene(id).is_ok() {
                deleted(state, id);
            }
        }
    }
}

/// Tells this server's scene-list watchers that a relayed scene is gone.
fn deleted(state: &AppState, id: &SceneId) {
    let msg = text(&ServerMsg::SceneDeleted { scene: id.clone() });
    state.watchers.push(&state.config.access, id, &msg, &[]);
}

/// Tells this server's scene-list watchers that avatars of a relayed scene left (those
/// subscribed to it were told by its feed).
fn removed(state: &Weak<AppState>, id: &SceneId, gone: Vec<(AvatarId, Vec<u64>)>) {
    let Some(state) = state.upgrade() else { return };
    for (avatar, told) in gone {
        let msg = text(&ServerMsg::AvatarRemoved {
            scene: id.clone(),
            avatar,
        });
        state.watchers.push(&state.config.access, id, &msg, &told);
    }
}

fn header(msg: &async_nats::Message, name: &str) -> String {
    msg.headers
        .as_ref()
        .and_then(|h| h.get(name))
        .map(|v| v.as_str().to_owned())
        .unwrap_or_default()
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
    state: Weak<AppState>,
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
    while let Some(msg) = live.next().await {
        metrics.cluster.received(msg.payload.len());
        let kind = header(&msg, KIND);
        if kind == "deleted" {
            if let Some(state) = state.upgrade()
                && state.world.delete_scene(&scene.id).is_ok()
            {
                deleted(&state, &scene.id);
            }
            return;
        }
        let e: u64 = header(&msg, EPOCH).parse().unwrap_or(0);
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
