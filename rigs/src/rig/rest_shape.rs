//! What a rig's rest skeleton says about its body: the classification, the up-axis guess and
//! the units guess read it from here, never from a clip.
//!
//! Two kinds of figures:
//! - **Lengths** along the limb chains (thigh, shank, upper arm, forearm, spine), summed joint
//!   to joint: they are the same in every pose, so they hold even when a BVH's offsets put the
//!   rest pose in a crumple of joint frames (Bandai-Namco files lay every segment along its
//!   parent's X axis, legs and spine in one line).
//! - **Directions**, only when the rest pose is *readable*: both legs straight (thigh and shank
//!   within [`READABLE_DEGREES`] of each other) and no more than [`LEGS_APART_DEGREES`] apart
//!   — a standing pose, whatever axis is up (CMU's rest legs splay 20° each way). A crumple has legs in opposite directions or
//!   bent, and gives no directions.

use glam::{Mat4, Vec3};
use posecast_proto::Skeleton;
use posecast_proto::fk::forward_kinematics;

use super::names::{HANIM_SPINE, find};
use super::reorient::SignedAxis;
use crate::asset::Asset;

/// Largest angle (degrees) between a thigh and its shank for the rest pose to count as
/// standing.
pub const READABLE_DEGREES: f32 = 35.0;

/// Largest angle (degrees) between the two legs for the rest pose to count as standing.
pub const LEGS_APART_DEGREES: f32 = 60.0;

/// Largest angle (degrees) between the legs' upward direction and the axis it is snapped to
/// for an up-axis guess.
pub const UP_GUESS_DEGREES: f32 = 30.0;

/// One side's limb: its three mapped joints (root end first), the last optional.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Limb {
    /// The joint at the body: hip or shoulder.
    pub top: usize,
    /// The joint in the middle: knee or elbow.
    pub middle: usize,
    /// The far joint, ankle or wrist, if mapped.
    pub end: Option<usize>,
}

/// The rest skeleton's figures (see the module docs). Lengths are in file units.
#[derive(Clone, Debug)]
pub struct RestShape {
    /// Rest-pose world positions of the joints.
    pub world: Vec<Vec3>,
    /// The joint mapped to `humanoid_root`, if any.
    pub root: Option<usize>,
    /// The nearest joint both arms hang from.
    pub chest: Option<usize>,
    /// The head: `skullbase`, else the highest mapped neck joint.
    pub head: Option<usize>,
    /// Left then right, where mapped (hip, knee, ankle).
    pub legs: Vec<Limb>,
    /// Left then right, where mapped (shoulder, elbow, wrist).
    pub arms: Vec<Limb>,
    /// Whether the rest pose is a standing one (see the module docs), with the angles that
    /// decided it: (worst thigh-to-shank, between the legs), degrees.
    pub readable: Option<(f32, f32)>,
    /// The lowest world point of each leg: its joints, their descendants and BVH end sites.
    pub soles: Vec<Vec3>,
}

impl RestShape {
    /// Measures `asset`'s rest skeleton with its H-Anim mapping `hanim`.
    #[must_use]
    pub fn measure(asset: &Asset, hanim: &[Option<String>]) -> Self {
        let sk = &asset.skeleton;
        let mut m = vec![Mat4::IDENTITY; sk.len()];
        forward_kinematics(sk, sk.rest(), &mut m);
        let world: Vec<Vec3> = m.iter().map(|w| w.w_axis.truncate()).collect();
        let joint = |n: &str| find(hanim, n);
        let limb = |side: &str, parts: [&str; 3]| {
            Some(Limb {
                top: joint(&format!("{side}_{}", parts[0]))?,
                middle: joint(&format!("{side}_{}", parts[1]))?,
                end: joint(&format!("{side}_{}", parts[2])),
            })
        };
        let legs: Vec<Limb> = ["l", "r"]
            .iter()
            .filter_map(|s| limb(s, ["hip", "knee", "ankle"]))
            .collect();
        let arms: Vec<Limb> = ["l", "r"]
            .iter()
            .filter_map(|s| limb(s, ["shoulder", "elbow", "wrist"]))
            .collect();
        let chest = match arms.as_slice() {
            [l, r] => common_ancestor(sk.parents(), l.top, r.top),
            _ => None,
        };
        let head = joint("skullbase").or_else(|| {
            HANIM_SPINE
                .iter()
                .rev()
                .filter(|n| n.starts_with("vc"))
                .find_map(|n| joint(n))
        });
        let ends: Vec<(usize, Vec3)> = asset
            .source
            .end_sites
            .iter()
            .map(|&(j, offset)| (j, m[j].transform_point3(offset)))
            .collect();
        let soles = legs
            .iter()
            .map(|l| lowest_below(sk, &world, &ends, l.top, legs_up(&world, &legs)))
            .collect();
        let mut shape = Self {
            world,
            root: joint("humanoid_root"),
            chest,
            head,
            legs,
            arms,
            readable: None,
            soles,
        };
        shape.readable = shape.standing();
        shape
    }

