//! Redefining the neutral pose (seed 000, "Redefining the avatar neutral pose"): any pose `H`
//! becomes what all-identity rotations mean, and the H-Anim pose (upright, facing +Z, arms and
//! legs down) is found by aligning named segments with target directions.

use std::f32::consts::PI;

use glam::{Quat, Vec3};
pub use posecast_proto::rig_options::NeutralPose;

use super::adjust::adjust_bind;
use super::names::{HANIM_SPINE, find};
use super::{JointMaps, RigError};
use crate::asset::Asset;

/// H-Anim joints a rig needs for the H-Anim neutral pose and for retargeting (the core chain
/// of [`super::humanoid`]).
pub const REQUIRED: &[&str] = super::humanoid::CORE;

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

/// The H-Anim neutral pose as local rotations `H_i`, found from the rig's actual joint
/// positions in its rest pose (rest rotations included, so it does not matter which frames the
/// joints were authored in) by aligning segments with target directions, parents first (seed
/// 000's last paragraph):
///
/// - the **pelvis** (the joint both hips hang from): the hip line (right to left hip) along +X,
///   so the body faces +Z, and the spine above it (or, when the spine does not hang from it,
///   the hips' midpoint below it) towards +Y;
/// - the **root**, when it is not the pelvis: the spine above it along +Y, the hip line
///   towards +X;
/// - each mapped **spine** joint: the segment to the next mapped spine joint along +Y; the
///   **chest** (the joint both clavicles hang from) also turns its clavicle line (or, when
///   the clavicles start at one point, its shoulder line) towards +X; `skullbase`: the head
///   (its first child) along +Y;
/// - **clavicles** (sternoclavicular to shoulder) along ±X (left +X, right −X); upper arm,
///   forearm and hand (wrist to the middle or index finger, else its first non-thumb child)
///   along −Y, the thumb towards +Z where the rig has one off the hand's axis;
/// - thigh and shank along −Y, the **foot** (ankle to toe) along +Z.
///
/// A segment runs from a joint to the first joint at a distance from it down the named chain,
/// so zero-length connectors (CMU's `LowerBack`, `Neck`) do not hide it. Each alignment rotates
/// the current world direction `a` onto `d` by `q = (a·h, a×h)` with the half-vector
/// `h = (a+d)/|a+d|` (a half-turn about an axis perpendicular to `a` when `a ≈ −d`); a second
/// direction, when given, then turns about `d` onto its target projected off `d`. The world
/// rotation is applied by post-multiplying the joint's local rotation by `s = r⁻¹ q r`, `r` its
/// current world rotation. Segments of zero length are skipped.
///
/// Every mapped segment thus points along a fixed direction whatever pose the rig starts in,
/// and every joint that several mapped segments hang from (pelvis, chest, hand) is turned
/// about all three axes, so two rigs that differ only in their joint frames or in the pose
/// they were bound in get the same neutral pose. Joints the mapping does not name keep their
/// rotation relative to their parent.
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
    let mut pose = Pose::new(asset);
    let tasks = Tasks::plan(&pose, hanim);
    for j in 0..asset.skeleton.len() {
        if let Some(task) = &tasks.by_joint[j] {
            pose.apply(j, task);
        }
    }
    Ok(pose.local)
}

/// A vector measured on the pose under construction, from a joint.
#[derive(Clone, Copy, Debug)]
enum Measure {
    /// From the aligned joint to this joint.
    To(usize),
    /// From the first joint to the second.
    Line(usize, usize),
    /// From the aligned joint to the midpoint of two joints.
    Mid(usize, usize),
}

/// What one joint is turned to: `primary` exactly onto its direction, then `secondary` (if
/// any) about that direction towards its own.
#[derive(Clone, Copy, Debug)]
struct Task {
    primary: (Measure, Vec3),
    secondary: Option<(Measure, Vec3)>,
    /// The half-turn axis preferred when the primary points opposite its target.
    prefer: Vec3,
}

impl Task {
    fn one(m: Measure, d: Vec3, prefer: Vec3) -> Self {
        Self {
            primary: (m, d),
            secondary: None,
            prefer,
        }
    }

    fn two(m: Measure, d: Vec3, m2: Measure, d2: Vec3) -> Self {
        Self {
            primary: (m, d),
            secondary: Some((m2, d2)),
            prefer: d2,
        }
    }
}

/// The alignment of every joint that has one.
struct Tasks {
    by_joint: Vec<Option<Task>>,
}

