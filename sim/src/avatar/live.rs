//! One live-driven avatar's driver state: the latest source pose, its retargeting onto the
//! avatar's rig, and when the driver counts as gone.

use crate::avatar::trackers::{TrackerSample, Trackers};
use glam::{Mat4, Quat, Vec3};
use posecast_core::quota::{CommandRate, TokenBucket};
use posecast_proto::Transform;
use posecast_proto::command::OnRelease;
use posecast_proto::fk::forward_kinematics;
use posecast_proto::live::MAX_RATE_HZ;
use posecast_rigs::rig::Rig;
use posecast_rigs::rig::retarget::{PoseRetargeter, PoseScratch};
use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Poses a driver may send at once above [`MAX_RATE_HZ`]: 100 ms worth, so network clumping
/// of a steady 120 Hz stream is not refused, while a sustained flood is.
pub const RATE_BURST: f64 = 12.0;

/// A live driver's pose of an avatar (consulted by [`crate::avatar::Avatar::evaluate`]
/// between the clip and the joint overrides).
///
/// Sampling at the tick takes the **latest** pose received (see `docs/src/how-to/live-driving.md`): the
/// driver's timestamps only order poses (an older one than the last applied is dropped).
#[derive(Debug)]
pub struct LivePose {
    /// The driving connection; `None` once it left with [`OnRelease::Hold`] (the pose holds).
    pub driver: Option<u64>,
    /// What happens when the driver leaves.
    pub on_release: OnRelease,
    /// The rig whose joints the poses name.
    pub source: Arc<Rig>,
    /// World-space retargeting from `source` to the avatar's rig; `None` when they are one rig
    /// (rotations are then the avatar's own local rotations).
    map: Option<(PoseRetargeter, PoseScratch)>,
    /// The source pose: local rotation per source joint.
    src_rot: Vec<Quat>,
    /// The source root's local translation, once one arrived.
    src_root: Option<Vec3>,
    /// The avatar's local rotations solved from the source pose.
    out_rot: Vec<Quat>,
    /// The avatar's root joint and its local translation, once a root position arrived.
    out_root: Option<(usize, Vec3)>,
    dirty: bool,
    last_pose: Instant,
    last_time_us: Option<u64>,
    rate: TokenBucket,
    timeout: Duration,
    /// Scratch for root positions: source and target world matrices.
    src_world: Vec<Mat4>,
    tgt_world: Vec<Mat4>,
    /// Blend shape (expression) values the driver applied, by name, as sent: kept and reported
    /// (`get_avatar`); VMC input sets them (and the avatar's morph weights they name).
    pub blend_shapes: BTreeMap<String, f32>,
    /// Who drives, as told to clients (presence); `None` until the server says.
    pub by: Option<posecast_proto::command::Driver>,
    /// The avatar's joints the driver owns (`drive … joints`); `None`: all of them.
    pub owned: Option<Vec<bool>>,
    /// A tracker drive (`drive … trackers`): the body is solved from these each evaluation
    /// instead of taking the driver's rotations.
    pub trackers: Option<Trackers>,
    /// When the drive began (the trackers' clock when poses carry no time).
    started: Instant,
}

/// A source pose, validated: every joint index is in range, every rotation a unit quaternion.
#[derive(Debug, Default)]
pub struct ValidPose {
    /// `(source joint, local rotation)`.
    pub rotations: Vec<(usize, Quat)>,
    /// The source root's local translation.
    pub root_position: Option<Vec3>,
    /// Driver time, µs.
    pub time_us: Option<u64>,
}

impl LivePose {
    /// A driver `conn` of an avatar of `target` whose current pose is `current`; poses name
    /// `source`'s joints.
    ///
    /// # Errors
    /// The rigs cannot be retargeted (not humanoid, see [`PoseRetargeter::new`]).
    pub fn new(
        conn: u64,
        on_release: OnRelease,
        source: Arc<Rig>,
        target: &Arc<Rig>,
        current: &[Transform],
        timeout: Duration,
    ) -> Result<Self, posecast_rigs::rig::RigError> {
        let same = Arc::ptr_eq(&source, target) || source.name == target.name;
        let map = if same {
            None
        } else {
            let (s, t) = (source.view(), target.view());
            Some((PoseRetargeter::new(s, t)?, PoseScratch::new(s, t)))
        };
        // The own rig starts from the avatar's pose, so a partial pose changes only the joints
        // it names; a source rig starts at neutral (identity, the pose both rigs share).
        let src_rot = if same {
            current.iter().map(|t| t.rotation).collect()
        } else {
            vec![Quat::IDENTITY; source.skeleton().len()]
        };
        let n_src = source.skeleton().len();
        let n_tgt = target.skeleton().len();
        Ok(Self {
            driver: Some(conn),
            on_release,
            out_rot: current.iter().map(|t| t.rotation).collect(),
            map,
            src_rot,
            src_root: None,
            out_root: None,
            dirty: true,
            last_pose: Instant::now(),
            last_time_us: None,
            rate: TokenBucket::new(CommandRate {
                per_second: f64::from(MAX_RATE_HZ),
                burst: RATE_BURST,
            }),
            timeout,
            src_world: vec![Mat4::IDENTITY; n_src],
            tgt_world: vec![Mat4::IDENTITY; n_tgt],
            blend_shapes: BTreeMap::new(),
            by: None,
            owned: None,
            trackers: None,
            started: Instant::now(),
            source,
        })
    }