    /// Sum of the segment lengths from `top` down to `bottom` (a descendant), joint to joint.
    #[must_use]
    pub fn chain(&self, parents: &[Option<usize>], top: usize, bottom: usize) -> Option<f32> {
        let mut j = bottom;
        let mut sum = 0.0;
        while j != top {
            let p = parents.get(j).copied().flatten()?;
            sum += (self.world[j] - self.world[p]).length();
            j = p;
        }
        Some(sum)
    }

    /// Mean thigh + shank length (hip to ankle along the chain), both sides where mapped.
    #[must_use]
    pub fn leg_length(&self, parents: &[Option<usize>]) -> Option<f32> {
        mean(self.legs.iter().filter_map(|l| {
            let thigh = self.chain(parents, l.top, l.middle)?;
            let shank = self.chain(parents, l.middle, l.end?)?;
            Some(thigh + shank)
        }))
    }

    /// Mean upper arm + forearm length (shoulder to wrist along the chain).
    #[must_use]
    pub fn arm_length(&self, parents: &[Option<usize>]) -> Option<f32> {
        mean(self.arms.iter().filter_map(|a| {
            let upper = self.chain(parents, a.top, a.middle)?;
            let fore = self.chain(parents, a.middle, a.end?)?;
            Some(upper + fore)
        }))
    }

    /// The legs' mean direction, hip to ankle (or knee), as a unit vector.
    #[must_use]
    pub fn leg_direction(&self) -> Option<Vec3> {
        let d = self
            .legs
            .iter()
            .map(|l| {
                (self.world[l.end.unwrap_or(l.middle)] - self.world[l.top]).normalize_or_zero()
            })
            .sum::<Vec3>()
            .normalize_or_zero();
        (d != Vec3::ZERO).then_some(d)
    }

    /// The spine's direction, root to chest (or to the head), as a unit vector.
    #[must_use]
    pub fn spine_direction(&self) -> Option<Vec3> {
        let top = self.chest.or(self.head)?;
        let d = (self.world[top] - self.world[self.root?]).normalize_or_zero();
        (d != Vec3::ZERO).then_some(d)
    }

    /// Both legs straight and parallel: (worst knee bend, angle between the legs), degrees.
    fn standing(&self) -> Option<(f32, f32)> {
        let [l, r] = self.legs.as_slice() else {
            return None;
        };
        let bend = |leg: &Limb| -> Option<f32> {
            let end = leg.end?;
            let thigh = self.world[leg.middle] - self.world[leg.top];
            let shank = self.world[end] - self.world[leg.middle];
            Some(angle(thigh, shank))
        };
        let bend = bend(l)?.max(bend(r)?);
        let dir = |leg: &Limb| self.world[leg.end.unwrap_or(leg.middle)] - self.world[leg.top];
        let apart = angle(dir(l), dir(r));
        (bend <= READABLE_DEGREES && apart <= LEGS_APART_DEGREES && bend.is_finite())
            .then_some((bend, apart))
    }

    /// The up axis the rest pose shows: opposite the legs, snapped to the nearest signed axis
    /// when within [`UP_GUESS_DEGREES`] of it, with the head (if mapped) not below the root.
    /// Returns the axis, the angle off it (degrees) and, when the hips' line is level, the
    /// facing axis (`left × up`, H-Anim's humanoid faces +Z with its left at +X).
    #[must_use]
    pub fn up_guess(&self) -> Option<(SignedAxis, f32, Option<SignedAxis>)> {
        self.readable?;
        let up = -self.leg_direction()?;
        let (axis, off) = snap(up)?;
        if off > UP_GUESS_DEGREES {
            return None;
        }
        let u = axis.vector();
        if let (Some(h), Some(r)) = (self.head, self.root)
            && (self.world[h] - self.world[r]).dot(u) < 0.0
        {
            return None;
        }
        let forward = match self.legs.as_slice() {
            [l, r] => {
                let left = self.world[l.top] - self.world[r.top];
                snap(left.cross(u).normalize_or_zero())
                    .filter(|(f, off)| *off <= UP_GUESS_DEGREES && f.vector().dot(u) == 0.0)
                    .map(|(f, _)| f)
            }
            _ => None,
        };
        Some((axis, off, forward))
    }

