//! Tracker driving (`drive … trackers`, issue 29): a headset and two controllers — and
//! optionally hip and foot trackers, or trackers on named joints — give world transforms, and
//! every tick the whole body is solved from them, once, for every viewer.
//!
//! **Input.** Each tracker's samples pass a One Euro filter (Casiez, Roussel and Vogel, CHI
//! 2012: a low-pass whose cutoff rises with the signal's speed, so a still tracker's jitter is
//! smoothed away while a fast one lags little), on the driver's clock, as they arrive; the tick
//! solves from the filtered values, so trackers at 72–120 Hz, jittery or clumped, give one
//! smooth pose per tick. A tracker that goes quiet holds its last transform.
//!
//! **Calibration** ([`Trackers::calibrate`]): the user stands in the neutral pose (or a T- or
//! A-pose);
//! the head tracker's height against the avatar's head height gives the scale the user's
//! positions are shrunk or grown by (about the user's place on the floor, so walking is not
//! scaled), a T- or A-pose's hand span the arms' own scale, and each tracker's offset to the joint it
//! stands for is measured (a controller held in the hand is not the wrist). Uncalibrated, a
//! tracker *is* its joint (`proto::trackers`).
//!
//! **The solve** (model space, every tick, [`Trackers::solve`]):
//! 1. the body's heading: the hip tracker's yaw, or the head's, followed with a dead zone of
//!    [`HEADING_DEAD_ZONE`] (looking around does not turn the body);
//! 2. the hips (`humanoid_root`): the hip tracker, or hung below the head by the rest offset
//!    from the head to the hips, turned by the heading, never higher than at rest (a user
//!    crouching bends the legs; one taller than the avatar stretches the spine straight);
//! 3. spine and neck by FABRIK ([`crate::ik::chain`]) from the hips to the head, the head
//!    turned to the head tracker's rotation;
//! 4. arms by two-bone IK ([`crate::ik::two_bone`]) to the hand trackers, the elbow swivelled
//!    toward a pole below, behind and outside the shoulder that rises and swings out as the
//!    hand rises above the shoulder;
//! 5. legs: to the foot trackers; else **planted**: each foot stays where it was put and steps
//!    ([`STEP_SECONDS`], a lifted arc) when the hips move or turn away from it, one foot at a
//!    time; or **animated**: the legs keep what the clip and layers gave them; or
//!    **locomotion**: the legs play the drive's locomotion clip nearest the hips' speed, at the
//!    rate matching it ([`Trackers::gait`]; the avatar plays it on a `@locomotion` layer);
//! 6. trackers on other joints, as IK goals (a limb end with its limb, else a 3-joint chain).

use crate::avatar::goals::{self, Solver};
use crate::ik::{self, ChainGoal, LimbGoal};
use glam::{Mat4, Quat, Vec3};
use posecast_proto::fk::forward_kinematics;
use posecast_proto::trackers::{
    CalibrationPose, HEAD, HIPS, LEFT_FOOT, LEFT_HAND, Legs, LocomotionClip, MAX_LOCOMOTION_CLIPS,
    MAX_TRACKERS, REQUIRED, RIGHT_FOOT, RIGHT_HAND,
};
use posecast_proto::{Skeleton, Transform};
use posecast_rigs::rig::Rig;
use std::f32::consts::PI;

/// How far the head may turn from the body's heading before the body follows, radians (35°).
pub const HEADING_DEAD_ZONE: f32 = 35.0 * PI / 180.0;
/// A planted foot steps once it is this share of the leg's length from where it belongs.
pub const STEP_TRIGGER: f32 = 0.2;
/// A planted foot also steps once its yaw is this far from the body's heading, radians.
pub const STEP_TURN: f32 = 40.0 * PI / 180.0;
/// How long a step takes, seconds.
pub const STEP_SECONDS: f64 = 0.3;
/// How high a step lifts the foot, as a share of the leg's length.
pub const STEP_HEIGHT: f32 = 0.08;

/// The One Euro filter's settings for positions: cutoff at rest (Hz) and its rise per m/s.
pub const POSITION_FILTER: (f32, f32) = (1.5, 4.0);
/// The same for rotations: cutoff at rest (Hz) and its rise per rad/s.
pub const ROTATION_FILTER: (f32, f32) = (1.5, 1.0);
/// The cutoff of the speed estimate the filter's cutoff follows, Hz.
const SPEED_CUTOFF: f32 = 1.0;
/// The forward curve each spine joint starts each solve with, radians (2°).
const SPINE_CURVE: f32 = 2.0 * PI / 180.0;
/// How far an elbow's swivel moves each solve from where it bent last toward the natural one.
const ELBOW_EASE: f32 = 0.1;
/// The fastest a locomotion clip may walk, m/s.
pub const MAX_LOCOMOTION_SPEED: f32 = 20.0;
/// The time constant the hips' speed is smoothed with, seconds.
const SPEED_SMOOTHING: f32 = 0.25;
/// How much nearer (in log speed ratio) another locomotion clip must be to be switched to.
const GAIT_HYSTERESIS: f32 = 0.15;
/// An ankle's height above the floor, as a share of the leg's length, for a rig whose ankles
/// are its lowest joints.
const ANKLE_CLEARANCE: f32 = 0.08;
/// Smallest and largest calibrated scale (a user a quarter or four times the avatar's size).
pub const SCALE_RANGE: (f32, f32) = (0.25, 4.0);

/// One tracker's transform in the scene's space.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrackerSample {
    /// Position, metres.
    pub position: Vec3,
    /// Rotation (unit).
    pub rotation: Quat,
}

