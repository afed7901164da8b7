//! Redefining the neutral pose (seed 000, "Redefining the avatar neutral pose"): any pose `H`
//! becomes what all-identity rotations mean, and the H-Anim pose (upright, facing +Z, arms and
//! legs down) is found by aligning named segments with target directions.

use std::f32::consts::PI;

use glam::{Quat, Vec3};
use serde::{Deserialize, Serialize};

use super::adjust::adjust_bind;
use super::names::{HANIM_SPINE, find};
use super::{JointMaps, RigError};
use crate::asset::Asset;

/// Which neutral pose the pipeline gives a rig.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum NeutralPose {
    /// H-Anim when the rig is humanoid (its hips, knees, shoulders and elbows are mapped),
    /// otherwise keep.
    #[default]
    Auto,
    /// H-Anim; an error when the rig is not humanoid.
    HAnim,
    /// Keep the current one (the bind pose, after simplification).
    Keep,
}

/// H-Anim joints a rig needs for the H-Anim neutral pose and for retargeting.
pub const REQUIRED: &[&str] = &[
    "humanoid_root",
    "l_hip",
    "l_knee",
    "r_hip",
    "r_knee",
    "l_shoulder",
    "l_elbow",
    "r_shoulder",
    "r_elbow",
];

/// Makes the pose with local rotations `H_i` the neutral one: `V_i = V_parent(i) H_i`, then
/// [`adjust_bind`]. Afterwards all-identity rotations reproduce the pose `H` (translations and
/// scales from the rest pose), and every skinned vertex is unchanged for every clip frame.
pub fn apply_neutral_pose(
    asset: Asset,
    h: &[Quat],
) -> Result<(Asset, JointMaps, Vec<String>), RigError> {
    let sk = &asset.skeleton;
    if h.len() != sk.len() {
        return Err(RigError::Length {
            what: "neutral pose rotations",
            expected: sk.len(),
            actual: h.len(),
        });
    }
    let mut v: Vec<Quat> = Vec::with_capacity(h.len());
    for (j, hj) in h.iter().enumerate() {
        let vp = sk.parents()[j].map_or(Quat::IDENTITY, |p| v[p]);
        v.push((vp * *hj).normalize());
    }
    adjust_bind(asset, &v)
}

/// The H-Anim neutral pose as local rotations `H_i`, starting from the current neutral pose
/// (all rotations identity) and aligning, parents first (seed 000's last paragraph):
/// 1. the body to face +Z (the hips' right-to-left line along +X, turning about Y);
/// 2. each mapped spine segment, up to `skullbase`, with +Y;
/// 3. thigh and shank with −Y, then the foot (ankle to toe) turned about Y to point +Z;
/// 4. upper arm, forearm and hand (wrist to its first non-thumb child) with −Y.
///
/// Each alignment rotates the segment's current world direction `a` onto `d` by
/// `q = (a·h, a×h)` with the half-vector `h = (a+d)/|a+d|` (a half-turn about an axis
/// perpendicular to `a` when `a ≈ −d`), then post-multiplies the parent joint's local rotation
/// by `s = r⁻¹ q r`, `r` its current world rotation. Segments of zero length are skipped.
pub fn hanim_pose(asset: &Asset, hanim: &[Option<String>]) -> Result<Vec<Quat>, RigError> {
    let missing: Vec<String> = REQUIRED
        .iter()
        .filter(|n| find(hanim, n).is_none())
        .map(|n| (*n).to_owned())
        .collect();
    if !missing.is_empty() {
        return Err(RigError::NotHumanoid {
            rig: asset.name.clone(),
            missing,
        });
    }
    let joint = |n: &str| find(hanim, n);
    let mut pose = Pose::new(asset);
    let root = joint("humanoid_root").unwrap_or(0);

    // 1. Facing.
    if let (Some(l), Some(r)) = (joint("l_hip"), joint("r_hip")) {
        let lateral = pose.position(l) - pose.position(r);
        let flat = Vec3::new(lateral.x, 0.0, lateral.z);
        if flat.length() > pose.eps {
            pose.rotate_world(
                root,
                half_vector_rotation(flat.normalize(), Vec3::X, Vec3::Y),
            );
        }
    }
    // 2. Spine, pelvis up.
    let spine: Vec<usize> = HANIM_SPINE.iter().filter_map(|n| joint(n)).collect();
    for pair in spine.windows(2) {
        if pose.is_ancestor(pair[0], pair[1]) {
            pose.align(pair[0], pair[1], Vec3::Y, Vec3::X);
        }
    }
    // 3. Legs and feet; 4. arms and hands.
    for side in ["l", "r"] {
        let j = |p: &str| joint(&format!("{side}_{p}"));
        for (a, b) in [("hip", "knee"), ("knee", "ankle")] {
            if let (Some(a), Some(b)) = (j(a), j(b)) {
                pose.align(a, b, Vec3::NEG_Y, Vec3::Z);
            }
        }
        if let Some(ankle) = j("ankle")
            && let Some(toe) = j("midtarsal").or_else(|| pose.first_child(ankle, &[]))
        {
            let a = pose.position(toe) - pose.position(ankle);
            let flat = Vec3::new(a.x, 0.0, a.z);
            if flat.length() > pose.eps {
                pose.rotate_world(
                    ankle,
                    half_vector_rotation(flat.normalize(), Vec3::Z, Vec3::Y),
                );
            }
        }
        for (a, b) in [("shoulder", "elbow"), ("elbow", "wrist")] {
            if let (Some(a), Some(b)) = (j(a), j(b)) {
                pose.align(a, b, Vec3::NEG_Y, Vec3::Z);
            }
        }
        if let Some(wrist) = j("wrist") {
            let thumbs: Vec<usize> = (0..4).filter_map(|k| j(&format!("thumb{k}"))).collect();
            let finger = j("middle1")
                .or_else(|| j("index1"))
                .or_else(|| pose.first_child(wrist, &thumbs));
            if let Some(finger) = finger {
                pose.align(wrist, finger, Vec3::NEG_Y, Vec3::Z);
            }
        }
    }
    Ok(pose.local)
}

