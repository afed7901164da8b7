//! Glue between the network client and the renderer: where an avatar's mesh comes from
//! ([`resolve_mesh`]), waiting for a pose that reflects a command ([`fresh_pose`]), and
//! [`ClientSource`], the viewer's [`PoseSource`] over a [`Client`].
//!
//! - [`fetch`]: the minimal HTTP client: the GET of the server's mesh endpoint, and the
//!   `posecast-client drive` upload of its source rig.

pub mod fetch;

use crate::net::{AvatarView, Client, ClientError, PoseSample};
use crate::render::glb_mesh::GlbMesh;
use crate::render::procedural::{TubeOptions, tube_mesh};
use crate::render::{AvatarUpdate, PoseSource};
use posecast_proto::SkinnedMesh;
use posecast_proto::morph::target_channels;
use posecast_proto::msg::{AvatarId, ErrorCode, ProtocolError};
use std::collections::HashMap;
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio::sync::mpsc;
use tracing::warn;

/// Where a mesh came from, for messages.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum MeshOrigin {
    /// The server's mesh endpoint.
    Server(String),
    /// The local `.glb` given with `--mesh`.
    File,
    /// Tubes around the bones: no mesh was available.
    Tubes,
}

impl std::fmt::Display for MeshOrigin {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Server(url) => write!(f, "server ({url})"),
            Self::File => f.write_str("local file"),
            Self::Tubes => f.write_str("tubes around the bones (no mesh available)"),
        }
    }
}

/// The weights of `mesh`'s morph targets (what the renderer takes) from the weights of an
/// avatar's `channels` (its description's `morph_targets`, what the stream carries): each
/// target takes the weight of the channel of its name, 0 when none names it.
#[must_use]
pub fn target_weights(mesh: &SkinnedMesh, channels: &[String], weights: &[f32]) -> Vec<f32> {
    target_channels(mesh, channels)
        .into_iter()
        .map(|c| c.and_then(|c| weights.get(c).copied()).unwrap_or(0.0))
        .collect()
}

/// The mesh to draw an avatar with, in order of preference: the description's `mesh_url`
/// fetched from the server at `ws_url`, the local `fallback` mapped onto the avatar's joints by
/// name, or tubes around the bones. Failures of the first two are logged and passed over, so
/// an avatar is always drawn.
pub async fn resolve_mesh(
    view: &AvatarView,
    ws_url: &str,
    fallback: Option<&GlbMesh>,
) -> (SkinnedMesh, MeshOrigin) {
    let description = &view.description;
    if let Some(path) = &description.mesh_url {
        match fetch_mesh(ws_url, path, &description.joint_names).await {
            Ok((mesh, url)) => return (mesh, MeshOrigin::Server(url)),
            Err(error) => warn!(avatar = %description.id, %error, "no mesh from the server"),
        }
    }
    if let Some(glb) = fallback {
        match glb.for_joints(&description.joint_names) {
            Ok(mesh) => return (mesh, MeshOrigin::File),
            Err(error) => warn!(avatar = %description.id, %error, "local mesh does not fit"),
        }
    }
    let mesh = tube_mesh(&view.skeleton, &TubeOptions::default());
    match mesh {
        Ok(mesh) => (mesh, MeshOrigin::Tubes),
        // A skeleton whose bones all have zero length: one degenerate triangle on joint 0.
        Err(error) => {
            warn!(avatar = %description.id, %error, "cannot build tubes either");
            (point_mesh(), MeshOrigin::Tubes)
        }
    }
}

fn point_mesh() -> SkinnedMesh {
    let zero = glam::Vec3::ZERO;
    SkinnedMesh::new(
        vec![zero; 3],
        vec![glam::Vec3::Y; 3],
        vec![0, 1, 2],
        1,
        vec![0; 3],
        vec![1.0; 3],
        1,
    )
    .unwrap_or_else(|_| unreachable!("three vertices on joint 0 are a valid mesh"))
}

async fn fetch_mesh(
    ws_url: &str,
    path: &str,
    joints: &[String],
) -> Result<(SkinnedMesh, String), Box<dyn std::error::Error + Send + Sync>> {
    let url = fetch::resolve(ws_url, path)?;
    let bytes = fetch::get(&url).await?;
    let mesh = GlbMesh::from_slice(&bytes)?.for_joints(joints)?;
    Ok((mesh, url.to_string()))
}

/// How long [`wait_for_avatars`] waits for an avatar `id` once the scene's other avatars have
/// poses: a subscriber is described every avatar, and gets their poses, at once.
const NAMED_AVATAR_GRACE: Duration = Duration::from_secs(1);