/// Why trackers cannot drive an avatar, or cannot be calibrated.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum TrackerError {
    /// A required tracker is not in the list.
    #[error("trackers must include {0} (head, l_hand and r_hand are required)")]
    Required(&'static str),
    /// A name is neither a standard tracker nor a joint of the rig.
    #[error(
        "tracker {0:?} is neither a standard tracker (head, l_hand, r_hand, hips, l_foot, r_foot) nor a joint of the rig"
    )]
    Unknown(String),
    /// A name appears twice.
    #[error("tracker {0:?} is named twice")]
    Duplicate(String),
    /// Too many trackers.
    #[error("{0} trackers: at most {MAX_TRACKERS}")]
    TooMany(usize),
    /// The rig lacks a joint the solve needs.
    #[error("the rig has no {joint} joint (H-Anim name), which {what} needs")]
    MissingJoint {
        /// The H-Anim joint.
        joint: &'static str,
        /// What needs it.
        what: &'static str,
    },
    /// A joint tracker names a root joint: nothing to reach with.
    #[error("tracker {0:?} names a root joint: it has no chain to reach with")]
    NoChain(String),
    /// Calibration needs samples of these trackers first.
    #[error("no sample of tracker {0} yet: send poses before calibrating")]
    NoSample(String),
    /// The head is too low (or below the floor) to measure a height from.
    #[error("the head tracker is {0:.3} m above the floor: too low to measure the user's height")]
    TooLow(f32),
    /// A `locomotion` list that cannot be played.
    #[error("locomotion: {0}")]
    Locomotion(String),
    /// The hands are too close for a T- or A-pose.
    #[error("the hand trackers are {0:.3} m apart: not a T- or A-pose")]
    NotTPose(f32),
}

/// What a calibration measured.
#[derive(Debug, Clone, PartialEq)]
pub struct Calibration {
    /// The head tracker's height above the floor (the avatar's placement), metres.
    pub user_height: f32,
    /// Avatar size over user size.
    pub scale: f32,
    /// The same for the arms.
    pub arm_scale: f32,
    /// The trackers whose offsets were measured.
    pub trackers: Vec<String>,
}

/// What a tracker stands for.
#[derive(Debug, Clone, PartialEq)]
enum Slot {
    Head,
    /// 0 left, 1 right.
    Hand(usize),
    Hips,
    Foot(usize),
    /// Another joint, reached as an IK goal.
    Joint(usize, Solver),
}

/// A One Euro filter's state for one tracker.
#[derive(Debug, Clone, Copy)]
struct Filtered {
    position: Vec3,
    rotation: Quat,
    speed: f32,
    angular_speed: f32,
    time: f64,
}

/// The smoothing factor of a first-order low-pass of `cutoff` Hz over `dt` seconds.
fn alpha(cutoff: f32, dt: f32) -> f32 {
    let tau = 1.0 / (2.0 * PI * cutoff);
    dt / (dt + tau)
}

impl Filtered {
    fn new(s: TrackerSample, time: f64) -> Self {
        Self {
            position: s.position,
            rotation: s.rotation,
            speed: 0.0,
            angular_speed: 0.0,
            time,
        }
    }

    /// Takes sample `s` at `time` (One Euro); `smooth` false takes it as it is.
    fn update(&mut self, s: TrackerSample, time: f64, smooth: bool) {
        // Same or older timestamps (clumped packets) count as one 120 Hz interval.
        let dt = if time > self.time {
            ((time - self.time) as f32).min(1.0)
        } else {
            1.0 / 120.0
        };
        self.time = self.time.max(time);
        let rotation = if self.rotation.dot(s.rotation) < 0.0 {
            -s.rotation
        } else {
            s.rotation
        };
        if !smooth {
            self.position = s.position;
            self.rotation = rotation;
            return;
        }
        let a = alpha(SPEED_CUTOFF, dt);
        let speed = s.position.distance(self.position) / dt;
        self.speed += a * (speed - self.speed);
        let angular = self.rotation.angle_between(rotation) / dt;
        self.angular_speed += a * (angular - self.angular_speed);
        let (min, beta) = POSITION_FILTER;
        let ap = alpha(min + beta * self.speed, dt);
        self.position = self.position.lerp(s.position, ap);
        let (min, beta) = ROTATION_FILTER;
        let ar = alpha(min + beta * self.angular_speed, dt);
        self.rotation = self.rotation.slerp(rotation, ar).normalize();
    }
}

/// The rig's joints the solve moves and its proportions at neutral.
#[derive(Debug, Clone)]
struct Body {
    root: usize,
    skeleton_root: usize,
    skull: usize,
    /// From the first joint above the root up to the skull.
    spine: Vec<usize>,
    arms: [Option<[usize; 3]>; 2],
    /// Each arm's clavicle (`l_sternoclavicular`), when the rig has one above the shoulder.
    clavicles: [Option<usize>; 2],
    /// The spine's length from its first joint to the skull, at neutral.
    spine_length: f32,
    legs: [Option<[usize; 3]>; 2],
    /// The rig's skeleton (for calibration poses).
    skeleton: Skeleton,
    /// Its neutral pose: rest translations and scales, identity rotations.
    neutral_locals: Vec<Transform>,
    /// Neutral-pose model-space positions.
    neutral: Vec<Vec3>,
    leg_length: f32,
    /// Joints reset to neutral before each solve (legs: when the solve moves them).
    reset: Vec<usize>,
}

fn hanim(rig: &Rig, name: &str) -> Option<usize> {
    rig.hanim_joint(name)
}

/// The joint a rig's H-Anim (or own) joint name stands for in a tracker drive: the joint
/// itself, except that a rig with no head joint (`skullbase`; CesiumMan's skeleton ends at its
/// neck) takes its topmost neck joint (`vc1` … `vc7`, the lowest number mapped) for the head.
#[must_use]
pub fn tracker_joint(rig: &Rig, name: &str) -> Option<usize> {
    hanim(rig, name).or_else(|| {
        (name == "skullbase")
            .then(|| (1..=7).find_map(|k| hanim(rig, &format!("vc{k}"))))
            .flatten()
    })
}