    /// The hips' height above the feet along +Y, in file units, and how it was found: measured
    /// (the mean hip joint above the lowest point of the legs) when the rest pose is readable
    /// and upright, else estimated from the leg chain: thigh + shank is 0.491 of stature and the
    /// hip joint stands at 0.530 of it (Drillis & Contini's segment proportions), so
    /// `hips ≈ (thigh + shank) · 0.530 / 0.491`.
    #[must_use]
    pub fn hip_height(&self, parents: &[Option<usize>]) -> Option<(f32, &'static str)> {
        let upright = self
            .leg_direction()
            .is_some_and(|d| angle(d, Vec3::NEG_Y) <= UP_GUESS_DEGREES);
        if self.readable.is_some() && upright && self.soles.len() == self.legs.len() {
            let hips = mean(self.legs.iter().map(|l| self.world[l.top].y))?;
            let sole = self.soles.iter().map(|s| s.y).fold(f32::INFINITY, f32::min);
            let h = hips - sole;
            if h.is_finite() && h > 0.0 {
                return Some((h, "measured at rest"));
            }
        }
        let leg = self.leg_length(parents)?;
        (leg > 0.0 && leg.is_finite()).then_some((
            leg * 0.530 / 0.491,
            "estimated from thigh + shank (the rest pose is not upright)",
        ))
    }
}

/// The legs' rough upward direction (for finding the lowest point of each leg), or +Y.
fn legs_up(world: &[Vec3], legs: &[Limb]) -> Vec3 {
    let d: Vec3 = legs
        .iter()
        .map(|l| (world[l.top] - world[l.end.unwrap_or(l.middle)]).normalize_or_zero())
        .sum();
    d.try_normalize().unwrap_or(Vec3::Y)
}

/// The point of `top`'s subtree (joints and end sites) lowest along `up`.
fn lowest_below(
    sk: &Skeleton,
    world: &[Vec3],
    ends: &[(usize, Vec3)],
    top: usize,
    up: Vec3,
) -> Vec3 {
    let parents = sk.parents();
    let under = |mut j: usize| loop {
        if j == top {
            return true;
        }
        match parents[j] {
            Some(p) => j = p,
            None => return false,
        }
    };
    let mut best = world[top];
    for (j, &p) in world.iter().enumerate() {
        if p.dot(up) < best.dot(up) && under(j) {
            best = p;
        }
    }
    for &(j, p) in ends {
        if p.dot(up) < best.dot(up) && under(j) {
            best = p;
        }
    }
    best
}

/// The signed axis nearest `v` and the angle to it, degrees.
fn snap(v: Vec3) -> Option<(SignedAxis, f32)> {
    if v == Vec3::ZERO || !v.is_finite() {
        return None;
    }
    [
        SignedAxis::PosX,
        SignedAxis::NegX,
        SignedAxis::PosY,
        SignedAxis::NegY,
        SignedAxis::PosZ,
        SignedAxis::NegZ,
    ]
    .into_iter()
    .map(|a| (a, angle(a.vector(), v)))
    .min_by(|a, b| a.1.total_cmp(&b.1))
}

/// The angle between two vectors, degrees (`atan2(|a×b|, a·b)`, exact near 0 and 180°).
#[must_use]
pub fn angle(a: Vec3, b: Vec3) -> f32 {
    a.cross(b).length().atan2(a.dot(b)).to_degrees()
}

fn mean(values: impl Iterator<Item = f32>) -> Option<f32> {
    let (sum, n) = values.fold((0.0, 0u32), |(s, n), v| (s + v, n + 1));
    (n > 0).then(|| sum / n as f32)
}

fn common_ancestor(parents: &[Option<usize>], a: usize, b: usize) -> Option<usize> {
    let chain = |mut j: usize| {
        let mut v = vec![j];
        while let Some(p) = parents[j] {
            v.push(p);
            j = p;
        }
        v
    };
    let cb = chain(b);
    chain(a).into_iter().find(|j| cb.contains(j))
}