impl Tasks {
    fn plan(pose: &Pose<'_>, hanim: &[Option<String>]) -> Self {
        let n = pose.asset.skeleton.len();
        let joint = |name: &str| find(hanim, name);
        let mut by_joint: Vec<Option<Task>> = vec![None; n];
        // Lowest priority first: later plans replace earlier ones for the same joint.
        let spine: Vec<usize> = HANIM_SPINE.iter().filter_map(|s| joint(s)).collect();
        // A spine joint's segment: to the next mapped spine joint above it, else (the top of
        // the spine, usually `skullbase`) to the end of its first child's chain that leads to
        // no limb.
        let sided: Vec<usize> = hanim
            .iter()
            .enumerate()
            .filter(|(_, h)| {
                h.as_deref()
                    .is_some_and(|h| h.starts_with("l_") || h.starts_with("r_"))
            })
            .map(|(j, _)| j)
            .collect();
        let top = spine.last().copied();
        let up_of = |j: usize| -> Option<usize> {
            let above = match spine.iter().position(|&s| s == j) {
                Some(k) => &spine[k + 1..],
                None => &spine[..],
            };
            let mut above = above.iter().copied().filter(|&s| pose.is_ancestor(j, s));
            let mut any = false;
            if let Some(s) = above.find(|&s| {
                any = true;
                pose.distance(j, s) > pose.eps
            }) {
                return Some(s);
            }
            // The top of the spine (`skullbase`): the head, the first child chain that leads
            // to no limb.
            if any || Some(j) != top || Some(j) == joint("humanoid_root") {
                return None;
            }
            pose.asset
                .skeleton
                .children(j)
                .filter(|&c| !sided.iter().any(|&s| s == c || pose.is_ancestor(c, s)))
                .find_map(|c| pose.chain_end(j, c))
        };
        for &s in &spine {
            if let Some(u) = up_of(s) {
                by_joint[s] = Some(Task::one(Measure::To(u), Vec3::Y, Vec3::X));
            }
        }
        let sides = ["l", "r"];
        let side = |s: &str, part: &str| joint(&format!("{s}_{part}"));
        for s in sides {
            let lateral = if s == "l" { Vec3::X } else { Vec3::NEG_X };
            let mut segment = |a: Option<usize>, b: Option<usize>, d: Vec3, prefer: Vec3| {
                if let (Some(a), Some(b)) = (a, b)
                    && pose.is_ancestor(a, b)
                    && let Some(end) = pose.chain_end(a, b)
                {
                    by_joint[a] = Some(Task::one(Measure::To(end), d, prefer));
                }
            };
            segment(
                side(s, "sternoclavicular"),
                side(s, "shoulder"),
                lateral,
                Vec3::Z,
            );
            segment(side(s, "shoulder"), side(s, "elbow"), Vec3::NEG_Y, Vec3::Z);
            segment(side(s, "elbow"), side(s, "wrist"), Vec3::NEG_Y, Vec3::Z);
            segment(side(s, "hip"), side(s, "knee"), Vec3::NEG_Y, Vec3::Z);
            segment(side(s, "knee"), side(s, "ankle"), Vec3::NEG_Y, Vec3::Z);
            if let Some(ankle) = side(s, "ankle") {
                let toe = side(s, "midtarsal")
                    .filter(|&t| pose.is_ancestor(ankle, t))
                    .or_else(|| pose.asset.skeleton.children(ankle).next());
                if let Some(end) = toe.and_then(|t| pose.chain_end(ankle, t)) {
                    by_joint[ankle] = Some(Task::one(Measure::To(end), Vec3::Z, Vec3::Y));
                }
            }
            if let Some(wrist) = side(s, "wrist") {
                let thumbs: Vec<usize> = (0..4)
                    .filter_map(|k| side(s, &format!("thumb{k}")))
                    .filter(|&t| pose.is_ancestor(wrist, t))
                    .collect();
                let finger = side(s, "middle1")
                    .or_else(|| side(s, "index1"))
                    .filter(|&f| pose.is_ancestor(wrist, f))
                    .or_else(|| {
                        pose.asset
                            .skeleton
                            .children(wrist)
                            .find(|&c| !thumbs.iter().any(|&t| t == c || pose.is_ancestor(c, t)))
                    });
                if let Some(end) = finger.and_then(|f| pose.chain_end(wrist, f)) {
                    let thumb = thumbs
                        .iter()
                        .copied()
                        .find(|&t| pose.off_axis(wrist, end, t));
                    by_joint[wrist] = Some(match thumb {
                        Some(t) => {
                            Task::two(Measure::To(end), Vec3::NEG_Y, Measure::To(t), Vec3::Z)
                        }
                        None => Task::one(Measure::To(end), Vec3::NEG_Y, Vec3::Z),
                    });
                }
            }
        }
        // The chest: both clavicles (or shoulders) hang from it.
        let pair = |part: &str| match (side("l", part), side("r", part)) {
            (Some(l), Some(r)) => Some((l, r)),
            _ => None,
        };
        let arms = pair("sternoclavicular")
            .filter(|&(l, r)| pose.distance(l, r) > pose.eps)
            .or_else(|| pair("shoulder"));
        if let Some((l, r)) = arms
            && let Some(chest) = pose.common_ancestor(l, r)
        {
            let line = Measure::Line(r, l);
            by_joint[chest] = Some(match up_of(chest) {
                Some(u) => Task::two(Measure::To(u), Vec3::Y, line, Vec3::X),
                None => Task::one(line, Vec3::X, Vec3::Y),
            });
        }
        // Root and pelvis last: they win over the spine rule.
        let root = joint("humanoid_root").unwrap_or(0);
        if let Some((l, r)) = pair("hip") {
            let line = Measure::Line(r, l);
            let pelvis = pose.common_ancestor(l, r);
            if let Some(p) = pelvis.filter(|&p| p != root)
                && pose.is_ancestor(root, p)
            {
                by_joint[root] = Some(match up_of(root) {
                    Some(u) => Task::two(Measure::To(u), Vec3::Y, line, Vec3::X),
                    None => Task::one(line, Vec3::X, Vec3::Y),
                });
            }
            if let Some(p) = pelvis {
                let up = match up_of(p) {
                    Some(u) => (Measure::To(u), Vec3::Y),
                    None => (Measure::Mid(l, r), Vec3::NEG_Y),
                };
                by_joint[p] = Some(Task::two(line, Vec3::X, up.0, up.1));
            }
        }
        Self { by_joint }
    }
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

/// A pose under construction: local rotations over the rest translations and scales,
/// starting from the rest pose.
struct Pose<'a> {
    asset: &'a Asset,
    local: Vec<Quat>,
    /// Lengths below this are zero (relative to the rig's size).
    eps: f32,
}