fn is_ancestor(parents: &[Option<usize>], a: usize, of: usize) -> bool {
    std::iter::successors(parents[of], |&p| parents[p]).any(|p| p == a)
}

impl Body {
    fn new(rig: &Rig) -> Result<Self, TrackerError> {
        let skeleton = rig.skeleton();
        let parents = skeleton.parents();
        let need = |joint: &'static str, what: &'static str| {
            hanim(rig, joint).ok_or(TrackerError::MissingJoint { joint, what })
        };
        let root = need("humanoid_root", "placing the hips")?;
        let skull = tracker_joint(rig, "skullbase").ok_or(TrackerError::MissingJoint {
            joint: "skullbase",
            what: "the head tracker (or a neck joint, vc1 to vc7, for it)",
        })?;
        if !is_ancestor(parents, root, skull) {
            return Err(TrackerError::MissingJoint {
                joint: "skullbase",
                what: "a spine above humanoid_root",
            });
        }
        let mut spine: Vec<usize> = std::iter::successors(Some(skull), |&j| parents[j])
            .take_while(|&j| j != root)
            .collect();
        spine.reverse();
        let limb = |a: &str, b: &str, c: &str| -> Option<[usize; 3]> {
            let (a, b, c) = (hanim(rig, a)?, hanim(rig, b)?, hanim(rig, c)?);
            (is_ancestor(parents, a, b) && is_ancestor(parents, b, c)).then_some([a, b, c])
        };
        let arms = [
            limb("l_shoulder", "l_elbow", "l_wrist"),
            limb("r_shoulder", "r_elbow", "r_wrist"),
        ];
        for (arm, joint) in arms.iter().zip(["l_wrist", "r_wrist"]) {
            if arm.is_none() {
                return Err(TrackerError::MissingJoint {
                    joint,
                    what: "a hand tracker (with its shoulder and elbow)",
                });
            }
        }
        let legs = [
            limb("l_hip", "l_knee", "l_ankle"),
            limb("r_hip", "r_knee", "r_ankle"),
        ];
        let mut locals: Vec<Transform> = skeleton.rest().to_vec();
        for l in &mut locals {
            l.rotation = Quat::IDENTITY;
        }
        let mut world = vec![Mat4::IDENTITY; skeleton.len()];
        forward_kinematics(skeleton, &locals, &mut world);
        let neutral: Vec<Vec3> = world.iter().map(|m| m.w_axis.truncate()).collect();
        let leg_length = legs
            .iter()
            .flatten()
            .map(|[a, b, c]| neutral[*a].distance(neutral[*b]) + neutral[*b].distance(neutral[*c]))
            .fold(0.0, f32::max)
            .max(1e-3);
        // Heights count from the floor, y = 0 in model space. A neutral pose reaching below it
        // (a BVH's, its hips at the origin and its height in its clips' root translation) is
        // lifted onto it: its lowest joint on the floor, or a sole's clearance above it when
        // that is an ankle (a rig without toes).
        let (lowest, floor) = neutral
            .iter()
            .enumerate()
            .map(|(j, p)| (j, p.y))
            .min_by(|a, b| a.1.total_cmp(&b.1))
            .unwrap_or((root, 0.0));
        let sole = if legs.iter().flatten().any(|l| l[2] == lowest) {
            ANKLE_CLEARANCE * leg_length
        } else {
            0.0
        };
        // A neutral pose standing on y = 0 or above is taken as it is.
        let lift = if floor < 0.0 { sole - floor } else { 0.0 };
        let neutral: Vec<Vec3> = neutral.into_iter().map(|p| p + Vec3::Y * lift).collect();
        let clavicles = [("l_sternoclavicular", 0), ("r_sternoclavicular", 1)].map(|(n, side)| {
            let c = hanim(rig, n)?;
            let [shoulder, _, _] = arms[side]?;
            is_ancestor(parents, c, shoulder).then_some(c)
        });
        let spine_length = spine
            .windows(2)
            .map(|w| neutral[w[0]].distance(neutral[w[1]]))
            .sum();
        // The clavicles keep the pose's (clip or rest): the solve only turns them further
        // when a hand is out of reach.
        let mut reset = vec![root];
        reset.extend(&spine);
        reset.extend(arms.iter().flatten().flatten());
        let skeleton_root = std::iter::successors(Some(root), |&j| parents[j])
            .last()
            .unwrap_or(root);
        Ok(Self {
            root,
            skeleton_root,
            skull,
            spine,
            arms,
            clavicles,
            spine_length,
            legs,
            skeleton: skeleton.clone(),
            neutral_locals: locals,
            neutral,
            leg_length,
            reset,
        })
    }

    /// The skull above the hips at neutral, model space.
    fn head_over_hips(&self) -> Vec3 {
        self.neutral[self.skull] - self.neutral[self.root]
    }

    /// Where a foot stands under hips at `hips` turned by `heading`.
    fn foot_home(&self, side: usize, hips: Vec3, heading: Quat) -> Option<Vec3> {
        let [_, _, ankle] = self.legs[side]?;
        let offset = self.neutral[ankle] - self.neutral[self.root];
        let mut p = hips + heading * Vec3::new(offset.x, 0.0, offset.z);
        p.y = self.neutral[ankle].y;
        Some(p)
    }
}

/// A planted foot.
#[derive(Debug, Clone, Copy)]
struct Foot {
    plant: Vec3,
    yaw: f32,
    step: Option<(Vec3, f32, f64)>,
}

