//! The tracker solve against ground truth (issue 29, goal 5), shared by
//! `sim/benches/trackers.rs` (release: the figures and the solve's cost) and
//! `sim/tests/tracker_quality.rs` (the same figures in a debug build, with asserted bounds).
//!
//! **Ground truth**: every humanoid BVH clip under `../shared/testdata/bvh` (today only CMU
//! 01_01, 2,752 frames at 120 Hz; the other two BVH files there are not humanoids), imported and
//! normalised as an upload is (`import::load_path`, then `Rig::from_asset` with the default
//! pipeline options). Each frame at the clip's own rate, after a leading calibration pose
//! ([`first_frame`]), is sampled and run through forward kinematics, giving the world positions
//! of every H-Anim-mapped joint and the trackers' transforms: a tracker *is* its joint
//! (`posecast_proto::trackers::STANDARD`: `skullbase`, `l_wrist`, `r_wrist`, `humanoid_root`,
//! `l_ankle`, `r_ankle`), its rotation the joint's world rotation — which is its rotation
//! relative to the neutral pose, whose local rotations are all identity (the rest pose is not
//! the neutral pose: CMU 01_01's rest holds the upper arms 67–71° from it).
//!
//! **Setups**: the solver with 3 trackers (head, hands) and 6 (and hips, feet), each with the
//! One Euro input filter off (the trackers are exact) and on (the default), and the naive
//! baseline: each tracker's rotation copied onto its joint as a model-space rotation, the root
//! placed at the hips tracker when there is one, every other joint at rest.
//!
//! **Figures** (per clip and setup, over the frames evaluated):
//! - joint-position error over every H-Anim-mapped joint and frame, per body height (`H`: the
//!   `skullbase` joint's height above the lower ankle in the neutral pose, standing straight;
//!   1.379 m for CMU 01_01): mean and 95th percentile;
//! - end effectors (`skullbase`, `l_wrist`, `r_wrist`): position error (mm) and rotation error
//!   (degrees), mean and worst;
//! - foot skate: the solved ankle's horizontal speed (cm/s) over the frames where the ground
//!   truth's foot is planted — its ankle moving horizontally slower than [`PLANTED_SPEED`] and
//!   within [`PLANTED_HEIGHT`] of the lowest it is while that slow in the clip — beside the
//!   ground truth's own;
//! - elbow and knee flips per minute: a limb's bend-plane normal (`(mid − root) × (end − mid)`)
//!   turning more than 90° within [`FLIP_WINDOW`] (50 ms: a flip over a few frames of 120 Hz
//!   capture counts too), where the limb is bent at least [`BENT`] (a straight limb has no
//!   bend plane), one event counted once;
//! - elbow and knee swivel error: the angle between the solved and the captured bend-plane
//!   normal, mean, and the share of frames where it is over 90° (the limb bent the other way
//!   round about the line from its root to its end);
//! - jitter: the mean length of the second difference of every mapped joint's position (mm);
//! - the cost of `Trackers::solve` alone, µs per call (one avatar, one tick).

#![allow(dead_code, clippy::unwrap_used, clippy::expect_used)]

use glam::{Mat4, Quat, Vec3};
use posecast_proto::Transform;
use posecast_proto::fk::forward_kinematics;
use posecast_proto::trackers::{Legs, STANDARD};
use posecast_rigs::clip::{Clip, RotationChannel, VectorChannel};
use posecast_rigs::rig::{PipelineOptions, Rig};
use posecast_sim::avatar::trackers::{TrackerSample, Trackers};
use std::fmt::Write as _;
use std::path::Path;
use std::sync::Arc;
use std::time::Instant;

/// A ground-truth foot is planted below this horizontal ankle speed (m/s) …
pub const PLANTED_SPEED: f32 = 0.15;
/// … and within this height (m) of its lowest while that slow in the clip.
pub const PLANTED_HEIGHT: f32 = 0.04;
/// A limb bent less than this (radians, 5°) has no bend plane to flip.
pub const BENT: f32 = 5.0 * std::f32::consts::PI / 180.0;
/// A flip is a bend plane turning over within this time (seconds: 6 frames at 120 Hz, one
/// at 20 Hz), so a flip spread over a few frames of fast capture counts too.
pub const FLIP_WINDOW: f64 = 0.05;

/// One clip on its rig.
#[derive(Debug)]
pub struct Subject {
    /// `cmu/01_01` (the file under `testdata/bvh`, without `.bvh`) or `builtin/walk`.
    pub label: String,
    /// Real motion capture (the shared BVH files), not an authored clip.
    pub mocap: bool,
    /// The normalised rig.
    pub rig: Arc<Rig>,
    /// Its clip.
    pub clip: Arc<Clip>,
    /// The clip's own frame rate (its keys per second).
    pub fps: f64,
    /// Frames at that rate, both ends included.
    pub frames: usize,
}

impl Subject {
    fn new(label: String, mocap: bool, rig: Arc<Rig>, clip: Arc<Clip>) -> Self {
        let fps = frame_rate(&clip);
        let frames = (f64::from(clip.duration()) * fps).round() as usize + 1;
        Self {
            label,
            mocap,
            rig,
            clip,
            fps,
            frames,
        }
    }
}

