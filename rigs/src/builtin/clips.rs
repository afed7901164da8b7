//! The built-in avatar's looping clips — `idle`, `walk`, `wave` — sampled from smooth periodic
//! functions of the cycle phase.
//!
//! Poses are authored as per-joint rotations `Δ_j` in the world-aligned frame the parent
//! carries (flex a knee = turn about X, whatever the bind frames are) and written as the
//! joint-local rotations of the rotated bind frames, `R_j = U_p⁻¹ Δ_j U_j`
//! ([`Rig::local_rotation`]). Angles are in degrees. Facing +Z with the left side at +X, a
//! negative turn about X swings a hanging limb forwards.

use super::skeleton::{JOINT_COUNT, Rig, joint::*};
use glam::{DQuat, DVec3};
use std::f64::consts::TAU;

/// Keys per second.
pub const SAMPLE_RATE: f64 = 30.0;

/// One clip as sampled keys, ready to write.
#[derive(Clone, Debug, PartialEq)]
pub struct SampledClip {
    /// The clip's name (`idle`, `walk` or `wave`).
    pub name: &'static str,
    /// Key times in seconds from 0 to the duration; the last key repeats the first pose.
    pub times: Vec<f32>,
    /// `(joint, rotations as [x, y, z, w])` for every joint the clip moves away from bind.
    pub rotations: Vec<(usize, Vec<[f32; 4]>)>,
    /// `humanoid_root`'s translation (its bind position plus the clip's offset), if animated.
    pub root_translation: Option<Vec<[f32; 3]>>,
}

/// A pose: `Δ_j` per joint and how far `humanoid_root` moved from its bind position.
#[derive(Clone, Debug, PartialEq)]
pub struct Pose {
    /// `Δ_j` per joint, indexed as [`super::JOINTS`]: the joint's turn in the world-aligned frame
    /// its parent carries (identity at bind).
    pub delta: [DQuat; JOINT_COUNT],
    /// `humanoid_root`'s offset from its bind position, model space, metres.
    pub root_offset: DVec3,
}

impl Pose {
    fn rest() -> Self {
        Self {
            delta: [DQuat::IDENTITY; JOINT_COUNT],
            root_offset: DVec3::ZERO,
        }
    }
}

/// A clip as a function of the cycle phase in `[0, 1)`.
#[derive(Clone, Copy, Debug)]
pub struct ClipSpec {
    /// The clip's name.
    pub name: &'static str,
    /// Seconds per cycle.
    pub duration: f64,
    /// Whether the clip moves `humanoid_root` (writes its translation channel).
    pub animates_root: bool,
    /// The pose at a cycle phase in `[0, 1)`.
    pub pose: fn(&Rig, f64) -> Pose,
}

/// The built-in clips, in file order.
pub const CLIPS: [ClipSpec; 3] = [
    ClipSpec {
        name: "idle",
        duration: 4.0,
        animates_root: true,
        pose: idle,
    },
    ClipSpec {
        name: "walk",
        duration: 1.0,
        animates_root: true,
        pose: walk,
    },
    ClipSpec {
        name: "wave",
        duration: 2.0,
        animates_root: false,
        pose: wave,
    },
];

fn rx(degrees: f64) -> DQuat {
    DQuat::from_rotation_x(degrees.to_radians())
}
fn ry(degrees: f64) -> DQuat {
    DQuat::from_rotation_y(degrees.to_radians())
}
fn rz(degrees: f64) -> DQuat {
    DQuat::from_rotation_z(degrees.to_radians())
}

/// Arms hanging at the sides from the T-pose, slightly away from the body.
const ARM_DOWN: f64 = 78.0;

/// Breathing and a slow sway over the feet, which stay planted: the hips lean the legs back
/// under the moving pelvis, and the root drops by what the lean costs in height.
fn idle(rig: &Rig, phase: f64) -> Pose {
    let mut pose = Pose::rest();
    let breath = (TAU * phase).sin();
    let sway = 0.012 * (TAU * phase).sin();
    let leg = rig.position[L_HIP].y - rig.position[L_ANKLE].y;
    let lean = (-sway / leg).asin();
    pose.root_offset = DVec3::new(sway, -leg * (1.0 - lean.cos()), 0.0);
    let d = &mut pose.delta;
    d[L_HIP] = DQuat::from_rotation_z(lean);
    d[R_HIP] = DQuat::from_rotation_z(lean);
    d[L_ANKLE] = DQuat::from_rotation_z(-lean);
    d[R_ANKLE] = DQuat::from_rotation_z(-lean);
    d[VT10] = rx(1.5 * breath);
    d[VT1] = rx(-breath);
    d[L_STERNOCLAVICULAR] = rz(breath);
    d[R_STERNOCLAVICULAR] = rz(-breath);
    d[L_SHOULDER] = rz(-ARM_DOWN + 1.5 * breath);
    d[R_SHOULDER] = rz(ARM_DOWN - 1.5 * breath);
    d[L_ELBOW] = ry(-12.0);
    d[R_ELBOW] = ry(12.0);
    d[SKULLBASE] = ry(6.0 * (TAU * phase).sin()) * rx(2.0 * (2.0 * TAU * phase).sin());
    pose
}