/// An avatar's trackers: their samples, calibration and the feet's state.
#[derive(Debug, Clone)]
pub struct Trackers {
    names: Vec<String>,
    slots: Vec<Slot>,
    samples: Vec<Option<Filtered>>,
    legs: Legs,
    body: Body,
    smooth: bool,
    scale: f32,
    arm_scale: f32,
    /// Per tracker: its joint's transform in the tracker's frame (position, rotation).
    offsets: Vec<(Vec3, Quat)>,
    /// The body's yaw, radians (about +Y; 0 faces +Z).
    heading: Option<f32>,
    feet: [Option<Foot>; 2],
    last_clock: f64,
    /// Where each elbow bent last tick: from the middle of shoulder and hand, body frame.
    elbows: [Option<Vec3>; 2],
    /// `legs: locomotion`: the clips the legs may play (index into the rig's clips, the speed
    /// its walk covers, m/s), the hips' smoothed horizontal speed (m/s), where the hips were at
    /// which clock, and the clip picked (index into `locomotion`).
    locomotion: Vec<(usize, f32)>,
    speed: f32,
    last_hips: Option<(Vec3, f64)>,
    gait: Option<usize>,
    /// The spine's solved positions last tick, relative to its first joint (FABRIK's start).
    spine_seed: Vec<Vec3>,
}

/// The yaw (about +Y, 0 facing +Z) a rotation faces: its forward axis flattened, or, when
/// that points straight up or down, its up axis (looking down, the top of the head faces
/// forward).
#[must_use]
pub fn yaw_of(q: Quat) -> f32 {
    let f = q * Vec3::Z;
    let up = q * Vec3::Y;
    let h = if f.x.hypot(f.z) > 0.3 {
        f
    } else if f.y < 0.0 {
        up
    } else {
        -up
    };
    h.x.atan2(h.z)
}

/// Most a clavicle turns to bring a hand's target within the arm's reach, radians (30°).
pub const SHRUG_LIMIT: f32 = 30.0 * PI / 180.0;

/// When `target` is beyond the arm's `reach` from the shoulder, turns the clavicle (about
/// itself, toward the target) by the least share of the way that brings it within reach, at
/// most [`SHRUG_LIMIT`]: reaching up or across, people move the shoulder too.
fn shrug(
    skeleton: &Skeleton,
    locals: &mut [Transform],
    world: &mut [Mat4],
    clavicle: usize,
    shoulder: usize,
    target: Vec3,
    reach: f32,
) {
    // Brought just within reach: a limb at its full length has no bend to keep.
    let within = reach - 2e-5;
    let c = ik::position(world, clavicle);
    let s = ik::position(world, shoulder);
    if target.distance(s) <= reach || !target.is_finite() {
        return;
    }
    let (Some(from), Some(to)) = (ik::direction(s - c), ik::direction(target - c)) else {
        return;
    };
    let full = Quat::from_rotation_arc(from, to);
    let limit = (SHRUG_LIMIT / full.angle_between(Quat::IDENTITY).max(1e-6)).min(1.0);
    let at = |f: f32| c + Quat::IDENTITY.slerp(full, f) * (s - c);
    // The least share that reaches, by bisection (the distance falls as the share grows).
    let (mut lo, mut hi) = (0.0, limit);
    if target.distance(at(hi)) > within {
        lo = hi;
    } else {
        for _ in 0..12 {
            let mid = 0.5 * (lo + hi);
            if target.distance(at(mid)) > within {
                lo = mid;
            } else {
                hi = mid;
            }
        }
    }
    let share = if lo >= limit { limit } else { hi };
    let g = ik::rotation(world, clavicle);
    let r = Quat::IDENTITY.slerp(full, share);
    locals[clavicle].rotation = (locals[clavicle].rotation * (g.inverse() * r * g)).normalize();
    ik::update_world(skeleton, locals, world, clavicle);
}

fn wrap(a: f32) -> f32 {
    (a + PI).rem_euclid(2.0 * PI) - PI
}

fn yaw(a: f32) -> Quat {
    Quat::from_rotation_y(a)
}

impl Trackers {
    /// Trackers `names` driving an avatar of `rig` (see `proto::trackers`: the standard names,
    /// or a joint by its rig or H-Anim name), its legs moved as `legs` says.
    ///
    /// # Errors
    /// A missing required tracker, an unknown or repeated name, too many, a rig lacking the
    /// joints the solve needs.
    pub fn new(rig: &Rig, names: &[String], legs: Legs) -> Result<Self, TrackerError> {
        if names.len() > MAX_TRACKERS {
            return Err(TrackerError::TooMany(names.len()));
        }
        for r in REQUIRED {
            if !names.iter().any(|n| n == r) {
                return Err(TrackerError::Required(r));
            }
        }
        let body = Body::new(rig)?;
        let skeleton = rig.skeleton();
        let mut slots = Vec::with_capacity(names.len());
        for (i, name) in names.iter().enumerate() {
            if names[..i].contains(name) {
                return Err(TrackerError::Duplicate(name.clone()));
            }
            let slot = match name.as_str() {
                HEAD => Slot::Head,
                LEFT_HAND => Slot::Hand(0),
                RIGHT_HAND => Slot::Hand(1),
                HIPS => Slot::Hips,
                LEFT_FOOT | RIGHT_FOOT => {
                    let side = usize::from(name == RIGHT_FOOT);
                    if body.legs[side].is_none() {
                        return Err(TrackerError::MissingJoint {
                            joint: ["l_ankle", "r_ankle"][side],
                            what: "a foot tracker (with its hip and knee)",
                        });
                    }
                    Slot::Foot(side)
                }
                other => {
                    let j = hanim(rig, other).ok_or_else(|| TrackerError::Unknown(other.into()))?;
                    let joint = &skeleton.names()[j];
                    let (end, solver) = goals::solver(rig, joint, None).map_err(|e| match e {
                        goals::GoalError::NoChain(_) => TrackerError::NoChain(other.into()),
                        _ => TrackerError::Unknown(other.into()),
                    })?;
                    Slot::Joint(end, solver)
                }
            };
            slots.push(slot);
        }
        Ok(Self {
            names: names.to_vec(),
            samples: vec![None; slots.len()],
            offsets: vec![(Vec3::ZERO, Quat::IDENTITY); slots.len()],
            slots,
            legs,
            body,
            smooth: true,
            scale: 1.0,
            arm_scale: 1.0,
            heading: None,
            feet: [None; 2],
            last_clock: f64::NEG_INFINITY,
            spine_seed: Vec::new(),
            elbows: [None; 2],
            locomotion: Vec::new(),
            speed: 0.0,
            last_hips: None,
            gait: None,
        })
    }