/// Keys per second of the channel with the most keys (BVH and baked clips key every joint
/// every frame).
fn frame_rate(clip: &Clip) -> f64 {
    let mut best: Option<&[f32]> = None;
    for ch in clip.channels() {
        let times = [
            match &ch.rotation {
                Some(RotationChannel::Keys(t)) => Some(t.times()),
                _ => None,
            },
            match &ch.translation {
                Some(VectorChannel::Keys(t)) => Some(t.times()),
                _ => None,
            },
        ];
        for t in times.into_iter().flatten() {
            if best.is_none_or(|b| t.len() > b.len()) {
                best = Some(t);
            }
        }
    }
    match best {
        Some(t) if t.len() > 1 => {
            let span = f64::from(t[t.len() - 1] - t[0]);
            ((t.len() - 1) as f64 / span * 1000.0).round() / 1000.0
        }
        _ => 30.0,
    }
}

/// Every humanoid BVH clip under `../shared/testdata/bvh`, in path order; `None` when the
/// folder is absent (a skip, and a failure under `CI=true`). Files that are not humanoids
/// (the synthetic `fairmotion/sinusoidal.bvh`, `bvh_anim/test_simple.bvh`) are left out.
pub fn mocap_subjects() -> Option<Vec<Subject>> {
    let dir = posecast_proto::testing::require_testdata("bvh")?;
    let mut files = Vec::new();
    collect_bvh(&dir, &mut files);
    files.sort();
    let mut out = Vec::new();
    for path in files {
        let rel = path
            .strip_prefix(&dir)
            .unwrap()
            .with_extension("")
            .to_string_lossy()
            .replace('\\', "/");
        let assets = posecast_rigs::import::load_path(&path)
            .unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        for asset in assets {
            let rig = Arc::new(
                Rig::from_asset(asset, &PipelineOptions::default())
                    .unwrap_or_else(|e| panic!("{rel}: {e}")),
            );
            if !rig.humanoid || !tracker_joints_mapped(&rig) {
                continue;
            }
            for clip in rig.clips.clone() {
                let label = if rig.clips.len() > 1 {
                    format!("{rel}/{}", clip.name())
                } else {
                    rel.clone()
                };
                out.push(Subject::new(label, true, rig.clone(), clip));
            }
        }
    }
    Some(out)
}

/// Every humanoid glTF under `../shared/testdata/gltf` with animations whose rig maps the
/// tracker joints (CesiumMan's walk; the rigged figure's), imported and normalised like an
/// upload: authored, not motion capture, but other skeletons. Empty without the folder.
pub fn gltf_subjects() -> Vec<Subject> {
    let Some(dir) = posecast_proto::testing::require_testdata("gltf") else {
        return Vec::new();
    };
    let mut files = Vec::new();
    collect_ext(&dir, "glb", &mut files);
    files.sort();
    let mut out = Vec::new();
    for path in files {
        let Ok(assets) = posecast_rigs::import::load_path(&path) else {
            continue;
        };
        let stem = path
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_default();
        for asset in assets {
            let Ok(rig) = Rig::from_asset(asset, &PipelineOptions::default()) else {
                continue;
            };
            let rig = Arc::new(rig);
            if !rig.humanoid || !tracker_joints_mapped(&rig) {
                continue;
            }
            for clip in rig.clips.clone() {
                let label = format!("gltf/{stem}/{}", clip.name());
                out.push(Subject::new(label, false, rig.clone(), clip));
            }
        }
    }
    out
}

/// The built-in avatar's authored clips (`idle`, `walk`, `wave`, 30 Hz): not motion capture,
/// but another skeleton (23 joints) and a walk whose feet plant.
pub fn builtin_subjects() -> Vec<Subject> {
    let rig = Arc::new(posecast_rigs::builtin::rig().unwrap());
    rig.clips
        .clone()
        .into_iter()
        .map(|clip| Subject::new(format!("builtin/{}", clip.name()), false, rig.clone(), clip))
        .collect()
}

fn collect_bvh(dir: &Path, out: &mut Vec<std::path::PathBuf>) {
    collect_ext(dir, "bvh", out);
}

fn collect_ext(dir: &Path, ext: &str, out: &mut Vec<std::path::PathBuf>) {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    for e in entries.flatten() {
        let p = e.path();
        if p.is_dir() {
            collect_ext(&p, ext, out);
        } else if p.extension().is_some_and(|x| x.eq_ignore_ascii_case(ext)) {
            out.push(p);
        }
    }
}

/// The joint a tracker stands for on `rig`, as the solver takes it (a rig without a head
/// joint uses its topmost neck joint for the head).
fn hanim_joint(rig: &Rig, name: &str) -> Option<usize> {
    posecast_sim::avatar::trackers::tracker_joint(rig, name)
}

fn tracker_joints_mapped(rig: &Rig) -> bool {
    STANDARD
        .iter()
        .map(|(_, j)| *j)
        .chain(LIMBS.concat())
        .all(|j| hanim_joint(rig, j).is_some())
}

/// The limbs whose flips are counted: `[root, mid, end]`.
const LIMBS: [[&str; 3]; 4] = [
    ["l_shoulder", "l_elbow", "l_wrist"],
    ["r_shoulder", "r_elbow", "r_wrist"],
    ["l_hip", "l_knee", "l_ankle"],
    ["r_hip", "r_knee", "r_ankle"],
];

