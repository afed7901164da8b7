//! VMC in: one UDP socket whose performer drives one avatar.
//!
//! [`Performer`] keeps what the datagrams said — the latest local rotation of every bone, the
//! root, the hips position, the blend shapes — and turns it into a pose of the VMC source rig
//! ([`super::rig::VmcRig`]). The task ([`run`]) reads datagrams, decodes them without any
//! lock, and hands the newest pose to the avatar at most [`MAX_RATE_HZ`] times a second
//! (latest pose wins, as for websocket drivers), so a flood costs the input's own task and
//! never holds a scene's lock longer than one pose.
//!
//! **Live-driving rules.** The input is a live driver like a websocket connection: it claims
//! the avatar with its first pose ([`posecast_sim::avatar::live::LivePose`], released to the clip when
//! the performer is silent for `--drive-timeout`). If another driver (a websocket `drive`)
//! holds the avatar, the input **waits**: its poses are counted as refused (`busy`) and
//! dropped, a warning is logged once, and it takes the avatar with its next pose after that
//! driver released it (disconnect, `release_drive`, timeout). While the input drives, a
//! websocket `drive` gets `conflict`. Likewise an avatar that does not exist (yet) is waited
//! for (`no_avatar`).

use std::collections::BTreeMap;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::{Duration, Instant};

use glam::{Quat, Vec3};
use posecast_proto::command::OnRelease;
use posecast_proto::live::MAX_RATE_HZ;
use posecast_proto::msg::AvatarId;
use tokio::net::UdpSocket;
use tracing::{debug, info, warn};

use super::packet::{self, Message};
use super::rig::VmcRig;
use super::unity::{BONES, LEG_BONES, LEG_LENGTH, mirror_position, mirror_rotation};
use crate::config::VmcIn;
use crate::metrics::vmc::{PacketDrop, PoseRefusal};
use crate::scene::Scene;
use crate::state::AppState;
use posecast_core::quota::{CommandRate, TokenBucket};
use posecast_sim::avatar::live::{LivePose, ValidPose};

/// Datagrams one input decodes per second at most (sustained): a performer sending every bone
/// as its own datagram at 120 Hz needs ~7,000. Beyond it datagrams are read and counted
/// (`flood`), not decoded.
pub const MAX_PACKETS_PER_SECOND: f64 = 20_000.0;
/// Datagrams one input may decode in a burst above [`MAX_PACKETS_PER_SECOND`].
pub const PACKET_BURST: f64 = 2_000.0;
/// Blend shape names one performer may set (VRM models have a few dozen; ARKit perfect sync
/// 52).
pub const MAX_BLEND_SHAPES: usize = 256;
/// The largest datagram UDP carries.
const MAX_DATAGRAM: usize = 65_536;

/// What one performer's datagrams said so far, in glTF's frame.
#[derive(Debug)]
pub struct Performer {
    vmc: Arc<VmcRig>,
    /// Latest local rotation per bone of [`BONES`], relative to the T-pose.
    bones: Vec<Quat>,
    /// Bones received since the last [`Performer::take_pose`].
    changed: Vec<bool>,
    /// Latest local position per bone (the performer's model's proportions; the hips'
    /// position is its motion).
    positions: Vec<Option<Vec3>>,
    root: (Vec3, Quat, Vec3),
    root_sent: bool,
    /// Blend shape values since the last `Apply`, and the last applied set not yet taken.
    blend_pending: BTreeMap<String, f32>,
    blend_applied: Option<BTreeMap<String, f32>>,
    /// Whether anything for the avatar arrived since the last take.
    dirty: bool,
    /// The sender's clock (`/VMC/Ext/T`), seconds.
    pub sender_time: Option<f32>,
    /// `/VMC/Ext/OK`'s `loaded`.
    pub loaded: Option<bool>,
}