    /// The trackers, in the order binary poses index them.
    #[must_use]
    pub fn names(&self) -> &[String] {
        &self.names
    }

    /// How the legs move.
    #[must_use]
    pub fn legs(&self) -> Legs {
        self.legs
    }

    /// Turns the input filter on (the default) or off (samples taken as they are).
    pub fn set_smoothing(&mut self, on: bool) {
        self.smooth = on;
    }

    /// The clips a `legs: locomotion` drive's legs play (see [`Trackers::gait`]).
    ///
    /// # Errors
    /// The legs are not [`Legs::Locomotion`], the list is empty or longer than
    /// [`MAX_LOCOMOTION_CLIPS`], a clip is not one of the rig's, a speed is not within 0–20 m/s.
    pub fn set_locomotion(
        &mut self,
        rig: &Rig,
        clips: &[LocomotionClip],
    ) -> Result<(), TrackerError> {
        let bad = |why: String| Err(TrackerError::Locomotion(why));
        if self.legs != Legs::Locomotion {
            return bad("give it with legs \"locomotion\"".into());
        }
        if clips.is_empty() || clips.len() > MAX_LOCOMOTION_CLIPS {
            return bad(format!(
                "{} clips: name 1 to {MAX_LOCOMOTION_CLIPS}",
                clips.len()
            ));
        }
        let mut resolved = Vec::with_capacity(clips.len());
        for c in clips {
            let Some(i) = rig.clips.iter().position(|k| k.name() == c.clip) else {
                return bad(format!("the avatar's rig has no clip {:?}", c.clip));
            };
            if !(c.speed.is_finite() && (0.0..=MAX_LOCOMOTION_SPEED).contains(&c.speed)) {
                return bad(format!(
                    "clip {:?}: speed {} is not within 0 to {MAX_LOCOMOTION_SPEED} m/s",
                    c.clip, c.speed
                ));
            }
            resolved.push((i, c.speed));
        }
        self.locomotion = resolved;
        self.gait = None;
        Ok(())
    }

    /// The locomotion clip the legs play now (an index into the rig's clips) and its rate:
    /// the clip whose speed is nearest the hips' (by ratio), switched only when another is
    /// clearly nearer, played at the hips' speed over its own (within 0.25–3; rate 1 for a
    /// clip of speed 0). `None` without `legs: locomotion` or before the first solve.
    #[must_use]
    pub fn gait(&self) -> Option<(usize, f32)> {
        let &(clip, speed) = self.locomotion.get(self.gait?)?;
        let rate = if speed > 0.0 {
            (self.speed / speed).clamp(0.25, 3.0)
        } else {
            1.0
        };
        Some((clip, rate))
    }

    /// The hips' smoothed horizontal speed, m/s (kept for `legs: locomotion`).
    #[must_use]
    pub fn hips_speed(&self) -> f32 {
        self.speed
    }

    /// Follows the hips' speed and picks the locomotion clip for it.
    fn walk(&mut self, hips: Vec3, clock: f64) {
        if self.locomotion.is_empty() {
            return;
        }
        match self.last_hips {
            Some((p, t)) if clock > t => {
                let dt = (clock - t) as f32;
                let v = Vec3::new(hips.x - p.x, 0.0, hips.z - p.z).length() / dt.max(1e-4);
                let a = dt / (dt + SPEED_SMOOTHING);
                self.speed += a * (v.min(100.0) - self.speed);
                self.last_hips = Some((hips, clock));
            }
            Some((_, t)) if clock == t => {}
            _ => {
                self.last_hips = Some((hips, clock));
                self.speed = 0.0;
            }
        }
        let score = |s: f32| ((self.speed + 0.1) / (s + 0.1)).ln().abs();
        let best = (0..self.locomotion.len())
            .min_by(|&a, &b| score(self.locomotion[a].1).total_cmp(&score(self.locomotion[b].1)));
        self.gait = match (self.gait, best) {
            (Some(now), Some(best))
                if score(self.locomotion[best].1)
                    > score(self.locomotion[now].1) - GAIT_HYSTERESIS =>
            {
                Some(now)
            }
            (_, best) => best,
        };
    }

    /// Stores samples (`(tracker index, transform in scene space)`, indices checked by the
    /// caller; out-of-range ones are ignored) taken at `time` on the driver's clock, seconds.
    pub fn store(&mut self, samples: &[(usize, TrackerSample)], time: f64) {
        for &(i, s) in samples {
            if let Some(slot) = self.samples.get_mut(i) {
                match slot {
                    Some(f) => f.update(s, time, self.smooth),
                    None => *slot = Some(Filtered::new(s, time)),
                }
            }
        }
    }