    /// Takes one pose from the driver's rate budget.
    ///
    /// # Errors
    /// The time until a pose would be accepted.
    pub fn take_rate(&mut self, now: Instant) -> Result<(), Duration> {
        self.rate.take_at(now)
    }

    /// Stores a validated pose (it shows at the next evaluation). A pose older than the last
    /// one stored (by driver time) is dropped; returns whether it was stored.
    pub fn store(&mut self, pose: ValidPose, now: Instant) -> bool {
        if let (Some(t), Some(last)) = (pose.time_us, self.last_time_us)
            && t < last
        {
            return false;
        }
        for (j, q) in pose.rotations {
            if let Some(slot) = self.src_rot.get_mut(j) {
                *slot = q;
            }
        }
        if pose.root_position.is_some() {
            self.src_root = pose.root_position;
        }
        self.last_time_us = pose.time_us.or(self.last_time_us);
        self.last_pose = now;
        self.dirty = true;
        true
    }

    /// Stores tracker samples (a tracker drive's pose), taken at driver time `time_us` (else
    /// when they arrived). A pose older than the last one stored is dropped; returns whether it
    /// was stored. Nothing is stored on a drive without trackers.
    pub fn store_trackers(
        &mut self,
        samples: &[(usize, TrackerSample)],
        time_us: Option<u64>,
        now: Instant,
    ) -> bool {
        if let (Some(t), Some(last)) = (time_us, self.last_time_us)
            && t < last
        {
            return false;
        }
        let Some(trackers) = self.trackers.as_mut() else {
            return false;
        };
        let time = time_us.map_or_else(
            || now.saturating_duration_since(self.started).as_secs_f64(),
            |t| t as f64 / 1e6,
        );
        trackers.store(samples, time);
        self.last_time_us = time_us.or(self.last_time_us);
        self.last_pose = now;
        true
    }

    /// Whether the driver has been silent for longer than the timeout.
    #[must_use]
    pub fn expired(&self, now: Instant) -> bool {
        self.driver.is_some() && now.saturating_duration_since(self.last_pose) > self.timeout
    }

    /// Solves the avatar's local rotations (and root translation) from the latest source pose,
    /// when a new one arrived since the last solve.
    pub fn solve(&mut self, target: &Rig) {
        if !self.dirty {
            return;
        }
        self.dirty = false;
        let Some((map, scratch)) = &mut self.map else {
            self.out_rot.clone_from(&self.src_rot);
            self.out_root = self
                .src_root
                .zip(target.skeleton().roots().next())
                .map(|(p, r)| (r, p));
            return;
        };
        map.solve(&self.src_rot, scratch, &mut self.out_rot);
        let Some(root) = self.src_root else {
            return;
        };
        // The source's humanoid root in world space, mapped like a baked clip's root: scaled
        // by the hip-height ratio about both rigs' neutral positions.
        let ss = self.source.skeleton();
        let mut locals: Vec<Transform> = ss.rest().to_vec();
        for (l, q) in locals.iter_mut().zip(&self.src_rot) {
            l.rotation = *q;
        }
        if let Some(r) = ss.roots().next()
            && let Some(l) = locals.get_mut(r)
        {
            l.translation = root;
        }
        forward_kinematics(ss, &locals, &mut self.src_world);
        let src_pos = self.src_world[map.src_root].w_axis.truncate();
        let desired = map.tgt_start + map.k * (src_pos - map.src_start);
        let ts = target.skeleton();
        let mut pose = map.tgt_neutral.clone();
        for (l, q) in pose.iter_mut().zip(&self.out_rot) {
            l.rotation = *q;
        }
        forward_kinematics(ts, &pose, &mut self.tgt_world);
        let local = match ts.parents()[map.tgt_root] {
            Some(p) => self.tgt_world[p].inverse().transform_point3(desired),
            None => desired,
        };
        self.out_root = Some((map.tgt_root, local));
    }

    /// Writes the live pose over `locals` (the clip's pose): every joint's rotation it owns
    /// ([`LivePose::owned`]; all without one), and the root translation once the driver sent
    /// one (when it owns the root).
    ///
    /// A tracker drive solves the body instead ([`Trackers::solve`]), the avatar placed at
    /// `placement` at scene clock `clock`, `world` scratch; joints it does not own keep what
    /// `locals` had.
    pub fn apply(
        &mut self,
        target: &Rig,
        placement: Mat4,
        clock: f64,
        locals: &mut [Transform],
        world: &mut [Mat4],
    ) {
        if let Some(trackers) = self.trackers.as_mut() {
            let before = self.owned.as_ref().map(|_| locals.to_vec());
            trackers.solve(target, placement, clock, locals, world);
            if let (Some(owned), Some(before)) = (&self.owned, before) {
                for (j, (l, b)) in locals.iter_mut().zip(before).enumerate() {
                    if !owned.get(j).copied().unwrap_or(false) {
                        *l = b;
                    }
                }
            }
            return;
        }
        self.solve(target);
        let owns = |j: usize| {
            self.owned
                .as_ref()
                .is_none_or(|o| o.get(j).copied().unwrap_or(false))
        };
        for (j, (l, q)) in locals.iter_mut().zip(&self.out_rot).enumerate() {
            if owns(j) {
                l.rotation = *q;
            }
        }
        if let Some((j, t)) = self.out_root
            && owns(j)
            && let Some(l) = locals.get_mut(j)
        {
            l.translation = t;
        }
    }
}