/// Ground truth of one subject over the frames evaluated.
#[derive(Debug)]
pub struct Truth {
    /// Every `stride`-th frame of the clip is evaluated.
    pub stride: usize,
    /// Seconds between evaluated frames.
    pub dt: f64,
    /// Clock of each evaluated frame (seconds from the clip's start).
    pub times: Vec<f64>,
    /// The H-Anim-mapped joints (skeleton indices).
    pub mapped: Vec<usize>,
    /// Per evaluated frame, the world position of each mapped joint.
    pub positions: Vec<Vec<Vec3>>,
    /// Per evaluated frame, the six standard trackers (in [`STANDARD`] order).
    pub trackers: Vec<[(Vec3, Quat); 6]>,
    /// Skeleton index of each standard tracker's joint.
    pub tracker_joints: [usize; 6],
    /// Index into `mapped` of each standard tracker's joint.
    pub tracker_slots: [usize; 6],
    /// Index into `mapped` of each limb's joints ([`LIMBS`]).
    pub limb_slots: [[usize; 3]; 4],
    /// The neutral pose's `skullbase` height above its lower ankle (m).
    pub height: f32,
    /// Per evaluated frame, whether the left / right foot is planted.
    pub planted: [Vec<bool>; 2],
}

/// Samples `subject` at every `stride`-th frame (at most `limit` frames).
pub fn truth(subject: &Subject, stride: usize, limit: Option<usize>) -> Truth {
    let rig = &subject.rig;
    let sk = rig.skeleton();
    let rest = sk.rest();
    let mapped: Vec<usize> = (0..sk.len()).filter(|&j| rig.hanim[j].is_some()).collect();
    let slot = |name: &str| {
        let j = hanim_joint(rig, name).unwrap_or_else(|| panic!("{name} not mapped"));
        mapped.iter().position(|&m| m == j).unwrap()
    };
    let tracker_joints = STANDARD.map(|(_, j)| hanim_joint(rig, j).unwrap());
    let tracker_slots = STANDARD.map(|(_, j)| slot(j));
    let limb_slots = LIMBS.map(|l| l.map(slot));

    // Body height in the neutral pose (identity rotations: standing straight, H-Anim's pose),
    // not the rest pose, which may be a T-pose or have bent legs (CMU 01_01's thighs: 21°).
    let mut world = vec![Mat4::IDENTITY; sk.len()];
    let neutral: Vec<Transform> = rest
        .iter()
        .map(|t| Transform {
            rotation: Quat::IDENTITY,
            ..*t
        })
        .collect();
    forward_kinematics(sk, &neutral, &mut world);
    let y = |j: usize| world[j].w_axis.y;
    let height = y(tracker_joints[0]) - y(tracker_joints[4]).min(y(tracker_joints[5]));

    let mut locals = rest.to_vec();
    let mut sample = |f: usize| {
        let t = f as f64 / subject.fps;
        subject
            .clip
            .sample(subject.clip.start() + t as f32, rest, &mut locals);
        forward_kinematics(sk, &locals, &mut world);
        let p: Vec<Vec3> = mapped.iter().map(|&j| world[j].w_axis.truncate()).collect();
        let trackers = tracker_joints.map(|j| {
            let (_, r, p) = world[j].to_scale_rotation_translation();
            (p, r.normalize())
        });
        (t, p, trackers)
    };
    let first = first_frame(subject, &mut sample);
    let (mut times, mut positions, mut trackers) = (Vec::new(), Vec::new(), Vec::new());
    let frames = (first..subject.frames)
        .step_by(stride)
        .take(limit.unwrap_or(usize::MAX));
    for f in frames {
        let (t, p, k) = sample(f);
        times.push(t);
        positions.push(p);
        trackers.push(k);
    }
    let dt = stride as f64 / subject.fps;
    let planted = [4, 5].map(|k| {
        let ankle: Vec<Vec3> = positions
            .iter()
            .map(|p: &Vec<Vec3>| p[tracker_slots[k]])
            .collect();
        let slow: Vec<bool> = (0..ankle.len())
            .map(|i| i > 0 && horizontal_speed(ankle[i - 1], ankle[i], dt) < PLANTED_SPEED)
            .collect();
        // The lowest height while slow: a landing can put the ankle lower for a frame or two
        // (CMU 01_01's right ankle: 6.5 cm once, 9 cm or more whenever it is slow).
        let lowest = (0..ankle.len())
            .filter(|&i| slow[i])
            .map(|i| ankle[i].y)
            .fold(f32::INFINITY, f32::min);
        (0..ankle.len())
            .map(|i| slow[i] && ankle[i].y < lowest + PLANTED_HEIGHT)
            .collect()
    });
    Truth {
        stride,
        dt,
        times,
        mapped,
        positions,
        trackers,
        tracker_joints,
        tracker_slots,
        limb_slots,
        height,
        planted,
    }
}

/// No tracker moves faster than this between frames of real motion, m/s.
pub const JUMP_SPEED: f32 = 10.0;