    /// The latest (filtered) transform of each tracker in the avatar's model space, positions
    /// scaled about the user's place on the floor, hands also by the arms' own scale,
    /// offsets not applied. Also returns the heading the hands were scaled with.
    fn mapped(&self, to_model: Mat4, heading: Option<f32>) -> Vec<Option<(Vec3, Quat)>> {
        let (_, to_model_rot, _) = to_model.to_scale_rotation_translation();
        let raw: Vec<Option<(Vec3, Quat)>> = self
            .samples
            .iter()
            .map(|s| {
                s.map(|f| {
                    (
                        to_model.transform_point3(f.position),
                        (to_model_rot * f.rotation).normalize(),
                    )
                })
            })
            .collect();
        let head = self
            .slots
            .iter()
            .zip(&raw)
            .find_map(|(s, r)| matches!(s, Slot::Head).then_some(*r).flatten());
        let Some((head, _)) = head else {
            return raw;
        };
        let anchor = Vec3::new(head.x, 0.0, head.z);
        let s = self.scale;
        let head_scaled = anchor + s * (head - anchor);
        // The shoulders' middle, by the avatar's proportions, for the arms' own scale.
        let k = self.arm_scale / s;
        let shoulders = {
            let b = &self.body;
            let mid = b
                .arms
                .iter()
                .flatten()
                .map(|a| b.neutral[a[0]])
                .sum::<Vec3>()
                / 2.0;
            head_scaled + yaw(heading.unwrap_or(0.0)) * (mid - b.neutral[b.skull])
        };
        raw.into_iter()
            .zip(&self.slots)
            .map(|(r, slot)| {
                r.map(|(p, q)| {
                    let p = anchor + s * (p - anchor);
                    let p = if matches!(slot, Slot::Hand(_)) {
                        shoulders + k * (p - shoulders)
                    } else {
                        p
                    };
                    (p, q)
                })
            })
            .collect()
    }

    /// The calibrated targets: mapped, then each tracker's offset applied.
    fn targets(&self, to_model: Mat4, heading: Option<f32>) -> Vec<Option<(Vec3, Quat)>> {
        self.mapped(to_model, heading)
            .into_iter()
            .zip(&self.offsets)
            .map(|(t, &(op, oq))| t.map(|(p, q)| (p + q * op, (q * oq).normalize())))
            .collect()
    }

    fn index(&self, want: impl Fn(&Slot) -> bool) -> Option<usize> {
        self.slots.iter().position(want)
    }

    /// Calibrates from the latest samples, the user standing in `pose` on the floor of an
    /// avatar placed at `placement` (its scene-space matrix): the scale, the arms' scale (a
    /// T- or A-pose) and every tracker's offset to its joint. Resets the feet and the heading.
    ///
    /// # Errors
    /// A tracker without a sample, a head too low, hands too close for a T- or A-pose.
    pub fn calibrate(
        &mut self,
        pose: CalibrationPose,
        placement: Mat4,
    ) -> Result<Calibration, TrackerError> {
        // Measured uncalibrated; a refused calibration keeps the last one.
        let kept = (self.scale, self.arm_scale);
        let measured = self.measure(pose, placement);
        if measured.is_err() {
            (self.scale, self.arm_scale) = kept;
        }
        measured
    }

    fn measure(
        &mut self,
        pose: CalibrationPose,
        placement: Mat4,
    ) -> Result<Calibration, TrackerError> {
        if let Some(i) = self.samples.iter().position(Option::is_none) {
            return Err(TrackerError::NoSample(self.names[i].clone()));
        }
        let to_model = placement.inverse();
        self.scale = 1.0;
        self.arm_scale = 1.0;
        let raw = self.mapped(to_model, None);
        let at = |want: &dyn Fn(&Slot) -> bool| {
            self.index(want)
                .and_then(|i| raw[i])
                .ok_or(TrackerError::NoSample("head".into()))
        };
        let (head, head_rot) = at(&|s| matches!(s, Slot::Head))?;
        if head.y < 0.1 {
            return Err(TrackerError::TooLow(head.y));
        }
        let b = &self.body;
        let scale = (b.neutral[b.skull].y / head.y).clamp(SCALE_RANGE.0, SCALE_RANGE.1);
        // The calibration pose of the avatar, model space.
        let skeleton_rest = self.body_pose(pose);
        let arm_scale = match pose {
            CalibrationPose::Neutral => scale,
            CalibrationPose::TPose | CalibrationPose::APose => {
                let (l, _) = at(&|s| matches!(s, Slot::Hand(0)))?;
                let (r, _) = at(&|s| matches!(s, Slot::Hand(1)))?;
                let span = l.distance(r);
                let [la, ra] = b.arms.map(|a| a.map(|a| a[2]));
                let avatar_span = match (la, ra) {
                    (Some(l), Some(r)) => skeleton_rest[l]
                        .w_axis
                        .truncate()
                        .distance(skeleton_rest[r].w_axis.truncate()),
                    _ => 0.0,
                };
                if span < 0.2 * head.y {
                    return Err(TrackerError::NotTPose(span));
                }
                (avatar_span / span).clamp(SCALE_RANGE.0, SCALE_RANGE.1)
            }
        };
        let heading = yaw_of(head_rot);
        self.scale = scale;
        self.arm_scale = arm_scale;
        let mapped = self.mapped(to_model, Some(heading));
        let turn = yaw(heading);
        let skull = skeleton_rest[b.skull].w_axis.truncate();
        let head_scaled = Vec3::new(head.x, scale * head.y, head.z);
        let joint = |j: usize| -> (Vec3, Quat) {
            let (_, r, p) = skeleton_rest[j].to_scale_rotation_translation();
            (head_scaled + turn * (p - skull), (turn * r).normalize())
        };
        let mut offsets = Vec::with_capacity(self.slots.len());
        for (slot, m) in self.slots.iter().zip(&mapped) {
            let Some((p, q)) = *m else {
                offsets.push((Vec3::ZERO, Quat::IDENTITY));
                continue;
            };
            let j = match slot {
                Slot::Head => b.skull,
                Slot::Hand(side) => b.arms[*side].map_or(b.skull, |a| a[2]),
                Slot::Hips => b.root,
                Slot::Foot(side) => b.legs[*side].map_or(b.root, |l| l[2]),
                Slot::Joint(j, _) => *j,
            };
            let (jp, jq) = joint(j);
            let inv = q.inverse();
            offsets.push((inv * (jp - p), (inv * jq).normalize()));
        }
        self.offsets = offsets;
        self.heading = Some(heading);
        self.feet = [None; 2];
        Ok(Calibration {
            user_height: head.y,
            scale,
            arm_scale,
            trackers: self.names.clone(),
        })
    }