/// A pose for the avatar and the blend shapes to publish with it.
#[derive(Debug, Default)]
pub struct Update {
    /// Source-rig pose (normalised frames).
    pub pose: ValidPose,
    /// A newly applied set of blend shape values.
    pub blend_shapes: Option<BTreeMap<String, f32>>,
}

impl Performer {
    /// Nothing received yet.
    #[must_use]
    pub fn new(vmc: Arc<VmcRig>) -> Self {
        let n = BONES.len();
        Self {
            vmc,
            bones: vec![Quat::IDENTITY; n],
            changed: vec![false; n],
            positions: vec![None; n],
            root: (Vec3::ZERO, Quat::IDENTITY, Vec3::ONE),
            root_sent: false,
            blend_pending: BTreeMap::new(),
            blend_applied: None,
            dirty: false,
            sender_time: None,
            loaded: None,
        }
    }

    /// Decodes one datagram into the performer's state, counting what it refuses.
    ///
    /// # Errors
    /// The datagram as a whole was unusable (nothing changed).
    pub fn datagram(
        &mut self,
        bytes: &[u8],
        metrics: &crate::metrics::vmc::VmcCounters,
    ) -> Result<(), PacketDrop> {
        let mut reject = |why| metrics.rejected(why);
        // Decoded first, applied after: `decode`'s callbacks cannot borrow `self` mutably.
        let mut messages = Vec::new();
        packet::decode(bytes, |m| messages.push(m), &mut reject)?;
        for m in messages {
            if let Err(why) = self.message(m) {
                reject(why);
            }
        }
        Ok(())
    }

    fn message(&mut self, m: Message) -> Result<(), crate::metrics::vmc::MessageReject> {
        match m {
            Message::Available { loaded } => self.loaded = Some(loaded),
            Message::Time(t) => self.sender_time = Some(t),
            Message::Root {
                position,
                rotation,
                scale,
            } => {
                self.root = (
                    mirror_position(position),
                    mirror_rotation(rotation),
                    scale.unwrap_or(Vec3::ONE),
                );
                self.root_sent = true;
                self.changed[0] = true;
                self.dirty = true;
            }
            Message::Bone {
                bone: Some(b),
                position,
                rotation,
            } => {
                if let (Some(slot), Some(changed), Some(p)) = (
                    self.bones.get_mut(b),
                    self.changed.get_mut(b),
                    self.positions.get_mut(b),
                ) {
                    *slot = mirror_rotation(rotation);
                    *changed = true;
                    *p = Some(mirror_position(position));
                    self.dirty = true;
                }
            }
            Message::Bone { bone: None, .. } => {}
            Message::BlendValue { name, value } => {
                if self.blend_pending.len() >= MAX_BLEND_SHAPES
                    && !self.blend_pending.contains_key(&name)
                {
                    return Err(crate::metrics::vmc::MessageReject::BlendShapeLimit);
                }
                self.blend_pending.insert(name, value);
            }
            Message::BlendApply => {
                self.blend_applied = Some(std::mem::take(&mut self.blend_pending));
                self.dirty = true;
            }
        }
        Ok(())
    }

    /// Whether something arrived for the avatar since the last [`Performer::take_pose`].
    #[must_use]
    pub fn pending(&self) -> bool {
        self.dirty
    }

    /// The performer's model scale: its leg length (knee and ankle offsets it sent) over the
    /// T-pose rig's, 1 until it sent them.
    #[must_use]
    pub fn model_scale(&self) -> f32 {
        for (knee, ankle) in LEG_BONES {
            if let (Some(Some(k)), Some(Some(a))) =
                (self.positions.get(knee), self.positions.get(ankle))
            {
                let s = (k.length() + a.length()) / LEG_LENGTH;
                if s.is_finite() && (0.05..=20.0).contains(&s) {
                    return s;
                }
            }
        }
        1.0
    }

