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
//!
//! **Tracked devices** (`/VMC/Ext/Hmd/Pos`, `/VMC/Ext/Con/Pos`, `/VMC/Ext/Tra/Pos`). The
//! performer keeps each device's latest pose by serial (at most [`MAX_DEVICES`]) and assigns
//! devices to the standard trackers (`posecast_proto::trackers`) once, for good: the first
//! headset is `head`; controllers are `l_hand` and `r_hand` by the side of the head they are on
//! in the head's yaw frame when first seen with it; generic trackers are `hips` (the one at
//! mid-body height nearest the head horizontally) and `l_foot` / `r_foot` (the lowest, by side)
//! ([`Performer::take_devices`]); a sender silent for `--drive-timeout` starts over. An input
//! whose sender sends devices and no bones (none for `--drive-timeout`) drives its avatar by
//! trackers — a [`LivePose`] whose [`posecast_sim::avatar::trackers::Trackers`] (the assigned
//! trackers, legs planted) solves the whole body every tick, calibratable by
//! `calibrate_trackers` — once the head and both hands have had a device for
//! [`DEVICES_ALONE`]; a sender's bones win over its devices. Device poses are in the sender's
//! tracking space, whose origin (the floor, y = 0) is the avatar's placement.

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

use super::packet::{self, DeviceKind, Message};
use super::rig::VmcRig;
use super::unity::{BONES, LEG_BONES, LEG_LENGTH, mirror_position, mirror_rotation};
use crate::config::VmcIn;
use crate::metrics::vmc::{MessageReject, PacketDrop, PoseRefusal};
use crate::scene::Scene;
use crate::state::Services;
use posecast_core::quota::{CommandRate, TokenBucket};
use posecast_proto::trackers::{Legs, REQUIRED, STANDARD};
use posecast_sim::avatar::live::{LivePose, ValidPose};
use posecast_sim::avatar::trackers::{TrackerSample, Trackers};

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
/// Tracked devices (serials of `/VMC/Ext/{Hmd,Con,Tra}/Pos`) one performer may send; further
/// serials are refused (`device_limit`). A full-body VR setup has a headset, two controllers
/// and up to about ten trackers.
pub const MAX_DEVICES: usize = 16;
/// How long a sender must have sent a head and two hands without any bones before its devices
/// drive (a sender of both, whose first datagrams hold only devices, drives by bones from the
/// start).
pub const DEVICES_ALONE: Duration = Duration::from_millis(100);
/// A generic tracker lower than this share of the head's height above the floor is a foot
/// candidate.
pub const FOOT_HEIGHT: f32 = 0.25;
/// A generic tracker between these shares of the head's height above the floor is a hips
/// candidate…
pub const HIPS_HEIGHT: (f32, f32) = (0.35, 0.75);
/// … when it is at most this share of the head's height from the head horizontally.
pub const HIPS_REACH: f32 = 0.3;
/// A head lower than this above the sender's floor (y = 0), metres, assigns no generic
/// trackers (heights are measured from that floor).
pub const MIN_HEAD_HEIGHT: f32 = 0.3;

/// The standard trackers' slots: indices into [`STANDARD`].
mod slot {
    pub const HEAD: usize = 0;
    pub const L_HAND: usize = 1;
    pub const R_HAND: usize = 2;
    pub const HIPS: usize = 3;
    pub const L_FOOT: usize = 4;
    pub const R_FOOT: usize = 5;
}

/// One tracked device's latest pose, glTF frame.
#[derive(Debug, Clone)]
struct Device {
    kind: DeviceKind,
    serial: String,
    position: Vec3,
    rotation: Quat,
    /// Received since the last [`Performer::take_devices`].
    changed: bool,
    /// The standard tracker it was assigned to (a slot of [`STANDARD`]), for good.
    tracker: Option<usize>,
}