    /// The avatar's model-space matrices in a calibration pose: neutral, the upper arms
    /// turned out to the sides (palms down) for a T-pose, half as far for an A-pose.
    fn body_pose(&self, pose: CalibrationPose) -> Vec<Mat4> {
        let b = &self.body;
        let mut locals = b.neutral_locals.clone();
        let raised = match pose {
            CalibrationPose::Neutral => 0.0,
            CalibrationPose::TPose => PI / 2.0,
            CalibrationPose::APose => PI / 4.0,
        };
        if raised > 0.0 {
            for (side, angle) in [(0, raised), (1, -raised)] {
                if let Some([shoulder, _, _]) = b.arms[side] {
                    // Parents are at neutral (identity rotations): local = model rotation.
                    locals[shoulder].rotation = Quat::from_rotation_z(angle);
                }
            }
        }
        let mut world = vec![Mat4::IDENTITY; b.skeleton.len()];
        forward_kinematics(&b.skeleton, &locals, &mut world);
        world
    }

    /// Where each planted foot is this tick (model space, with its rotation), the hips at
    /// `hips` and the body turned to `heading`, at scene clock `clock`: see the module docs.
    fn planted(&mut self, hips: Vec3, heading: f32, clock: f64) -> [Option<(Vec3, Quat)>; 2] {
        let restart = clock < self.last_clock;
        self.last_clock = clock;
        let leg = self.body.leg_length;
        let homes = [0, 1].map(|side| self.body.foot_home(side, hips, yaw(heading)));
        for (foot, home) in self.feet.iter_mut().zip(homes) {
            let Some(home) = home else {
                *foot = None;
                continue;
            };
            // First solve, the clock gone back (a new scene clock) or the body moved far at
            // once (a placement, a teleport): stand there.
            let lost = foot.is_none_or(|f| f.plant.distance(home) > 3.0 * leg);
            if restart || lost {
                *foot = Some(Foot {
                    plant: home,
                    yaw: heading,
                    step: None,
                });
            }
        }
        if self.feet.iter().flatten().all(|f| f.step.is_none()) {
            let away = |f: &Foot, home: Vec3| {
                let d = Vec3::new(f.plant.x - home.x, 0.0, f.plant.z - home.z).length() / leg;
                let turn = wrap(f.yaw - heading).abs();
                (d > STEP_TRIGGER || turn > STEP_TURN)
                    .then_some(d / STEP_TRIGGER + turn / STEP_TURN)
            };
            let worst = (0..2)
                .filter_map(|side| {
                    let f = self.feet[side].as_ref()?;
                    Some((side, away(f, homes[side]?)?))
                })
                .max_by(|a, b| a.1.total_cmp(&b.1));
            if let Some((side, _)) = worst
                && let Some(f) = self.feet[side].as_mut()
            {
                f.step = Some((f.plant, f.yaw, clock));
            }
        }
        let mut out = [None; 2];
        for side in 0..2 {
            let (Some(f), Some(home)) = (self.feet[side].as_mut(), homes[side]) else {
                continue;
            };
            let (position, angle) = match f.step {
                Some((from, from_yaw, start)) => {
                    let t = (((clock - start) / STEP_SECONDS) as f32).clamp(0.0, 1.0);
                    let eased = t * t * (3.0 - 2.0 * t);
                    let lift = Vec3::Y * ((PI * t).sin() * STEP_HEIGHT * leg);
                    let angle = from_yaw + wrap(heading - from_yaw) * eased;
                    if t >= 1.0 {
                        f.plant = home;
                        f.yaw = heading;
                        f.step = None;
                    }
                    (from.lerp(home, eased) + lift, angle)
                }
                None => (f.plant, f.yaw),
            };
            out[side] = Some((position, yaw(angle)));
        }
        out
    }