/// The first frame of the motion: leading frames from which some tracker jumps to the next
/// faster than [`JUMP_SPEED`] are skipped — the CMU conversions' frame 0 is the capture's
/// calibration pose (01_01's wrists jump 0.55 and 0.64 m, one of them turning 179°, to frame 1).
fn first_frame(
    subject: &Subject,
    sample: &mut impl FnMut(usize) -> (f64, Vec<Vec3>, [(Vec3, Quat); 6]),
) -> usize {
    let mut first = 0;
    let mut here = sample(0).2;
    while first + 1 < subject.frames.min(10) {
        let next = sample(first + 1).2;
        let jump = here
            .iter()
            .zip(&next)
            .map(|(a, b)| a.0.distance(b.0))
            .fold(0.0f32, f32::max);
        if f64::from(jump) * subject.fps <= f64::from(JUMP_SPEED) {
            break;
        }
        first += 1;
        here = next;
    }
    first
}

fn horizontal_speed(a: Vec3, b: Vec3, dt: f64) -> f32 {
    let d = b - a;
    (d.x.hypot(d.z) as f64 / dt) as f32
}

/// How the body is made from the trackers.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Method {
    /// Tracker rotations copied onto their joints, the root at the hips tracker if any.
    Naive,
    /// `Trackers::solve`, with the One Euro input filter on or off.
    Solver {
        /// `Trackers::set_smoothing`.
        smoothing: bool,
    },
}

/// A tracker setup: 3 points (head, hands) or 6 (and hips, feet), and the method.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Setup {
    /// 3 or 6.
    pub points: usize,
    /// How the body is made.
    pub method: Method,
}

impl Setup {
    /// `3-point solver`, `6-point naive`, `3-point filtered` …
    #[must_use]
    pub fn label(&self) -> String {
        let m = match self.method {
            Method::Naive => "naive",
            Method::Solver { smoothing: false } => "solver",
            Method::Solver { smoothing: true } => "solver+filter",
        };
        format!("{}-pt {m}", self.points)
    }
}

/// The setups every clip is evaluated with: naive, solver (filter off), solver (filter on),
/// for 3 and then 6 points.
#[must_use]
pub fn setups() -> Vec<Setup> {
    let mut out = Vec::new();
    for points in [3, 6] {
        for method in [
            Method::Naive,
            Method::Solver { smoothing: false },
            Method::Solver { smoothing: true },
        ] {
            out.push(Setup { points, method });
        }
    }
    out
}

/// The tracker names of a setup (`STANDARD`'s first `points`).
#[must_use]
pub fn tracker_names(points: usize) -> Vec<String> {
    STANDARD[..points]
        .iter()
        .map(|(n, _)| (*n).to_string())
        .collect()
}

/// What one setup achieved on one subject.
#[derive(Debug, Clone, Default)]
pub struct Metrics {
    /// Frames evaluated.
    pub frames: usize,
    /// Seconds of motion they span.
    pub seconds: f64,
    /// Every joint error over body height (mapped joints × frames), for pooling.
    pub errors: Vec<f32>,
    /// Mean and 95th percentile joint-position error, fraction of body height.
    pub err_mean: f32,
    /// See `err_mean`.
    pub err_p95: f32,
    /// Mean joint-position error, mm.
    pub err_mean_mm: f32,
    /// End effectors (head, wrists): mean and worst position error, mm.
    pub ee_pos_mean_mm: f32,
    /// See `ee_pos_mean_mm`.
    pub ee_pos_max_mm: f32,
    /// End effectors: mean and worst rotation error, degrees.
    pub ee_rot_mean_deg: f32,
    /// See `ee_rot_mean_deg`.
    pub ee_rot_max_deg: f32,
    /// Worst position error (mm) per end effector: head, left, right wrist.
    pub ee_pos_max_each_mm: [f32; 3],
    /// Mean solved / ground-truth ankle horizontal speed while planted, cm/s.
    pub skate_cm_s: f32,
    /// See `skate_cm_s`.
    pub skate_truth_cm_s: f32,
    /// Worst solved ankle horizontal speed while planted, cm/s.
    pub skate_max_cm_s: f32,
    /// Planted foot-frames.
    pub planted: usize,
    /// Elbow / knee flips per minute, solved and ground truth.
    pub elbow_flips_min: f32,
    /// See `elbow_flips_min`.
    pub knee_flips_min: f32,
    /// See `elbow_flips_min`.
    pub elbow_flips_truth_min: f32,
    /// See `elbow_flips_min`.
    pub knee_flips_truth_min: f32,
    /// Elbow / knee swivel error: mean degrees, and the share of frames over 90°.
    pub elbow_swivel_deg: f32,
    /// See `elbow_swivel_deg`.
    pub elbow_wrong: f32,
    /// See `elbow_swivel_deg`.
    pub knee_swivel_deg: f32,
    /// See `elbow_swivel_deg`.
    pub knee_wrong: f32,
    /// Limb-frames the elbow / knee swivel was measured on (both bent).
    pub swivel_frames: [usize; 2],
    /// Mean second-difference length over mapped joints, mm: solved, ground truth.
    pub jitter_mm: f32,
    /// See `jitter_mm`.
    pub jitter_truth_mm: f32,
    /// Frames with a non-finite local transform or joint position.
    pub non_finite: usize,
    /// `solve` (or the naive copy) alone: mean and worst µs per call.
    pub solve_us: f64,
    /// See `solve_us`.
    pub solve_max_us: f64,
}