impl<'a> Pose<'a> {
    fn new(asset: &'a Asset) -> Self {
        let mut p = Self {
            asset,
            local: asset.skeleton.rest().iter().map(|t| t.rotation).collect(),
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

    fn distance(&self, a: usize, b: usize) -> f32 {
        let (pos, _) = self.world();
        (pos[b] - pos[a]).length()
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

    /// The nearest joint that is `a` or `b` or an ancestor of both.
    fn common_ancestor(&self, a: usize, b: usize) -> Option<usize> {
        let parents = self.asset.skeleton.parents();
        let mut x = Some(a);
        while let Some(j) = x {
            if j == b || self.is_ancestor(j, b) {
                return Some(j);
            }
            x = parents[j];
        }
        None
    }

    /// The end of the segment from `j` through its descendant `first`: `first` when it is
    /// away from `j`, else the first joint away from `j` down `first`'s first children.
    fn chain_end(&self, j: usize, first: usize) -> Option<usize> {
        let mut c = first;
        for _ in 0..self.asset.skeleton.len() {
            if self.distance(j, c) > self.eps {
                return Some(c);
            }
            c = self.asset.skeleton.children(c).next()?;
        }
        None
    }

    /// Whether `t` is off the line from `a` to `b` (by more than 1% of `a`–`b`).
    fn off_axis(&self, a: usize, b: usize, t: usize) -> bool {
        let (pos, _) = self.world();
        let axis = pos[b] - pos[a];
        let v = pos[t] - pos[a];
        let len = axis.length();
        len > self.eps && (v - axis * (v.dot(axis) / (len * len))).length() > 0.01 * len
    }

    fn measure(&self, j: usize, m: Measure) -> Vec3 {
        let (pos, _) = self.world();
        match m {
            Measure::To(c) => pos[c] - pos[j],
            Measure::Line(a, b) => pos[b] - pos[a],
            Measure::Mid(a, b) => 0.5 * (pos[a] + pos[b]) - pos[j],
        }
    }

    /// Turns joint `j` (and its subtree) as `task` says.
    fn apply(&mut self, j: usize, task: &Task) {
        let (m, d) = task.primary;
        let a = self.measure(j, m);
        let mut q = if a.length() > self.eps {
            half_vector_rotation(a.normalize(), d, task.prefer)
        } else {
            Quat::IDENTITY
        };
        if let Some((m2, d2)) = task.secondary {
            // About `d`: the second vector, projected off `d`, onto its target projected off
            // `d` (both perpendicular to `d`, so the half-vector turn is about `d`).
            let off = |v: Vec3| v - d * d.dot(v);
            let (a2, t2) = (off(q * self.measure(j, m2)), off(d2));
            if a2.length() > self.eps && t2.length() > 1e-6 {
                q = half_vector_rotation(a2.normalize(), t2.normalize(), d) * q;
            }
        }
        self.rotate_world(j, q);
    }

    /// Post-multiplies `j`'s local rotation by `s = r⁻¹ q r`, so its world rotation becomes
    /// `q r` and its subtree turns by the world rotation `q` about the joint.
    fn rotate_world(&mut self, j: usize, q: Quat) {
        let r = self.world().1[j];
        let s = r.inverse() * q * r;
        self.local[j] = (self.local[j] * s).normalize();
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