/// The assigned devices' poses for a tracker drive ([`Performer::take_devices`]).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Devices {
    /// The drive's trackers: `head`, `l_hand`, `r_hand` and each other standard tracker a
    /// device is assigned to, in [`STANDARD`]'s order.
    pub names: Vec<&'static str>,
    /// `(index into names, latest pose in the sender's space mirrored to glTF's frame,
    /// received since the last take)`, for every assigned device.
    pub samples: Vec<(usize, TrackerSample, bool)>,
    /// Whether the head and both hands have a device (the body can be solved).
    pub ready: bool,
}

/// The head's left, horizontal: its yaw frame's +X (the avatar's left is +X facing +Z). The
/// yaw is the forward (+Z) axis flattened or, looking straight up or down, the up axis (the
/// tracker solve's rule).
fn head_left(q: Quat) -> Vec3 {
    Quat::from_rotation_y(posecast_sim::avatar::trackers::yaw_of(q)) * Vec3::X
}

/// The sender's clock (`/VMC/Ext/T`, seconds) as driver time in µs that never goes back: after
/// a restart of the sender's clock it goes on from where it was.
#[derive(Debug, Default)]
struct SenderClock {
    offset: u64,
    last: u64,
}

impl SenderClock {
    fn micros(&mut self, seconds: f32) -> u64 {
        // f64 → u64 saturates; the decoder let only finite values through.
        let t = (f64::from(seconds).max(0.0) * 1e6) as u64;
        let out = t.saturating_add(self.offset);
        if out < self.last {
            self.offset = self.last - t;
        } else {
            self.last = out;
        }
        self.last
    }
}

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
    /// Whether a `/VMC/Ext/Bone/Pos` arrived since the last take.
    bones_received: bool,
    /// Tracked devices in the order first seen, at most [`MAX_DEVICES`].
    devices: Vec<Device>,
    /// Whether a device pose arrived since the last [`Performer::take_devices`].
    devices_dirty: bool,
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
    /// Whether bone messages (`/VMC/Ext/Bone/Pos`) arrived since the last take: the sender
    /// sends bones, and they win over its devices.
    pub bones: bool,
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
            bones_received: false,
            devices: Vec::new(),
            devices_dirty: false,
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

    fn message(&mut self, m: Message) -> Result<(), MessageReject> {
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
                self.bones_received = true;
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
            Message::Bone { bone: None, .. } => self.bones_received = true,
            Message::BlendValue { name, value } => {
                if self.blend_pending.len() >= MAX_BLEND_SHAPES
                    && !self.blend_pending.contains_key(&name)
                {
                    return Err(MessageReject::BlendShapeLimit);
                }
                self.blend_pending.insert(name, value);
            }
            Message::BlendApply => {
                self.blend_applied = Some(std::mem::take(&mut self.blend_pending));
                self.dirty = true;
            }
            Message::Device {
                kind,
                serial,
                position,
                rotation,
            } => {
                let (position, rotation) = (mirror_position(position), mirror_rotation(rotation));
                let known = self
                    .devices
                    .iter()
                    .position(|d| d.kind == kind && d.serial == serial);
                if let Some(d) = known.and_then(|i| self.devices.get_mut(i)) {
                    d.position = position;
                    d.rotation = rotation;
                    d.changed = true;
                } else if self.devices.len() >= MAX_DEVICES {
                    return Err(MessageReject::DeviceLimit);
                } else {
                    self.devices.push(Device {
                        kind,
                        serial,
                        position,
                        rotation,
                        changed: true,
                        tracker: None,
                    });
                }
                self.devices_dirty = true;
            }
        }
        Ok(())
    }

    /// Whether a device pose arrived since the last [`Performer::take_devices`].
    #[must_use]
    pub fn devices_pending(&self) -> bool {
        self.devices_dirty
    }

    /// Forgets every device and its assignment (a sender that fell silent starts over).
    pub fn forget_devices(&mut self) {
        self.devices.clear();
        self.devices_dirty = false;
    }

    /// Assigns unassigned devices to free standard trackers (see the module docs); an
    /// assignment is never undone.
    fn assign(&mut self) {
        use slot::{HEAD, HIPS, L_FOOT, L_HAND, R_FOOT, R_HAND};
        let free = |devices: &[Device], s: usize| devices.iter().all(|d| d.tracker != Some(s));
        if free(&self.devices, HEAD)
            && let Some(d) = self
                .devices
                .iter_mut()
                .find(|d| d.kind == DeviceKind::Hmd && d.tracker.is_none())
        {
            d.tracker = Some(HEAD);
        }
        let Some((head, left)) = self
            .devices
            .iter()
            .find(|d| d.tracker == Some(HEAD))
            .map(|d| (d.position, head_left(d.rotation)))
        else {
            return;
        };
        let side = |d: &Device| (d.position - head).dot(left);
        let unassigned = |devices: &[Device], kind: DeviceKind| -> Vec<usize> {
            (0..devices.len())
                .filter(|&i| devices[i].kind == kind && devices[i].tracker.is_none())
                .collect()
        };
        let controllers = unassigned(&self.devices, DeviceKind::Controller);
        self.pair(&controllers, [L_HAND, R_HAND], side);
        if head.y < MIN_HEAD_HEIGHT {
            return;
        }
        let trackers = unassigned(&self.devices, DeviceKind::Tracker);
        if free(&self.devices, HIPS) {
            let horizontal =
                |d: &Device| Vec3::new(d.position.x - head.x, 0.0, d.position.z - head.z).length();
            let hips = trackers
                .iter()
                .copied()
                .filter(|&i| {
                    let d = &self.devices[i];
                    let h = d.position.y / head.y;
                    (HIPS_HEIGHT.0..=HIPS_HEIGHT.1).contains(&h)
                        && horizontal(d) <= HIPS_REACH * head.y
                })
                .min_by(|&a, &b| {
                    horizontal(&self.devices[a]).total_cmp(&horizontal(&self.devices[b]))
                });
            if let Some(i) = hips {
                self.devices[i].tracker = Some(HIPS);
            }
        }
        let mut feet: Vec<usize> = trackers
            .into_iter()
            .filter(|&i| {
                let d = &self.devices[i];
                d.tracker.is_none() && d.position.y < FOOT_HEIGHT * head.y
            })
            .collect();
        // The lowest first (a stable sort: ties in the order first seen).
        feet.sort_by(|&a, &b| {
            self.devices[a]
                .position
                .y
                .total_cmp(&self.devices[b].position.y)
        });
        self.pair(&feet, [L_FOOT, R_FOOT], side);
    }

    /// Assigns `candidates` (best first) to the `[left, right]` slots still free: two free
    /// slots and two or more candidates, the first two by which is more to the left; one
    /// candidate, by its side of the head (`side`, positive on the left); one free slot, the
    /// first candidate.
    fn pair(&mut self, candidates: &[usize], [l, r]: [usize; 2], side: impl Fn(&Device) -> f32) {
        let free = |s: usize| self.devices.iter().all(|d| d.tracker != Some(s));
        let (l_free, r_free) = (free(l), free(r));
        match (l_free, r_free, candidates) {
            (true, true, [a, b, ..]) => {
                let (a, b) = (*a, *b);
                let (left, right) = if side(&self.devices[a]) >= side(&self.devices[b]) {
                    (a, b)
                } else {
                    (b, a)
                };
                self.devices[left].tracker = Some(l);
                self.devices[right].tracker = Some(r);
            }
            (true, true, [a]) => {
                let to = if side(&self.devices[*a]) >= 0.0 { l } else { r };
                self.devices[*a].tracker = Some(to);
            }
            (true, false, [a, ..]) => self.devices[*a].tracker = Some(l),
            (false, true, [a, ..]) => self.devices[*a].tracker = Some(r),
            _ => {}
        }
    }

    /// The assigned devices' latest poses for a tracker drive, each marked whether it arrived
    /// since the last call, after assigning new devices (see the module docs).
    pub fn take_devices(&mut self) -> Devices {
        if std::mem::take(&mut self.devices_dirty) {
            self.assign();
        }
        let assigned = |s: usize| self.devices.iter().any(|d| d.tracker == Some(s));
        let names: Vec<&'static str> = STANDARD
            .iter()
            .enumerate()
            .filter(|&(s, _)| s <= slot::R_HAND || assigned(s))
            .map(|(_, (name, _))| *name)
            .collect();
        let ready = [slot::HEAD, slot::L_HAND, slot::R_HAND]
            .into_iter()
            .all(assigned);
        let mut samples = Vec::new();
        for d in &mut self.devices {
            let changed = std::mem::take(&mut d.changed);
            let Some(s) = d.tracker else { continue };
            let Some(i) = names.iter().position(|n| *n == STANDARD[s].0) else {
                continue;
            };
            let sample = TrackerSample {
                position: d.position,
                rotation: d.rotation,
            };
            samples.push((i, sample, changed));
        }
        Devices {
            names,
            samples,
            ready,
        }
    }

    /// Which standard tracker (a name of [`STANDARD`]) the device `serial` of `kind` was
    /// assigned to, if any.
    #[must_use]
    pub fn assigned(&self, kind: DeviceKind, serial: &str) -> Option<&'static str> {
        self.devices
            .iter()
            .find(|d| d.kind == kind && d.serial == serial)
            .and_then(|d| d.tracker)
            .map(|s| STANDARD[s].0)
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
        let bones = std::mem::take(&mut self.bones_received);
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
            bones,
        }
    }
}