/// The naive baseline's pose for one frame: rest, each tracker's rotation copied onto its
/// joint as a model-space rotation, the root (`humanoid_root`) placed at the hips tracker when
/// there is one.
pub fn naive(
    rig: &Rig,
    truth: &Truth,
    frame: usize,
    points: usize,
    locals: &mut [Transform],
    world: &mut [Mat4],
) {
    let sk = rig.skeleton();
    let parents = sk.parents();
    let targets = &truth.trackers[frame];
    for j in 0..sk.len() {
        let parent = parents[j].map_or(Mat4::IDENTITY, |p| world[p]);
        if let Some(k) = truth.tracker_joints[..points].iter().position(|&t| t == j) {
            let (pos, rot) = targets[k];
            let (_, parent_rot, _) = parent.to_scale_rotation_translation();
            locals[j].rotation = (parent_rot.inverse() * rot).normalize();
            if STANDARD[k].1 == "humanoid_root" {
                locals[j].translation = parent.inverse().transform_point3(pos);
            }
        }
        world[j] = parent * locals[j].to_mat4();
    }
}

/// Rotation between two unit quaternions, degrees (precise near zero).
fn angle_deg(a: Quat, b: Quat) -> f32 {
    let d = a.inverse() * b;
    (2.0 * d.xyz().length().atan2(d.w.abs())).to_degrees()
}

/// Runs `setup` on `subject` frame by frame (store then solve at that frame's clock) and
/// measures it against `truth`.
pub fn evaluate(subject: &Subject, truth: &Truth, setup: Setup) -> Metrics {
    let rig = &subject.rig;
    let sk = rig.skeleton();
    let rest = sk.rest();
    let n = truth.times.len();
    let mut locals = rest.to_vec();
    let mut world = vec![Mat4::IDENTITY; sk.len()];
    let mut scratch = vec![Mat4::IDENTITY; sk.len()];
    let mut solver = match setup.method {
        Method::Naive => None,
        Method::Solver { smoothing } => {
            let mut s = Trackers::new(rig, &tracker_names(setup.points), Legs::Planted)
                .unwrap_or_else(|e| panic!("{}: {e:?}", subject.label));
            s.set_smoothing(smoothing);
            Some(s)
        }
    };
    let mut samples: Vec<(usize, TrackerSample)> = Vec::with_capacity(6);
    let mut solved: Vec<Vec<Vec3>> = Vec::with_capacity(n);
    let mut m = Metrics {
        frames: n,
        seconds: truth.dt * n.saturating_sub(1) as f64,
        ..Metrics::default()
    };
    let (mut ee_pos_sum, mut ee_rot_sum) = (0.0f64, 0.0f64);
    let mut solve_total = 0.0f64;
    for (i, &clock) in truth.times.iter().enumerate() {
        locals.copy_from_slice(rest);
        let elapsed = match solver.as_mut() {
            None => {
                let start = Instant::now();
                naive(rig, truth, i, setup.points, &mut locals, &mut scratch);
                start.elapsed()
            }
            Some(s) => {
                samples.clear();
                for (k, &(position, rotation)) in
                    truth.trackers[i][..setup.points].iter().enumerate()
                {
                    samples.push((k, TrackerSample { position, rotation }));
                }
                s.store(&samples, clock);
                let start = Instant::now();
                s.solve(rig, Mat4::IDENTITY, clock, &mut locals, &mut scratch);
                start.elapsed()
            }
        };
        let us = elapsed.as_secs_f64() * 1e6;
        solve_total += us;
        m.solve_max_us = m.solve_max_us.max(us);

        forward_kinematics(sk, &locals, &mut world);
        let finite = locals
            .iter()
            .all(|t| t.translation.is_finite() && t.rotation.is_finite())
            && truth.mapped.iter().all(|&j| world[j].is_finite());
        if !finite {
            m.non_finite += 1;
        }
        let p: Vec<Vec3> = truth
            .mapped
            .iter()
            .map(|&j| world[j].w_axis.truncate())
            .collect();
        for (a, b) in p.iter().zip(&truth.positions[i]) {
            m.errors.push(a.distance(*b) / truth.height);
        }
        for e in 0..3 {
            let mm = p[truth.tracker_slots[e]].distance(truth.positions[i][truth.tracker_slots[e]])
                * 1000.0;
            let (_, rot, _) = world[truth.tracker_joints[e]].to_scale_rotation_translation();
            let deg = angle_deg(rot.normalize(), truth.trackers[i][e].1);
            ee_pos_sum += f64::from(mm);
            ee_rot_sum += f64::from(deg);
            m.ee_pos_max_mm = m.ee_pos_max_mm.max(mm);
            m.ee_pos_max_each_mm[e] = m.ee_pos_max_each_mm[e].max(mm);
            m.ee_rot_max_deg = m.ee_rot_max_deg.max(deg);
        }
        solved.push(p);
    }
    m.solve_us = solve_total / n.max(1) as f64;
    m.ee_pos_mean_mm = (ee_pos_sum / (3 * n).max(1) as f64) as f32;
    m.ee_rot_mean_deg = (ee_rot_sum / (3 * n).max(1) as f64) as f32;
    m.err_mean = mean(&m.errors);
    m.err_p95 = percentile(&m.errors, 0.95);
    m.err_mean_mm = m.err_mean * truth.height * 1000.0;

    let (skate_mean, skate_max, planted) = skate(&solved, truth);
    let (skate_truth, _, _) = skate(&truth.positions, truth);
    m.skate_cm_s = skate_mean;
    m.skate_max_cm_s = skate_max;
    m.skate_truth_cm_s = skate_truth;
    m.planted = planted;

    let minutes = (m.seconds / 60.0).max(1e-9);
    let (elbows, knees) = flips(&solved, truth);
    let (elbows_t, knees_t) = flips(&truth.positions, truth);
    m.elbow_flips_min = (elbows as f64 / minutes) as f32;
    m.knee_flips_min = (knees as f64 / minutes) as f32;
    m.elbow_flips_truth_min = (elbows_t as f64 / minutes) as f32;
    m.knee_flips_truth_min = (knees_t as f64 / minutes) as f32;
    let [elbow, knee] = swivel(&solved, truth);
    (m.elbow_swivel_deg, m.elbow_wrong, m.swivel_frames[0]) = elbow;
    (m.knee_swivel_deg, m.knee_wrong, m.swivel_frames[1]) = knee;
    m.jitter_mm = jitter(&solved) * 1000.0;
    m.jitter_truth_mm = jitter(&truth.positions) * 1000.0;
    m
}