    /// The changes since the last call as a pose of the VMC source rig: each bone received,
    /// `R' = V_parent · R · V⁻¹` ([`VmcRig::to_normalised`]); the hips take the root's
    /// rotation too (`R_hips = R_root · R_hips,local`) and, once the root or the hips'
    /// position arrived, the hips' position `(p_root + R_root (s_root ⊙ p_hips)) / scale`
    /// (the performer's model scaled to the T-pose rig's size).
    pub fn take_pose(&mut self) -> Update {
        self.dirty = false;
        let mut pose = ValidPose::default();
        let (root_p, root_q, root_s) = self.root;
        for (j, changed) in self.changed.iter_mut().enumerate() {
            if !std::mem::take(changed) {
                continue;
            }
            let local = self.bones.get(j).copied().unwrap_or(Quat::IDENTITY);
            let local = if j == 0 { root_q * local } else { local };
            pose.rotations.push((j, self.vmc.to_normalised(j, local)));
        }
        let hips = self.positions.first().copied().flatten();
        if self.root_sent || hips.is_some() {
            let scale = self.model_scale();
            let hips = hips.unwrap_or_else(|| Vec3::from(BONES[0].offset) * scale);
            pose.root_position = Some((root_p + root_q * (root_s * hips)) / scale);
        }
        Update {
            pose,
            blend_shapes: self.blend_applied.take(),
        }
    }
}

/// The avatar a [`run`] task drives, once claimed.
struct Claim {
    scene: Arc<Scene>,
}

/// Where the task is with its avatar, for logging transitions once.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Standing {
    Idle,
    Driving,
    Refused(PoseRefusal),
}

/// Reads `socket` until the server stops, driving `input.avatar` as driver `driver`.
pub async fn run(
    state: Arc<AppState>,
    input: VmcIn,
    socket: UdpSocket,
    vmc: Arc<VmcRig>,
    driver: u64,
) {
    let metrics = &state.metrics.vmc;
    let mut buf = vec![0u8; MAX_DATAGRAM];
    let mut performer = Performer::new(vmc.clone());
    let mut budget = TokenBucket::new(CommandRate {
        per_second: MAX_PACKETS_PER_SECOND,
        burst: PACKET_BURST,
    });
    let interval = Duration::from_secs_f64(1.0 / f64::from(MAX_RATE_HZ));
    let mut next_apply = tokio::time::Instant::now();
    let mut claim: Option<Claim> = None;
    let mut standing = Standing::Idle;
    let mut warned_sender = false;
    let addr = socket.local_addr().map_or(input.addr, |a| a);
    let who = posecast_proto::command::Driver {
        name: format!("vmc {addr}"),
        via: posecast_proto::command::DriveVia::Vmc,
    };
    loop {
        let wait_apply = performer.pending();
        tokio::select! {
            received = socket.recv_from(&mut buf) => match received {
                Ok((n, peer)) => {
                    metrics.packet(n);
                    // Before the rate budget: an outsider's flood must not use the
                    // performer's share.
                    if !input.allows(peer.ip()) {
                        metrics.dropped(PacketDrop::Sender);
                        if !warned_sender {
                            warn!(%addr, %peer, avatar = %input.avatar,
                                "VMC datagram from a sender outside the input's from= list dropped \
                                 (counted as posecast_vmc_packets_dropped_total, reason \"sender\"; \
                                 logged once)");
                            warned_sender = true;
                        }
                        continue;
                    }
                    if budget.take_at(Instant::now()).is_err() {
                        metrics.dropped(PacketDrop::Flood);
                        continue;
                    }
                    let bytes = buf.get(..n).unwrap_or_default();
                    if let Err(why) = performer.datagram(bytes, metrics) {
                        metrics.dropped(why);
                        debug!(%addr, %peer, ?why, "VMC datagram dropped");
                    }
                }
                Err(e) => {
                    // ICMP errors and the like: nothing to do but go on, without spinning.
                    debug!(%addr, error = %e, "VMC receive failed");
                    tokio::time::sleep(Duration::from_millis(10)).await;
                }
            },
            () = tokio::time::sleep_until(next_apply), if wait_apply => {}
        }
        let now = tokio::time::Instant::now();
        if performer.pending() && now >= next_apply {
            next_apply = now + interval;
            let update = performer.take_pose();
            let outcome = apply(
                &state,
                &input.avatar,
                (driver, &who),
                &vmc,
                &mut claim,
                update,
            );
            match outcome {
                Ok(()) => metrics.pose(),
                Err(why) => metrics.refused(why),
            }
            let now_standing = outcome.map_or_else(Standing::Refused, |()| Standing::Driving);
            if now_standing != standing {
                if now_standing == Standing::Driving
                    && let Some(c) = &claim
                {
                    // Presence: subscribers and dashboards see who drives it now.
                    crate::changes::avatar_changed(&state, &c.scene, &input.avatar);
                }
                log_standing(addr, &input.avatar, now_standing);
                standing = now_standing;
            }
        }
    }
}