/// The avatar a [`run`] task drives, once claimed.
struct Claim {
    scene: Arc<Scene>,
    /// The trackers a tracker drive was last made for ([`Devices::names`]).
    tracker_names: Vec<&'static str>,
}

/// Where the task is with its avatar, for logging transitions once.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Standing {
    Idle,
    Driving,
    Refused(PoseRefusal),
}

/// What one update drives the avatar with.
#[derive(Debug)]
enum Drive {
    /// The sender's bones: a pose of the VMC source rig.
    Bones(ValidPose),
    /// Its tracked devices: a tracker drive, at driver time `time_us` (the sender's clock).
    Trackers {
        devices: Devices,
        time_us: Option<u64>,
    },
}

/// Reads `socket` until the server stops, driving `input.avatar` as driver `driver`.
pub async fn run(
    state: Arc<Services>,
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
    // When bones last arrived: they win over devices until they have been silent for the
    // drive timeout.
    let mut bones_at: Option<tokio::time::Instant> = None;
    // When a head and two hands were first assigned.
    let mut devices_from: Option<tokio::time::Instant> = None;
    // When the last datagram was decoded: a sender silent for the drive timeout starts over
    // with its devices (assignments, the device limit).
    let mut heard_at: Option<tokio::time::Instant> = None;
    let mut clock = SenderClock::default();
    let addr = socket.local_addr().map_or(input.addr, |a| a);
    let who = posecast_proto::command::Driver {
        name: format!("vmc {addr}"),
        via: posecast_proto::command::DriveVia::Vmc,
    };
    loop {
        let wait_apply = performer.pending() || performer.devices_pending();
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
                    let heard = tokio::time::Instant::now();
                    if heard_at.is_some_and(|t| heard.duration_since(t) > state.config.drive_timeout) {
                        performer.forget_devices();
                        devices_from = None;
                    }
                    heard_at = Some(heard);
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
        let (pose_pending, devices_pending) = (performer.pending(), performer.devices_pending());
        if !(pose_pending || devices_pending) || now < next_apply {
            continue;
        }
        next_apply = now + interval;
        let update = performer.take_pose();
        let devices = performer.take_devices();
        if update.bones {
            bones_at = Some(now);
        }
        let bones_win =
            bones_at.is_some_and(|t| now.duration_since(t) <= state.config.drive_timeout);
        if devices.ready && devices_from.is_none() {
            devices_from = Some(now);
        }
        let devices_only =
            devices_from.is_some_and(|t| now.duration_since(t) >= DEVICES_ALONE) && !bones_win;
        let drive = if devices.ready && devices_only {
            Drive::Trackers {
                devices,
                time_us: performer.sender_time.map(|t| clock.micros(t)),
            }
        } else if pose_pending && (bones_at.is_some() || devices_from.is_none()) {
            Drive::Bones(update.pose)
        } else {
            // Devices alone, not yet a head and two hands or not for long (or the sender's
            // bones drive); or a sender of devices (no bones yet) sent a root or blend shapes
            // before its devices drive.
            continue;
        };
        let by_trackers = matches!(drive, Drive::Trackers { .. });
        let outcome = apply(
            &state,
            &input.avatar,
            (driver, &who),
            &vmc,
            &mut claim,
            drive,
            update.blend_shapes,
        );
        match outcome {
            Ok(_) => metrics.pose(),
            Err(why) => metrics.refused(why),
        }
        let switched = outcome == Ok(true);
        let now_standing = outcome.map_or_else(Standing::Refused, |_| Standing::Driving);
        if (now_standing != standing || switched)
            && now_standing == Standing::Driving
            && let Some(c) = &claim
        {
            // Presence: subscribers and dashboards see who drives it now (and how).
            crate::changes::avatar_changed(&state, &c.scene, &input.avatar);
        }
        if now_standing != standing {
            log_standing(addr, &input.avatar, now_standing);
            standing = now_standing;
        }
        if switched {
            info!(%addr, avatar = %input.avatar, by_trackers,
                "VMC input switched between bones and tracked devices");
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
/// pose is only held), stores the pose when this input drives it. A drive of the other kind
/// (bones, tracked devices) by this input is replaced; returns whether it was.
fn apply(
    state: &Services,
    avatar: &AvatarId,
    (driver, who): (u64, &posecast_proto::command::Driver),
    vmc: &VmcRig,
    claim: &mut Option<Claim>,
    drive: Drive,
    blend_shapes: Option<BTreeMap<String, f32>>,
) -> Result<bool, PoseRefusal> {
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
                    tracker_names: Vec::new(),
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
        let ours = match a.live.as_ref().and_then(|l| l.driver) {
            Some(d) if d == driver => true,
            Some(_) => return Err(PoseRefusal::Busy),
            None => false,
        };
        let by_trackers = matches!(drive, Drive::Trackers { .. });
        let same_kind = ours
            && a.live
                .as_ref()
                .is_some_and(|l| l.trackers.is_some() == by_trackers);
        if !same_kind {
            let timeout = state.config.drive_timeout;
            let mut live = match &drive {
                Drive::Bones(_) => LivePose::new(
                    driver,
                    OnRelease::Clip,
                    vmc.for_target(&a.rig),
                    &a.rig,
                    &a.locals,
                    timeout,
                )
                .map_err(|_| PoseRefusal::NotHumanoid)?,
                Drive::Trackers { devices, .. } => {
                    // The avatar's own rig: the solve writes its local rotations.
                    let mut live = LivePose::new(
                        driver,
                        OnRelease::Clip,
                        a.rig.clone(),
                        &a.rig,
                        &a.locals,
                        timeout,
                    )
                    .map_err(|_| PoseRefusal::NotHumanoid)?;
                    live.trackers = Some(tracker_solve(a, &devices.names)?);
                    live
                }
            };
            live.by = Some(who.clone());
            a.live = Some(live);
        }
        // Blend shapes by VRM name drive the avatar's morph channels (`A` → `aa`, `Joy` →
        // `happy`, or its own names); names it lacks are kept in `blend_shapes` only.
        let morph: Option<Vec<(usize, f32)>> = blend_shapes.as_ref().map(|b| {
            b.iter()
                .filter_map(|(name, w)| Some((a.morph_channel(name)?, *w)))
                .collect()
        });
        // Device poses are in the sender's space, whose origin is the avatar's placement.
        let placement = a.placing.current();
        // A device newly assigned to hips or a foot: the solve is made again with it (its
        // filters, calibration and feet start over).
        let rebuilt = match &drive {
            Drive::Trackers { devices, .. } if same_kind && claim_names(claim) != devices.names => {
                tracker_solve(a, &devices.names).ok()
            }
            _ => None,
        };
        if let Some(live) = a.live.as_mut() {
            match drive {
                Drive::Bones(pose) => {
                    live.store(pose, Instant::now());
                }
                Drive::Trackers { devices, time_us } => {
                    let all = rebuilt.is_some() || !same_kind;
                    if let Some(t) = rebuilt {
                        live.trackers = Some(t);
                    }
                    if let Some(c) = claim.as_mut() {
                        c.tracker_names.clone_from(&devices.names);
                    }
                    let names = live
                        .trackers
                        .as_ref()
                        .map(Trackers::names)
                        .unwrap_or_default();
                    let samples: Vec<(usize, TrackerSample)> = devices
                        .samples
                        .iter()
                        .filter(|(_, _, changed)| all || *changed)
                        .filter_map(|&(i, s, _)| {
                            let name = devices.names.get(i)?;
                            let j = names.iter().position(|n| n == name)?;
                            let sample = TrackerSample {
                                position: placement.position + placement.rotation * s.position,
                                rotation: (placement.rotation * s.rotation).normalize(),
                            };
                            Some((j, sample))
                        })
                        .collect();
                    live.store_trackers(&samples, time_us, Instant::now());
                }
            }
            if let Some(b) = blend_shapes {
                live.blend_shapes = b;
            }
        }
        if let Some(weights) = morph.filter(|w| !w.is_empty()) {
            a.store_morph(&weights);
        }
        return Ok(ours && !same_kind);
    }
    Err(PoseRefusal::NoAvatar)
}

/// The trackers the claimed drive was last made for (empty before any).
fn claim_names(claim: &Option<Claim>) -> &[&'static str] {
    claim.as_ref().map_or(&[], |c| c.tracker_names.as_slice())
}

/// The tracker solve of an avatar driven by devices assigned to `names` (the standard
/// trackers), its feet planted; only the head and hands when the rig cannot take the others
/// (no legs).
///
/// # Errors
/// The rig lacks a joint the head and hands need ([`PoseRefusal::NotHumanoid`]).
fn tracker_solve(
    a: &posecast_sim::avatar::Avatar,
    names: &[&str],
) -> Result<Trackers, PoseRefusal> {
    let solve = |names: &[&str]| {
        let names: Vec<String> = names.iter().map(|n| (*n).to_owned()).collect();
        Trackers::new(&a.rig, &names, Legs::Planted)
    };
    solve(names)
        .or_else(|_| solve(&REQUIRED))
        .map_err(|_| PoseRefusal::NotHumanoid)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::metrics::vmc::VmcCounters;
    use rosc::{OscBundle, OscMessage, OscPacket, OscTime, OscType};

    const HMD: &str = "/VMC/Ext/Hmd/Pos";
    const CON: &str = "/VMC/Ext/Con/Pos";
    const TRA: &str = "/VMC/Ext/Tra/Pos";

    /// A device message with a glTF-frame pose, written in Unity's frame as senders do.
    fn device(addr: &str, serial: &str, p: Vec3, q: Quat) -> OscPacket {
        let (p, q) = (mirror_position(p), mirror_rotation(q));
        let mut args = vec![OscType::String(serial.into())];
        args.extend(p.to_array().map(OscType::Float));
        args.extend(q.to_array().map(OscType::Float));
        OscPacket::Message(OscMessage {
            addr: addr.into(),
            args,
        })
    }

    fn send(p: &mut Performer, counters: &VmcCounters, content: Vec<OscPacket>) {
        let bundle = OscPacket::Bundle(OscBundle {
            timetag: OscTime {
                seconds: 0,
                fractional: 1,
            },
            content,
        });
        p.datagram(&rosc::encoder::encode(&bundle).unwrap(), counters)
            .unwrap();
    }

    fn performer() -> (Performer, VmcCounters) {
        (
            Performer::new(Arc::new(VmcRig::new().unwrap())),
            VmcCounters::standalone(),
        )
    }

    #[test]
    fn controllers_are_hands_by_their_side_of_the_head_in_its_yaw_frame() {
        for (yaw, left_at) in [(0.0, 1.0), (std::f32::consts::PI, -1.0), (0.4, 1.0)] {
            let (mut p, c) = performer();
            let head = Quat::from_rotation_y(yaw);
            let x = head * Vec3::X;
            // The right controller first.
            send(
                &mut p,
                &c,
                vec![
                    device(
                        CON,
                        "A",
                        Vec3::new(0.0, 1.2, 0.0) - 0.3 * left_at * x,
                        Quat::IDENTITY,
                    ),
                    device(
                        CON,
                        "B",
                        Vec3::new(0.0, 1.2, 0.0) + 0.3 * left_at * x,
                        Quat::IDENTITY,
                    ),
                ],
            );
            // No head yet: nothing assigned, not ready.
            let d = p.take_devices();
            assert!(!d.ready && d.samples.is_empty(), "{d:?}");
            send(
                &mut p,
                &c,
                vec![device(HMD, "H", Vec3::new(0.0, 1.6, 0.0), head)],
            );
            let d = p.take_devices();
            assert!(d.ready);
            assert_eq!(d.names, ["head", "l_hand", "r_hand"]);
            assert_eq!(p.assigned(DeviceKind::Hmd, "H"), Some("head"));
            let (l, r) = if left_at > 0.0 {
                ("B", "A")
            } else {
                ("A", "B")
            };
            assert_eq!(
                p.assigned(DeviceKind::Controller, l),
                Some("l_hand"),
                "yaw {yaw}"
            );
            assert_eq!(
                p.assigned(DeviceKind::Controller, r),
                Some("r_hand"),
                "yaw {yaw}"
            );
            // Crossing the arms later changes nothing: an assignment sticks.
            send(
                &mut p,
                &c,
                vec![
                    device(CON, "A", Vec3::new(0.0, 1.2, 0.0) + x, Quat::IDENTITY),
                    device(CON, "B", Vec3::new(0.0, 1.2, 0.0) - x, Quat::IDENTITY),
                ],
            );
            let d = p.take_devices();
            assert_eq!(p.assigned(DeviceKind::Controller, l), Some("l_hand"));
            // Both changed, the head not.
            let changed: Vec<_> = d.samples.iter().map(|s| (s.0, s.2)).collect();
            assert!(changed.contains(&(0, false)), "{changed:?}");
            assert!(changed.contains(&(1, true)) && changed.contains(&(2, true)));
        }
    }

    #[test]
    fn a_lone_controller_goes_by_its_side_and_the_next_takes_the_other_hand() {
        let (mut p, c) = performer();
        send(
            &mut p,
            &c,
            vec![
                device(HMD, "H", Vec3::new(0.0, 1.6, 0.0), Quat::IDENTITY),
                device(CON, "R", Vec3::new(-0.3, 1.0, 0.0), Quat::IDENTITY),
            ],
        );
        assert!(!p.take_devices().ready);
        assert_eq!(p.assigned(DeviceKind::Controller, "R"), Some("r_hand"));
        // The second, on the same side (arms crossed): the free hand.
        send(
            &mut p,
            &c,
            vec![device(CON, "L", Vec3::new(-0.1, 1.0, 0.0), Quat::IDENTITY)],
        );
        assert!(p.take_devices().ready);
        assert_eq!(p.assigned(DeviceKind::Controller, "L"), Some("l_hand"));
    }

    #[test]
    fn trackers_are_hips_and_feet_by_height_nearness_and_side() {
        let (mut p, c) = performer();
        // The head turned to face −X (yaw −90°): its left is +Z.
        let head = Quat::from_rotation_y(-std::f32::consts::FRAC_PI_2);
        assert!((head * Vec3::Z).abs_diff_eq(-Vec3::X, 1e-6));
        let q = Quat::IDENTITY;
        send(
            &mut p,
            &c,
            vec![
                device(TRA, "elbow", Vec3::new(0.0, 1.0, 0.35), q),
                device(TRA, "right foot", Vec3::new(0.0, 0.1, -0.12), q),
                device(TRA, "knee", Vec3::new(0.0, 0.45, 0.1), q),
                device(TRA, "waist", Vec3::new(-0.08, 0.95, 0.02), q),
                device(TRA, "left foot", Vec3::new(0.05, 0.08, 0.1), q),
                device(TRA, "far", Vec3::new(2.0, 0.9, 0.0), q),
                device(HMD, "H", Vec3::new(0.0, 1.6, 0.0), head),
                device(CON, "c1", Vec3::new(0.0, 1.0, 0.3), q),
                device(CON, "c2", Vec3::new(0.0, 1.0, -0.3), q),
            ],
        );
        let d = p.take_devices();
        assert_eq!(
            d.names,
            ["head", "l_hand", "r_hand", "hips", "l_foot", "r_foot"]
        );
        let t = |s| p.assigned(DeviceKind::Tracker, s);
        assert_eq!(t("waist"), Some("hips"));
        assert_eq!(t("left foot"), Some("l_foot"));
        assert_eq!(t("right foot"), Some("r_foot"));
        assert_eq!((t("elbow"), t("knee"), t("far")), (None, None, None));
        assert_eq!(p.assigned(DeviceKind::Controller, "c1"), Some("l_hand"));
        // Every assigned device has a sample, indexed by the names.
        let mut slots: Vec<usize> = d.samples.iter().map(|s| s.0).collect();
        slots.sort_unstable();
        assert_eq!(slots, [0, 1, 2, 3, 4, 5]);
        let hips = d.samples.iter().find(|s| s.0 == 3).unwrap().1;
        assert!(
            hips.position
                .abs_diff_eq(Vec3::new(-0.08, 0.95, 0.02), 1e-6)
        );
    }

    #[test]
    fn serials_past_the_limit_are_refused_and_counted() {
        let (mut p, c) = performer();
        let many: Vec<_> = (0..MAX_DEVICES + 3)
            .map(|i| {
                device(
                    TRA,
                    &format!("T{i}"),
                    Vec3::new(0.0, 3.0, 0.0),
                    Quat::IDENTITY,
                )
            })
            .collect();
        send(&mut p, &c, many);
        assert_eq!(c.rejected_total(MessageReject::DeviceLimit), 3);
        // A known serial still updates.
        send(
            &mut p,
            &c,
            vec![device(TRA, "T0", Vec3::new(0.0, 2.0, 0.0), Quat::IDENTITY)],
        );
        assert_eq!(c.rejected_total(MessageReject::DeviceLimit), 3);
        assert!(p.devices_pending());
    }

    #[test]
    fn devices_do_not_count_as_bones() {
        let (mut p, c) = performer();
        send(
            &mut p,
            &c,
            vec![device(HMD, "H", Vec3::new(0.0, 1.6, 0.0), Quat::IDENTITY)],
        );
        assert!(!p.pending() && p.devices_pending());
        assert!(!p.take_pose().bones);
    }

    #[test]
    fn the_sender_clock_never_goes_back() {
        let mut c = SenderClock::default();
        assert_eq!(c.micros(1.0), 1_000_000);
        assert_eq!(c.micros(1.5), 1_500_000);
        // Restarted: goes on from where it was.
        assert_eq!(c.micros(0.0), 1_500_000);
        assert_eq!(c.micros(0.25), 1_750_000);
    }
}