fn mean(v: &[f32]) -> f32 {
    (v.iter().map(|&x| f64::from(x)).sum::<f64>() / v.len().max(1) as f64) as f32
}

fn percentile(v: &[f32], q: f64) -> f32 {
    if v.is_empty() {
        return 0.0;
    }
    let mut s = v.to_vec();
    s.sort_by(f32::total_cmp);
    s[((s.len() - 1) as f64 * q).round() as usize]
}

/// Mean and worst ankle horizontal speed (cm/s) over the planted foot-frames, and their count.
fn skate(positions: &[Vec<Vec3>], truth: &Truth) -> (f32, f32, usize) {
    let (mut sum, mut worst, mut count) = (0.0f64, 0.0f32, 0usize);
    for (foot, slot) in [(0, truth.tracker_slots[4]), (1, truth.tracker_slots[5])] {
        for i in 1..positions.len() {
            if truth.planted[foot][i] {
                let v =
                    horizontal_speed(positions[i - 1][slot], positions[i][slot], truth.dt) * 100.0;
                sum += f64::from(v);
                worst = worst.max(v);
                count += 1;
            }
        }
    }
    ((sum / count.max(1) as f64) as f32, worst, count)
}

/// Each limb's bend-plane normal per frame (`None` where it is bent less than [`BENT`]).
fn bend_normals(positions: &[Vec<Vec3>], slots: [usize; 3]) -> Vec<Option<Vec3>> {
    let min_sin = BENT.sin();
    positions
        .iter()
        .map(|p| {
            let (u, v) = (p[slots[1]] - p[slots[0]], p[slots[2]] - p[slots[1]]);
            let cross = u.cross(v);
            (cross.length() >= min_sin * u.length() * v.length()).then(|| cross.normalize())
        })
        .collect()
}

/// Flips: a limb's bend-plane normal turning more than 90° within [`FLIP_WINDOW`] (both ends
/// bent at least [`BENT`]), one event counted once: (elbows, knees).
fn flips(positions: &[Vec<Vec3>], truth: &Truth) -> (usize, usize) {
    let window = ((FLIP_WINDOW / truth.dt).round() as usize).max(1);
    let mut counts = [0usize; 4];
    for (l, slots) in truth.limb_slots.iter().enumerate() {
        let normals = bend_normals(positions, *slots);
        let mut since = 0;
        for i in 1..normals.len() {
            let Some(n) = normals[i] else { continue };
            let from = since.max(i.saturating_sub(window));
            if normals[from..i].iter().flatten().any(|m| m.dot(n) < 0.0) {
                counts[l] += 1;
                since = i;
            }
        }
    }
    (counts[0] + counts[1], counts[2] + counts[3])
}

/// Swivel error: the angle between the solved and the captured bend-plane normal (frames where
/// both are bent at least [`BENT`]), mean in degrees and the share of frames over 90° (bent
/// the other way round): (elbows, knees).
fn swivel(solved: &[Vec<Vec3>], truth: &Truth) -> [(f32, f32, usize); 2] {
    [0, 2].map(|first| {
        let (mut sum, mut wrong, mut count) = (0.0f64, 0usize, 0usize);
        for slots in &truth.limb_slots[first..first + 2] {
            let a = bend_normals(solved, *slots);
            let b = bend_normals(&truth.positions, *slots);
            for (x, y) in a.iter().zip(&b) {
                if let (Some(x), Some(y)) = (x, y) {
                    sum += f64::from(x.dot(*y).clamp(-1.0, 1.0).acos().to_degrees());
                    wrong += usize::from(x.dot(*y) < 0.0);
                    count += 1;
                }
            }
        }
        let n = count.max(1) as f64;
        ((sum / n) as f32, (wrong as f64 / n) as f32, count)
    })
}