/// The rotation taking unit `a` onto unit `d` through the half-vector (seed 000):
/// `h = (a+d)/|a+d|`, `q = (a·h, a×h)`. When `a ≈ −d` the half-vector is undefined and any
/// half-turn about an axis perpendicular to `a` works; `prefer` picks it (projected off `a`).
#[must_use]
pub fn half_vector_rotation(a: Vec3, d: Vec3, prefer: Vec3) -> Quat {
    let sum = a + d;
    if sum.length() < 1e-4 {
        let axis = (prefer - a * a.dot(prefer))
            .try_normalize()
            .unwrap_or_else(|| a.any_orthonormal_vector());
        return Quat::from_axis_angle(axis, PI);
    }
    let h = sum.normalize();
    let v = a.cross(h);
    Quat::from_xyzw(v.x, v.y, v.z, a.dot(h)).normalize()
}

/// A pose under construction: local rotations over the rest translations and scales.
struct Pose<'a> {
    asset: &'a Asset,
    local: Vec<Quat>,
    /// Lengths below this are zero (relative to the rig's size).
    eps: f32,
}

impl<'a> Pose<'a> {
    fn new(asset: &'a Asset) -> Self {
        let n = asset.skeleton.len();
        let mut p = Self {
            asset,
            local: vec![Quat::IDENTITY; n],
            eps: 0.0,
        };
        let (pos, _) = p.world();
        let (lo, hi) = pos.iter().fold(
            (Vec3::splat(f32::MAX), Vec3::splat(f32::MIN)),
            |(lo, hi), &x| (lo.min(x), hi.max(x)),
        );
        p.eps = 1e-6 * (hi - lo).max_element().max(1e-3);
        p
    }

    /// World positions and rotations (rest translations and scales, these rotations).
    fn world(&self) -> (Vec<Vec3>, Vec<Quat>) {
        let sk = &self.asset.skeleton;
        let n = sk.len();
        let mut pos = vec![Vec3::ZERO; n];
        let mut rot = vec![Quat::IDENTITY; n];
        let mut scale = vec![Vec3::ONE; n];
        for j in 0..n {
            let rest = sk.rest()[j];
            match sk.parents()[j] {
                Some(p) => {
                    pos[j] = pos[p] + rot[p] * (scale[p] * rest.translation);
                    rot[j] = (rot[p] * self.local[j]).normalize();
                    scale[j] = scale[p] * rest.scale;
                }
                None => {
                    pos[j] = rest.translation;
                    rot[j] = self.local[j];
                    scale[j] = rest.scale;
                }
            }
        }
        (pos, rot)
    }

    fn position(&self, j: usize) -> Vec3 {
        self.world().0[j]
    }

    fn is_ancestor(&self, a: usize, mut b: usize) -> bool {
        while let Some(p) = self.asset.skeleton.parents()[b] {
            if p == a {
                return true;
            }
            b = p;
        }
        false
    }

    fn first_child(&self, j: usize, except: &[usize]) -> Option<usize> {
        self.asset
            .skeleton
            .children(j)
            .find(|c| !except.contains(c))
    }

    /// Post-multiplies `j`'s local rotation by `s = r⁻¹ q r`, so its world rotation becomes
    /// `q r` and its subtree turns by the world rotation `q` about the joint.
    fn rotate_world(&mut self, j: usize, q: Quat) {
        let r = self.world().1[j];
        let s = r.inverse() * q * r;
        self.local[j] = (self.local[j] * s).normalize();
    }

    /// Turns joint `p` so that the segment from `p` to its descendant `c` points along `d`.
    fn align(&mut self, p: usize, c: usize, d: Vec3, prefer: Vec3) {
        let (pos, _) = self.world();
        let a = pos[c] - pos[p];
        if a.length() <= self.eps {
            return;
        }
        self.rotate_world(p, half_vector_rotation(a.normalize(), d, prefer));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn half_vector_rotates_a_onto_d() {
        let cases = [
            (Vec3::X, Vec3::NEG_Y),
            (Vec3::new(0.3, -0.2, 0.9).normalize(), Vec3::Y),
            (Vec3::Y, Vec3::NEG_Y),
            (Vec3::NEG_Y, Vec3::NEG_Y),
            (Vec3::new(1e-7, -1.0, 0.0).normalize(), Vec3::Y),
        ];
        for (a, d) in cases {
            let q = half_vector_rotation(a, d, Vec3::Z);
            assert!((q * a).abs_diff_eq(d, 1e-5), "{a} -> {d}: {}", q * a);
            assert!((q.length() - 1.0).abs() < 1e-5);
        }
        // The antiparallel case turns about the preferred axis.
        let q = half_vector_rotation(Vec3::Y, Vec3::NEG_Y, Vec3::Z);
        assert!((q * Vec3::Z).abs_diff_eq(Vec3::Z, 1e-5));
    }
}