    /// Solves the body from the trackers' latest transforms onto `locals` (the pose so far:
    /// clip and layers) of an avatar of `rig` placed at `placement` (scene-space matrix), at
    /// scene clock `clock`; `world` is scratch (one matrix per joint). Does nothing until the
    /// head and both hands have a sample.
    pub fn solve(
        &mut self,
        rig: &Rig,
        placement: Mat4,
        clock: f64,
        locals: &mut [Transform],
        world: &mut [Mat4],
    ) {
        let skeleton = rig.skeleton();
        let n = self.body.skeleton.len();
        if skeleton.len() != n || locals.len() != n || world.len() != n {
            return;
        }
        let required = [
            self.index(|s| matches!(s, Slot::Head)),
            self.index(|s| matches!(s, Slot::Hand(0))),
            self.index(|s| matches!(s, Slot::Hand(1))),
        ];
        let [Some(head), Some(l_hand), Some(r_hand)] = required else {
            return;
        };
        if [head, l_hand, r_hand]
            .iter()
            .any(|&i| self.samples[i].is_none())
        {
            return;
        }
        let targets = self.targets(placement.inverse(), self.heading);
        let Some((head_p, head_q)) = targets[head] else {
            return;
        };
        let hips_tracked = self
            .index(|s| matches!(s, Slot::Hips))
            .and_then(|i| targets[i]);
        let want = yaw_of(hips_tracked.map_or(head_q, |(_, q)| q));
        let heading = match (self.heading, hips_tracked) {
            (Some(h), None) => {
                let d = wrap(want - h);
                if d.abs() > HEADING_DEAD_ZONE {
                    wrap(h + d - HEADING_DEAD_ZONE.copysign(d))
                } else {
                    h
                }
            }
            _ => want,
        };
        self.heading = Some(heading);
        let turn = yaw(heading);
        let (hips_p, hips_q) = hips_tracked.unwrap_or_else(|| {
            let b = &self.body;
            let mut p = head_p - turn * b.head_over_hips();
            p.y = p.y.min(b.neutral[b.root].y);
            (p, turn)
        });
        self.walk(hips_p, clock);
        let feet_tracked = [
            self.index(|s| matches!(s, Slot::Foot(0)))
                .and_then(|i| targets[i]),
            self.index(|s| matches!(s, Slot::Foot(1)))
                .and_then(|i| targets[i]),
        ];
        let planted = if self.legs == Legs::Planted {
            self.planted(hips_p, heading, clock)
        } else {
            [None; 2]
        };
        let feet = [0, 1].map(|side| feet_tracked[side].or(planted[side]));

        let b = &self.body;
        for &j in &b.reset {
            locals[j].rotation = Quat::IDENTITY;
        }
        for (side, foot) in feet.iter().enumerate() {
            if let (Some(_), Some(leg)) = (foot, b.legs[side]) {
                for j in leg {
                    locals[j].rotation = Quat::IDENTITY;
                }
            }
        }

        // The hips: turned, then the whole skeleton moved so they are where they belong.
        ik::update_world(skeleton, locals, world, 0);
        ik::set_model_rotation(skeleton, locals, world, b.root, hips_q);
        let delta = hips_p - ik::position(world, b.root);
        locals[b.skeleton_root].translation += delta;
        ik::update_world(skeleton, locals, world, 0);

        if b.spine.len() >= 2 {
            // A spine asked to shorten starts from a slight forward curve, so it bends rather
            // than staying on its line (FABRIK keeps collinear joints collinear); one at its
            // length stays straight.
            let base = ik::position(world, b.spine[0]);
            if self.spine_seed.is_empty() && head_p.distance(base) < 0.999 * b.spine_length {
                for &j in &b.spine[..b.spine.len() - 1] {
                    locals[j].rotation = Quat::from_rotation_x(SPINE_CURVE);
                }
                ik::update_world(skeleton, locals, world, 0);
            }
            let goal = ChainGoal {
                chain: b.spine.clone(),
                target: head_p,
                rotation: Some(head_q),
                weight: 1.0,
            };
            ik::chain_seeded(skeleton, locals, world, &goal, &mut self.spine_seed);
        } else {
            ik::set_model_rotation(skeleton, locals, world, b.skull, head_q);
        }

        for (side, hand) in [l_hand, r_hand].into_iter().enumerate() {
            let (Some(arm), Some((p, q))) = (b.arms[side], targets[hand]) else {
                continue;
            };
            let shoulder = ik::position(world, arm[0]);
            let length = b.neutral[arm[0]].distance(b.neutral[arm[1]])
                + b.neutral[arm[1]].distance(b.neutral[arm[2]]);
            let out = if side == 0 { 1.0 } else { -1.0 };
            let rise = ((p.y - shoulder.y) / length.max(1e-3)).clamp(0.0, 1.0);
            // The natural swivel, eased toward from where the elbow was last tick (in the
            // body's frame), so an elbow does not jump from one side to the other.
            let natural = Vec3::new(out * (0.4 + rise), rise - 1.0, -0.4).normalize();
            let toward = match self.elbows[side] {
                Some(last) => turn * last.lerp(natural, ELBOW_EASE).normalize_or(natural),
                None => turn * natural,
            };
            if let Some(clavicle) = b.clavicles[side] {
                shrug(skeleton, locals, world, clavicle, arm[0], p, length);
            }
            let shoulder = ik::position(world, arm[0]);
            let goal = LimbGoal {
                target: p,
                rotation: Some(q),
                pole: Some(shoulder + toward * length),
                weight: 1.0,
            };
            ik::two_bone(skeleton, locals, world, arm, &goal);
            let bend = ik::position(world, arm[1]) - (shoulder + p) / 2.0;
            self.elbows[side] = ik::direction(turn.inverse() * bend).or(self.elbows[side]);
        }

        for (side, foot) in feet.into_iter().enumerate() {
            let (Some(leg), Some((p, q))) = (b.legs[side], foot) else {
                continue;
            };
            // Knees bend toward the body's front: a foot tracker's own yaw carries the twist
            // of whatever the ankle's frame is (on CesiumMan's walk it bent 62 % of the knees
            // backwards), the body's heading does not.
            let hip = ik::position(world, leg[0]);
            let knee_forward = turn * Vec3::Z * b.leg_length;
            let goal = LimbGoal {
                target: p,
                rotation: Some(q),
                pole: Some((hip + p) / 2.0 + knee_forward),
                weight: 1.0,
            };
            ik::two_bone(skeleton, locals, world, leg, &goal);
        }

        for (slot, t) in self.slots.iter().zip(&targets) {
            let (Slot::Joint(_, solver), Some((p, q))) = (slot, *t) else {
                continue;
            };
            match solver {
                Solver::Limb(limb) => {
                    let goal = LimbGoal {
                        target: p,
                        rotation: Some(q),
                        pole: None,
                        weight: 1.0,
                    };
                    ik::two_bone(skeleton, locals, world, *limb, &goal);
                }
                Solver::Chain(chain) => {
                    let goal = ChainGoal {
                        chain: chain.clone(),
                        target: p,
                        rotation: Some(q),
                        weight: 1.0,
                    };
                    ik::chain(skeleton, locals, world, &goal);
                }
            }
        }
    }
}

#[cfg(test)]
mod tests;