/// Mean length of the second difference of every joint's position (m).
fn jitter(positions: &[Vec<Vec3>]) -> f32 {
    let (mut sum, mut count) = (0.0f64, 0usize);
    for w in positions.windows(3) {
        for ((a, b), c) in w[0].iter().zip(&w[1]).zip(&w[2]) {
            sum += f64::from((*c - 2.0 * *b + *a).length());
            count += 1;
        }
    }
    (sum / count.max(1) as f64) as f32
}

/// Pools several subjects' figures for one setup: joint errors pooled (mean, p95), the others
/// weighted by frames (rates by seconds), worst of the worsts.
#[must_use]
pub fn pool(rows: &[&Metrics]) -> Metrics {
    let mut out = Metrics::default();
    let frames: usize = rows.iter().map(|m| m.frames).sum();
    let seconds: f64 = rows.iter().map(|m| m.seconds).sum();
    let planted: usize = rows.iter().map(|m| m.planted).sum();
    let by_frames = |f: fn(&Metrics) -> f32| {
        (rows
            .iter()
            .map(|m| f64::from(f(m)) * m.frames as f64)
            .sum::<f64>()
            / frames.max(1) as f64) as f32
    };
    let by_seconds = |f: fn(&Metrics) -> f32| {
        (rows
            .iter()
            .map(|m| f64::from(f(m)) * m.seconds)
            .sum::<f64>()
            / seconds.max(1e-9)) as f32
    };
    let by_planted = |f: fn(&Metrics) -> f32| {
        (rows
            .iter()
            .map(|m| f64::from(f(m)) * m.planted as f64)
            .sum::<f64>()
            / planted.max(1) as f64) as f32
    };
    let worst = |f: fn(&Metrics) -> f32| rows.iter().map(|m| f(m)).fold(0.0f32, f32::max);
    out.frames = frames;
    out.seconds = seconds;
    out.planted = planted;
    out.errors = rows.iter().flat_map(|m| m.errors.iter().copied()).collect();
    out.err_mean = mean(&out.errors);
    out.err_p95 = percentile(&out.errors, 0.95);
    out.err_mean_mm = by_frames(|m| m.err_mean_mm);
    out.ee_pos_mean_mm = by_frames(|m| m.ee_pos_mean_mm);
    out.ee_pos_max_mm = worst(|m| m.ee_pos_max_mm);
    out.ee_rot_mean_deg = by_frames(|m| m.ee_rot_mean_deg);
    out.ee_rot_max_deg = worst(|m| m.ee_rot_max_deg);
    for e in 0..3 {
        out.ee_pos_max_each_mm[e] = rows
            .iter()
            .map(|m| m.ee_pos_max_each_mm[e])
            .fold(0.0, f32::max);
    }
    out.skate_cm_s = by_planted(|m| m.skate_cm_s);
    out.skate_truth_cm_s = by_planted(|m| m.skate_truth_cm_s);
    out.skate_max_cm_s = worst(|m| m.skate_max_cm_s);
    out.elbow_flips_min = by_seconds(|m| m.elbow_flips_min);
    out.knee_flips_min = by_seconds(|m| m.knee_flips_min);
    out.elbow_flips_truth_min = by_seconds(|m| m.elbow_flips_truth_min);
    out.knee_flips_truth_min = by_seconds(|m| m.knee_flips_truth_min);
    for (limb, (deg, wrong)) in [
        (|m: &Metrics| (m.elbow_swivel_deg, m.elbow_wrong)) as fn(&Metrics) -> (f32, f32),
        |m: &Metrics| (m.knee_swivel_deg, m.knee_wrong),
    ]
    .into_iter()
    .enumerate()
    .map(|(limb, f)| {
        let count: usize = rows.iter().map(|m| m.swivel_frames[limb]).sum();
        let w = |g: fn((f32, f32)) -> f32| {
            (rows
                .iter()
                .map(|m| f64::from(g(f(m))) * m.swivel_frames[limb] as f64)
                .sum::<f64>()
                / count.max(1) as f64) as f32
        };
        out.swivel_frames[limb] = count;
        (limb, (w(|x| x.0), w(|x| x.1)))
    }) {
        if limb == 0 {
            (out.elbow_swivel_deg, out.elbow_wrong) = (deg, wrong);
        } else {
            (out.knee_swivel_deg, out.knee_wrong) = (deg, wrong);
        }
    }
    out.jitter_mm = by_frames(|m| m.jitter_mm);
    out.jitter_truth_mm = by_frames(|m| m.jitter_truth_mm);
    out.non_finite = rows.iter().map(|m| m.non_finite).sum();
    out.solve_us = f64::from(by_frames(|m| m.solve_us as f32));
    out.solve_max_us = rows.iter().map(|m| m.solve_max_us).fold(0.0, f64::max);
    out
}

/// The table's columns: two header lines and a width each (after clip and setup).
const COLUMNS: [(&str, &str, usize); 14] = [
    ("frames", "", 6),
    ("err", "mean %H", 7),
    ("err", "p95 %H", 6),
    ("err", "mean mm", 7),
    ("end effector", "mm mean/max", 13),
    ("end effector", "° mean/max", 12),
    ("foot skate", "cm/s (truth)", 12),
    ("elbow flips", "/min (truth)", 12),
    ("knee flips", "/min (truth)", 12),
    ("elbow swivel", "° (>90°)", 12),
    ("knee swivel", "° (>90°)", 12),
    ("jitter", "mm (truth)", 13),
    ("solve µs", "mean/max", 11),
    ("NaN", "", 3),
];