/// Waits until some avatar is known (`id`, or any when `None`); returns the known avatars
/// sorted by id.
///
/// # Errors
/// At once, [`ClientError::Server`] when the server refused the subscription (no such scene,
/// not allowed), or `unknown_avatar` when the scene's avatars have arrived without `id`;
/// [`ClientError::Timeout`] when no avatar came within `timeout`.
pub async fn wait_for_avatars(
    client: &Client,
    id: Option<&AvatarId>,
    timeout: Duration,
) -> Result<Vec<AvatarView>, ClientError> {
    let deadline = tokio::time::Instant::now() + timeout;
    let mut others_since = None;
    loop {
        if let Some(e) = client.stats().last_error
            && matches!(
                e.code,
                ErrorCode::UnknownScene | ErrorCode::Unauthorized | ErrorCode::Forbidden
            )
        {
            return Err(ClientError::Server(e));
        }
        let mut views = client.avatars();
        views.retain(|v| v.latest.is_some());
        let found = match id {
            Some(id) => views.iter().any(|v| &v.description.id == id),
            None => !views.is_empty(),
        };
        if found {
            views.sort_by(|a, b| a.description.id.0.cmp(&b.description.id.0));
            return Ok(views);
        }
        let now = tokio::time::Instant::now();
        if let Some(id) = id
            && !views.is_empty()
            && now.duration_since(*others_since.get_or_insert(now)) >= NAMED_AVATAR_GRACE
        {
            let mut present: Vec<&str> =
                views.iter().map(|v| v.description.id.0.as_str()).collect();
            present.sort_unstable();
            return Err(ClientError::Server(ProtocolError::new(
                ErrorCode::UnknownAvatar,
                format!(
                    "the scene has no avatar {id} (it has {})",
                    present.join(", ")
                ),
            )));
        }
        if now >= deadline {
            return Err(ClientError::Timeout("an avatar with a pose"));
        }
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
}

/// The first pose of `avatar` from a tick at least two after `after_seq`. Call with the
/// newest seq seen once a command has been acknowledged: the acknowledgement and the frames
/// travel through different queues on the server, so the next frame may still have been
/// encoded before the command; two ticks later it cannot have been.
pub async fn fresh_pose(
    client: &Client,
    avatar: &AvatarId,
    after_seq: u64,
    timeout: Duration,
) -> Result<PoseSample, ClientError> {
    let deadline = tokio::time::Instant::now() + timeout;
    loop {
        if let Some(sample) = client.latest(avatar)
            && sample.seq >= after_seq + 2
        {
            return Ok(sample);
        }
        if tokio::time::Instant::now() >= deadline {
            return Err(ClientError::Timeout("a pose after the command"));
        }
        tokio::time::sleep(Duration::from_millis(2)).await;
    }
}

/// One mesh resolved in the background.
#[derive(Debug)]
struct Resolved {
    avatar: AvatarId,
    hash: String,
    skeleton: Arc<posecast_proto::Skeleton>,
    /// For each of the mesh's morph targets, the description's channel that drives it.
    target_channels: Vec<Option<usize>>,
    mesh: SkinnedMesh,
}

#[derive(Debug)]
struct Shown {
    id: u64,
    hash: String,
    spawned: bool,
    /// For each of the spawned mesh's morph targets, the channel whose weight it takes.
    target_channels: Vec<Option<usize>>,
}

/// The viewer's [`PoseSource`] over a [`Client`]: spawns avatars as their descriptions arrive
/// (meshes resolved on the runtime by [`resolve_mesh`], so `poll` never blocks), poses each
/// from the jitter buffer's interpolated [`Client::pose_now`], despawns avatars that left, and
/// reports stream rate and latency for the title.
#[derive(Debug)]
pub struct ClientSource {
    client: Arc<Client>,
    runtime: tokio::runtime::Handle,
    ws_url: String,
    fallback: Option<Arc<GlbMesh>>,
    shown: HashMap<AvatarId, Shown>,
    next_id: u64,
    resolved_tx: mpsc::Sender<Resolved>,
    resolved_rx: mpsc::Receiver<Resolved>,
    last_stats: (Instant, crate::net::Stats),
    status: String,
}

impl ClientSource {
    /// A source over `client`, connected to `ws_url`; meshes are fetched on `runtime`, with
    /// `fallback` used when the server has none.
    #[must_use]
    pub fn new(
        client: Arc<Client>,
        runtime: tokio::runtime::Handle,
        ws_url: impl Into<String>,
        fallback: Option<Arc<GlbMesh>>,
    ) -> Self {
        // A handful of avatars resolve at once; a full channel only delays a spawn.
        let (resolved_tx, resolved_rx) = mpsc::channel(64);
        let stats = client.stats();
        Self {
            client,
            runtime,
            ws_url: ws_url.into(),
            fallback,
            shown: HashMap::new(),
            next_id: 0,
            resolved_tx,
            resolved_rx,
            last_stats: (Instant::now(), stats),
            status: "connecting".into(),
        }
    }

    fn start_resolving(&self, view: AvatarView) {
        let tx = self.resolved_tx.clone();
        let ws_url = self.ws_url.clone();
        let fallback = self.fallback.clone();
        self.runtime.spawn(async move {
            let (mesh, origin) = resolve_mesh(&view, &ws_url, fallback.as_deref()).await;
            tracing::info!(avatar = %view.description.id, %origin, "mesh");
            let resolved = Resolved {
                avatar: view.description.id.clone(),
                hash: view.description.hash.clone(),
                skeleton: view.skeleton.clone(),
                target_channels: target_channels(&mesh, &view.description.morph_targets),
                mesh,
            };
            if tx.send(resolved).await.is_err() {
                tracing::debug!("viewer closed before a mesh arrived");
            }
        });
    }

    fn update_status(&mut self, now: Instant) {
        let (since, before) = &self.last_stats;
        let elapsed = now.duration_since(*since).as_secs_f64();
        if elapsed < 0.5 {
            return;
        }
        let stats = self.client.stats();
        let frames = stats.frames.saturating_sub(before.frames);
        let latency_n = stats.latency_count.saturating_sub(before.latency_count);
        let latency = if latency_n > 0 {
            (stats.latency_sum_us - before.latency_sum_us) / latency_n as f64 / 1000.0
        } else {
            f64::NAN
        };
        let (_, rtt) = self.client.clock();
        let link = if self.client.is_connected() {
            ""
        } else {
            " — reconnecting"
        };
        self.status = format!(
            "stream {:.0} frames/s, latency {latency:.1} ms, rtt {}{link}",
            frames as f64 / elapsed,
            rtt.map_or("?".into(), |r| format!("{:.1} ms", r / 1000.0)),
        );
        self.last_stats = (now, stats);
    }
}

impl PoseSource for ClientSource {
    fn poll(&mut self, now: Instant) -> Vec<AvatarUpdate> {
        let mut updates = Vec::new();
        while let Ok(resolved) = self.resolved_rx.try_recv() {
            let Some(shown) = self.shown.get_mut(&resolved.avatar) else {
                continue;
            };
            // A newer description may have arrived while this mesh was on its way.
            if shown.hash == resolved.hash {
                shown.spawned = true;
                shown.target_channels = resolved.target_channels;
                updates.push(AvatarUpdate::Spawn {
                    id: shown.id,
                    skeleton: Box::new((*resolved.skeleton).clone()),
                    mesh: Box::new(resolved.mesh),
                });
            }
        }
        let views = self.client.avatars();
        for view in &views {
            let id = &view.description.id;
            let known = self
                .shown
                .get(id)
                .is_some_and(|s| s.hash == view.description.hash);
            if !known {
                let numeric = match self.shown.get(id) {
                    Some(s) => s.id,
                    None => {
                        self.next_id += 1;
                        self.next_id
                    }
                };
                self.shown.insert(
                    id.clone(),
                    Shown {
                        id: numeric,
                        hash: view.description.hash.clone(),
                        spawned: false,
                        target_channels: Vec::new(),
                    },
                );
                self.start_resolving(view.clone());
            }
        }
        self.shown.retain(|id, shown| {
            let alive = views.iter().any(|v| &v.description.id == id);
            if !alive && shown.spawned {
                updates.push(AvatarUpdate::Despawn { id: shown.id });
            }
            alive
        });
        for (avatar, shown) in &self.shown {
            if !shown.spawned {
                continue;
            }
            if let Some(locals) = self.client.pose_now(avatar) {
                let channels = self.client.weights_now(avatar).unwrap_or_default();
                let weights = shown
                    .target_channels
                    .iter()
                    .map(|c| c.and_then(|c| channels.get(c).copied()).unwrap_or(0.0))
                    .collect();
                updates.push(AvatarUpdate::Pose {
                    id: shown.id,
                    locals,
                    weights,
                });
            }
        }
        self.update_status(now);
        updates
    }

    fn status(&self) -> String {
        self.status.clone()
    }
}