fn log_standing(addr: SocketAddr, avatar: &AvatarId, standing: Standing) {
    match standing {
        Standing::Driving => info!(%addr, %avatar, "VMC input drives its avatar"),
        Standing::Refused(PoseRefusal::Busy) => warn!(
            %addr, %avatar,
            "VMC input waits: another driver (a websocket drive) holds the avatar; \
             its poses are dropped until that driver releases it"
        ),
        Standing::Refused(why) => {
            warn!(%addr, %avatar, reason = why.label(), "VMC input cannot drive its avatar; waiting");
        }
        Standing::Idle => {}
    }
}

/// Hands one update to the avatar: claims it when nobody drives it (or a released driver's
/// pose is only held), stores the pose when this input drives it.
fn apply(
    state: &AppState,
    avatar: &AvatarId,
    (driver, who): (u64, &posecast_proto::command::Driver),
    vmc: &VmcRig,
    claim: &mut Option<Claim>,
    update: Update,
) -> Result<(), PoseRefusal> {
    for attempt in 0..2 {
        let scene = match claim {
            Some(c) => c.scene.clone(),
            None => {
                let scene = state
                    .world
                    .find_avatar(avatar)
                    .map_err(|_| PoseRefusal::NoAvatar)?;
                *claim = Some(Claim {
                    scene: scene.clone(),
                });
                scene
            }
        };
        let mut s = scene.lock();
        let Some(a) = s.avatar_mut(avatar) else {
            // Removed or moved: look again once.
            drop(s);
            *claim = None;
            if attempt == 0 {
                continue;
            }
            return Err(PoseRefusal::NoAvatar);
        };
        match a.live.as_ref().and_then(|l| l.driver) {
            Some(d) if d == driver => {}
            Some(_) => return Err(PoseRefusal::Busy),
            None => {
                let source = vmc.for_target(&a.rig);
                let live = LivePose::new(
                    driver,
                    OnRelease::Clip,
                    source,
                    &a.rig,
                    &a.locals,
                    state.config.drive_timeout,
                )
                .map_err(|_| PoseRefusal::NotHumanoid)?;
                a.live = Some(live);
                if let Some(l) = a.live.as_mut() {
                    l.by = Some(who.clone());
                }
            }
        }
        // Blend shapes by VRM name drive the avatar's morph channels (`A` → `aa`, `Joy` →
        // `happy`, or its own names); names it lacks are kept in `blend_shapes` only.
        let morph: Option<Vec<(usize, f32)>> = update.blend_shapes.as_ref().map(|b| {
            b.iter()
                .filter_map(|(name, w)| Some((a.morph_channel(name)?, *w)))
                .collect()
        });
        if let Some(live) = a.live.as_mut() {
            live.store(update.pose, Instant::now());
            if let Some(b) = update.blend_shapes {
                live.blend_shapes = b;
            }
        }
        if let Some(weights) = morph.filter(|w| !w.is_empty()) {
            a.store_morph(&weights);
        }
        return Ok(());
    }
    Err(PoseRefusal::NoAvatar)
}