fn line(clip: &str, setup: &str, cells: &[String]) -> String {
    let mut s = format!("{clip:<16} {setup:<18}");
    for (cell, (_, _, width)) in cells.iter().zip(COLUMNS) {
        let _ = write!(s, " {cell:>width$}");
    }
    s
}

/// The table's header (two lines). `H` is the body height.
#[must_use]
pub fn header() -> String {
    let first: Vec<String> = COLUMNS.iter().map(|c| c.0.to_string()).collect();
    let second: Vec<String> = COLUMNS.iter().map(|c| c.1.to_string()).collect();
    format!(
        "{}\n{}",
        line("clip", "setup", &first),
        line("", "", &second)
    )
}

fn swivel_cell(deg: f32, wrong: f32, frames: usize) -> String {
    if frames == 0 {
        "-".to_string()
    } else {
        format!("{deg:.0} ({:.0}%)", wrong * 100.0)
    }
}

/// One table row.
#[must_use]
pub fn row(clip: &str, setup: &str, m: &Metrics) -> String {
    let cells = [
        m.frames.to_string(),
        format!("{:.2}", m.err_mean * 100.0),
        format!("{:.2}", m.err_p95 * 100.0),
        format!("{:.1}", m.err_mean_mm),
        format!("{:.1}/{:.1}", m.ee_pos_mean_mm, m.ee_pos_max_mm),
        format!("{:.2}/{:.1}", m.ee_rot_mean_deg, m.ee_rot_max_deg),
        format!("{:.1} ({:.1})", m.skate_cm_s, m.skate_truth_cm_s),
        format!("{:.1} ({:.1})", m.elbow_flips_min, m.elbow_flips_truth_min),
        format!("{:.1} ({:.1})", m.knee_flips_min, m.knee_flips_truth_min),
        swivel_cell(m.elbow_swivel_deg, m.elbow_wrong, m.swivel_frames[0]),
        swivel_cell(m.knee_swivel_deg, m.knee_wrong, m.swivel_frames[1]),
        format!("{:.3} ({:.3})", m.jitter_mm, m.jitter_truth_mm),
        format!("{:.2}/{:.0}", m.solve_us, m.solve_max_us),
        m.non_finite.to_string(),
    ];
    line(clip, setup, &cells)
}

/// The cost of `solve` alone on `subject`'s trackers: per-call times over repeated passes of
/// every evaluated frame (a new solver each pass) until `seconds` of wall time.
#[derive(Debug, Clone, Copy)]
pub struct Cost {
    /// Calls timed.
    pub calls: usize,
    /// Mean, median, 99th percentile and worst, µs per call.
    pub mean_us: f64,
    /// See `mean_us`.
    pub p50_us: f64,
    /// See `mean_us`.
    pub p99_us: f64,
    /// See `mean_us`.
    pub max_us: f64,
    /// What timing an empty region costs (`Instant::now` twice), µs: included above.
    pub clock_us: f64,
}

/// Times `Trackers::solve` alone (store and the pose reset outside the timed region).
pub fn cost(
    subject: &Subject,
    truth: &Truth,
    points: usize,
    smoothing: bool,
    seconds: f64,
) -> Cost {
    let rig = &subject.rig;
    let sk = rig.skeleton();
    let rest = sk.rest();
    let mut locals = rest.to_vec();
    let mut scratch = vec![Mat4::IDENTITY; sk.len()];
    let names = tracker_names(points);
    let mut samples: Vec<(usize, TrackerSample)> = Vec::with_capacity(6);
    let mut times_ns: Vec<u64> = Vec::new();
    let wall = Instant::now();
    while wall.elapsed().as_secs_f64() < seconds || times_ns.is_empty() {
        let mut solver = Trackers::new(rig, &names, Legs::Planted).unwrap();
        solver.set_smoothing(smoothing);
        for (i, &clock) in truth.times.iter().enumerate() {
            samples.clear();
            for (k, &(position, rotation)) in truth.trackers[i][..points].iter().enumerate() {
                samples.push((k, TrackerSample { position, rotation }));
            }
            solver.store(&samples, clock);
            locals.copy_from_slice(rest);
            let start = Instant::now();
            solver.solve(
                rig,
                std::hint::black_box(Mat4::IDENTITY),
                clock,
                &mut locals,
                &mut scratch,
            );
            times_ns.push(start.elapsed().as_nanos() as u64);
            std::hint::black_box(&locals);
        }
    }
    let mut empty: Vec<u64> = (0..10_000)
        .map(|_| {
            let start = Instant::now();
            std::hint::black_box(());
            start.elapsed().as_nanos() as u64
        })
        .collect();
    empty.sort_unstable();
    let calls = times_ns.len();
    let mean_us = times_ns.iter().sum::<u64>() as f64 / calls as f64 / 1000.0;
    times_ns.sort_unstable();
    let at = |q: f64| times_ns[((calls - 1) as f64 * q).round() as usize] as f64 / 1000.0;
    Cost {
        calls,
        mean_us,
        p50_us: at(0.5),
        p99_us: at(0.99),
        max_us: at(1.0),
        clock_us: empty[empty.len() / 2] as f64 / 1000.0,
    }
}