/// A walk cycle in place: the left leg swings forwards in the first half-cycle, arms swing
/// against the legs, the torso counter-rotates the pelvis, and the root bobs so that the lower
/// ankle stays at its bind height (the stance foot is flat on the ground).
fn walk(rig: &Rig, phase: f64) -> Pose {
    let mut pose = Pose::rest();
    let angle = TAU * phase;
    let d = &mut pose.delta;
    for (hip, knee, ankle, offset) in [(L_HIP, L_KNEE, L_ANKLE, 0.0), (R_HIP, R_KNEE, R_ANKLE, 0.5)]
    {
        let a = TAU * (phase + offset);
        // Hip flexion (+ forwards), peaking at the ends of the swing.
        let flex = 25.0 * a.sin();
        // Swing is when the hip flexes (cos > 0); the knee bends most in mid-swing.
        let swing = (0.5 * (1.0 + a.cos())).powi(3);
        let bend = 5.0 + 55.0 * swing;
        d[hip] = rx(-flex);
        d[knee] = rx(bend);
        // Keep the sole level, lifting the toes a little in swing.
        d[ankle] = rx(flex - bend - 8.0 * swing);
    }
    for (shoulder, elbow, side, offset) in [
        (L_SHOULDER, L_ELBOW, 1.0, 0.5),
        (R_SHOULDER, R_ELBOW, -1.0, 0.0),
    ] {
        let a = TAU * (phase + offset);
        let swing = 18.0 * a.sin();
        d[shoulder] = rx(-swing) * rz(-side * ARM_DOWN);
        d[elbow] = ry(-side * (18.0 + 10.0 * (0.5 + 0.5 * a.sin())));
    }
    d[SACROILIAC] = ry(-5.0 * angle.sin());
    d[VL5] = rx(3.0) * ry(3.0 * angle.sin());
    d[VT10] = ry(3.0 * angle.sin());
    d[SKULLBASE] = rx(-3.0) * ry(-6.0 * angle.sin());
    pose.root_offset.x = -0.02 * angle.cos();
    let rest_ankle = rig.position[L_ANKLE].y;
    let ankles = rig.joint_positions(&pose.delta, pose.root_offset);
    pose.root_offset.y = rest_ankle - ankles[L_ANKLE].y.min(ankles[R_ANKLE].y);
    pose
}

/// The right hand raised beside the head, the forearm waving side to side three times a cycle.
fn wave(_: &Rig, phase: f64) -> Pose {
    let mut pose = Pose::rest();
    let wag = (3.0 * TAU * phase).sin();
    let lag = (3.0 * TAU * phase - 0.6).sin();
    let d = &mut pose.delta;
    d[R_STERNOCLAVICULAR] = rz(-8.0);
    d[R_SHOULDER] = ry(15.0) * rz(-45.0);
    // The forearm swings ±25° about vertical (45° + 45° above the horizontal).
    d[R_ELBOW] = rz(-45.0 - 25.0 * wag);
    d[R_WRIST] = rz(-12.0 * lag);
    d[L_SHOULDER] = rz(-ARM_DOWN);
    d[L_ELBOW] = ry(-10.0);
    d[VT10] = rz(2.0);
    d[SKULLBASE] = ry(-8.0) * rz(-4.0 + 2.0 * (TAU * phase).sin());
    pose
}

/// Samples `spec` at [`SAMPLE_RATE`]; key `n` (at the duration) reuses phase 0, so the clip
/// loops without a seam.
#[must_use]
pub fn sample(rig: &Rig, spec: &ClipSpec) -> SampledClip {
    let keys = (spec.duration * SAMPLE_RATE).round() as usize;
    let poses: Vec<Pose> = (0..=keys)
        .map(|i| (spec.pose)(rig, (i % keys) as f64 / keys as f64))
        .collect();
    let times = (0..=keys)
        .map(|i| (i as f64 / SAMPLE_RATE) as f32)
        .collect();
    let mut rotations = Vec::new();
    for j in 0..JOINT_COUNT {
        if poses.iter().all(|p| p.delta[j] == DQuat::IDENTITY) {
            continue;
        }
        let rest = rig.rest_local(j).1;
        let keys = poses
            .iter()
            .map(|p| {
                let r = rig.local_rotation(j, p.delta[j]);
                // The hemisphere of the rest rotation: every clip stays well within a half turn
                // of it, so neighbouring keys never flip sign and LINEAR takes the short way.
                let r = if r.dot(rest) < 0.0 { -r } else { r };
                r.as_quat().to_array()
            })
            .collect();
        rotations.push((j, keys));
    }
    let root_translation = spec.animates_root.then(|| {
        poses
            .iter()
            .map(|p| {
                (rig.position[HUMANOID_ROOT] + p.root_offset)
                    .as_vec3()
                    .to_array()
            })
            .collect()
    });
    SampledClip {
        name: spec.name,
        times,
        rotations,
        root_translation,
    }
}

/// Every built-in clip, sampled.
#[must_use]
pub fn sample_all(rig: &Rig) -> Vec<SampledClip> {
    CLIPS.iter().map(|spec| sample(rig, spec)).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn clips_loop_and_stay_in_the_rest_hemisphere() {
        let rig = Rig::new();
        for clip in sample_all(&rig) {
            assert_eq!(clip.times.first(), Some(&0.0));
            for (j, keys) in &clip.rotations {
                assert_eq!(keys.first(), keys.last(), "{} joint {j}", clip.name);
                for pair in keys.windows(2) {
                    let [a, b] = [pair[0], pair[1]].map(glam::Quat::from_array);
                    assert!(a.dot(b) > 0.9, "{} joint {j} jumps", clip.name);
                }
            }
        }
    }

    #[test]
    fn walk_keeps_the_lower_ankle_on_its_bind_height() {
        let rig = Rig::new();
        for i in 0..30 {
            let pose = walk(&rig, i as f64 / 30.0);
            let p = rig.joint_positions(&pose.delta, pose.root_offset);
            let low = p[L_ANKLE].y.min(p[R_ANKLE].y);
            assert!((low - rig.position[L_ANKLE].y).abs() < 1e-12);
        }
    }
}
