//! Inverse kinematics (seed 002: "the process of computing a set of DOFs that causes some
//! world space goal to be met"): an avatar's pose after its clip and live driver, bent so that
//! chosen joints reach goals, before overrides and DOF limits.
//!
//! Everything here works in the avatar's **model space** (the space of its forward kinematics,
//! before its placement in the scene; metres, Y up, facing +Z) on the local transforms of one
//! tick, and changes only local rotations:
//!
//! - [`two_bone`]: a limb (root, middle, end — shoulder, elbow, wrist) solved in closed form.
//!   The triangle's angles from the law of cosines, `cos ∠b = (l₁² + l₂² − d²) / (2 l₁ l₂)`,
//!   bent in the plane the limb bends in now (or the pole's), the root turned so the end lies
//!   on the line to the goal, then the limb swivelled about that line so the middle joint lies
//!   toward the pole. A goal out of reach (or too close) is clamped to the limb's reach: the
//!   limb points straight at it. Exact to float rounding for reachable goals.
//! - [`chain`]: any chain (a spine, a neck, a tail) by FABRIK on the joints' positions, then
//!   each joint turned onto its solved position.
//! - [`look_at`]: a gaze: the neck turned part of the way, then the head the rest, so the
//!   head's forward axis (+Z at rest) points at a target; eyes follow when the rig has them.
//!
//! A rotation goal sets the end joint's model-space rotation. Every solve blends with the pose
//! it started from by a weight in [0, 1] (slerp of each changed local rotation).

use glam::{Mat4, Quat, Vec3};
use posecast_proto::{Skeleton, Transform};

/// Passes of [`chain`] at most.
pub const CHAIN_ITERATIONS: usize = 1024;
/// [`chain`] stops once the end is this close to the goal, metres.
pub const CHAIN_TOLERANCE: f32 = 1e-4;
/// How far inside its full reach a limb is kept, metres: a limb exactly straight has no bend
/// plane, and the next tick's solve would have to guess one.
const REACH_MARGIN: f32 = 1e-5;

/// World (model-space) matrices of `locals`, recomputed for joint `from` and everything below
/// it (parents precede children, so each is recomputed from an up-to-date parent); `from` 0
/// recomputes every joint. Joints after `from` in other subtrees are skipped: a solve turning
/// an elbow does not pay for the legs.
pub fn update_world(skeleton: &Skeleton, locals: &[Transform], world: &mut [Mat4], from: usize) {
    /// Joints after `from` a subtree walk tracks on the stack; more recompute everything.
    const WORDS: usize = 16;
    let parents = skeleton.parents();
    let n = skeleton.len();
    let at = |j: usize, world: &mut [Mat4]| {
        let local = locals[j].to_mat4();
        world[j] = match parents[j] {
            Some(p) => world[p] * local,
            None => local,
        };
    };
    if from == 0 || n - from > WORDS * 64 {
        for j in from..n {
            at(j, world);
        }
        return;
    }
    let mut moved = [0u64; WORDS];
    for (j, parent) in parents.iter().enumerate().skip(from) {
        let below = j == from
            || parent.is_some_and(|p| {
                p >= from && (moved[(p - from) / 64] >> ((p - from) % 64)) & 1 == 1
            });
        if below {
            let k = j - from;
            moved[k / 64] |= 1 << (k % 64);
            at(j, world);
        }
    }
}

pub(crate) fn position(world: &[Mat4], j: usize) -> Vec3 {
    world[j].w_axis.truncate()
}

/// The model-space rotation of a world matrix (its scale taken out).
pub(crate) fn rotation(world: &[Mat4], j: usize) -> Quat {
    let (_, r, _) = world[j].to_scale_rotation_translation();
    r.normalize()
}

/// Turns joint `j` by the model-space rotation `r` about its own position:
/// `L' = L · (G⁻¹ · r · G)`, `G` the joint's model-space rotation, so `G' = r · G`.
fn turn(locals: &mut [Transform], world: &[Mat4], j: usize, r: Quat) {
    let g = rotation(world, j);
    locals[j].rotation = (locals[j].rotation * (g.inverse() * r * g)).normalize();
}

/// `v`'s direction, also for vectors whose squared length overflows (a goal 10²⁰ m away);
/// `None` for a zero or non-finite vector.
pub(crate) fn direction(v: Vec3) -> Option<Vec3> {
    let largest = v.abs().max_element();
    if !(largest.is_finite() && largest > 0.0) {
        return None;
    }
    (v / largest).try_normalize()
}

/// The shortest rotation taking direction `from` onto `to`; identity when either is
/// degenerate.
fn arc(from: Vec3, to: Vec3) -> Quat {
    match (direction(from), direction(to)) {
        (Some(a), Some(b)) => Quat::from_rotation_arc(a, b),
        _ => Quat::IDENTITY,
    }
}

/// A unit vector perpendicular to `v` (any, stable: the axis least aligned with it, crossed).
fn perpendicular(v: Vec3) -> Vec3 {
    let a = v.abs();
    let other = if a.x <= a.y && a.x <= a.z {
        Vec3::X
    } else if a.y <= a.z {
        Vec3::Y
    } else {
        Vec3::Z
    };
    v.cross(other).normalize_or(Vec3::X)
}

/// Blends the changed joints' local rotations back toward `before` by `1 − weight`.
fn blend(locals: &mut [Transform], before: &[Quat], joints: &[usize], weight: f32) {
    if weight >= 1.0 {
        return;
    }
    for (&j, &q) in joints.iter().zip(before) {
        let solved = locals[j].rotation;
        // The shorter way round: q and −q are the same rotation.
        let solved = if q.dot(solved) < 0.0 { -solved } else { solved };
        locals[j].rotation = q.slerp(solved, weight.max(0.0)).normalize();
    }
}

/// A limb goal for [`two_bone`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LimbGoal {
    /// Where the end joint goes, model space, metres.
    pub target: Vec3,
    /// The end joint's model-space rotation, if the goal sets it.
    pub rotation: Option<Quat>,
    /// A point the middle joint bends toward (an elbow's or knee's swivel), model space;
    /// `None`: the plane the limb bends in now.
    pub pole: Option<Vec3>,
    /// How much of the solve to apply, 0 (none) to 1 (all).
    pub weight: f32,
}

/// Solves a limb in closed form: `a` (root, e.g. the shoulder), `b` (middle, the elbow) and
/// `c` (end, the wrist), `a` an ancestor of `b` and `b` of `c`; changes the local rotations of
/// `a`, `b` and, with a rotation goal, `c`, and leaves `world` up to date.
///
/// The limb's new shape is built first: with `d` the goal's distance from `a` (clamped to what
/// the limb spans), `n` the direction to the goal and `s` the side the middle joint bends to
/// (toward the pole, else the side it bends to now), the middle joint goes to
/// `b* = a + l₁ (cos α · n + sin α · s)`, `α` the triangle's angle at `a` (law of cosines;
/// its sine from the triangle's area by Heron's formula, accurate when the limb is nearly
/// straight), and the end to `c* = a + d · n`. Then `a` is turned by the shortest arc taking
/// `b` onto `b*`, and `b` by the one taking `c` onto `c*`: the least change of the pose that
/// meets the goal, and the same answer every tick for a still goal.
pub fn two_bone(
    skeleton: &Skeleton,
    locals: &mut [Transform],
    world: &mut [Mat4],
    [a, b, c]: [usize; 3],
    goal: &LimbGoal,
) {
    let before = [locals[a].rotation, locals[b].rotation, locals[c].rotation];
    let (pa, pb, pc) = (position(world, a), position(world, b), position(world, c));
    let (l1, l2) = (pb.distance(pa), pc.distance(pb));
    if l1 <= f32::EPSILON || l2 <= f32::EPSILON {
        return;
    }
    let to_goal = goal.target - pa;
    // Toward the goal; a goal on the root itself keeps the limb's current direction.
    let Some(n) = direction(to_goal).or_else(|| direction(pc - pa)) else {
        return;
    };
    // The distance the end can be from the root, within what the limb spans.
    let far = l1 + l2 - REACH_MARGIN;
    let near = ((l1 - l2).abs() + REACH_MARGIN).min(far);
    let d = if to_goal.is_finite() {
        to_goal.length()
    } else {
        f32::INFINITY
    };
    let d = if d.is_finite() {
        d.clamp(near, far)
    } else {
        far
    };
    // The side the middle joint bends to: toward the pole, else where it bends now, else any.
    let flat = |v: Vec3| v - n * v.dot(n);
    let side = goal
        .pole
        .and_then(|p| direction(flat(p - pa)))
        .or_else(|| direction(flat(pb - pa)))
        .unwrap_or_else(|| perpendicular(n));
    let cos_a = ((l1 * l1 + d * d - l2 * l2) / (2.0 * l1 * d)).clamp(-1.0, 1.0);
    let sin_a = (2.0 * heron(l1, l2, d) / (l1 * d)).clamp(0.0, 1.0);
    let b_goal = pa + l1 * (cos_a * n + sin_a * side);
    let c_goal = pa + d * n;

    turn(locals, world, a, arc(pb - pa, b_goal - pa));
    update_world(skeleton, locals, world, a);
    let pb = position(world, b);
    turn(locals, world, b, arc(position(world, c) - pb, c_goal - pb));
    update_world(skeleton, locals, world, a);

    // The end's rotation: G_c = goal, so L_c = G_parent(c)⁻¹ · goal.
    if let Some(r) = goal.rotation {
        set_model_rotation(skeleton, locals, world, c, r);
    }
    blend(locals, &before, &[a, b, c], goal.weight);
    update_world(skeleton, locals, world, a);
}

/// The area of a triangle of sides `x`, `y`, `z` (Heron's formula in Kahan's stable form:
/// sides sorted, the brackets kept), 0 for a degenerate triangle.
fn heron(x: f32, y: f32, z: f32) -> f32 {
    let mut s = [x, y, z];
    s.sort_by(|p, q| q.total_cmp(p));
    let [a, b, c] = s;
    let product = (a + (b + c)) * (c - (a - b)) * (c + (a - b)) * (a + (b - c));
    0.25 * product.max(0.0).sqrt()
}

/// Sets joint `j`'s model-space rotation to `r` (its local rotation `G_parent⁻¹ · r`, scale
/// kept), and updates `world` from it.
pub fn set_model_rotation(
    skeleton: &Skeleton,
    locals: &mut [Transform],
    world: &mut [Mat4],
    j: usize,
    r: Quat,
) {
    turn(
        locals,
        world,
        j,
        r.normalize() * rotation(world, j).inverse(),
    );
    update_world(skeleton, locals, world, j);
}

/// A chain goal for [`chain`].
#[derive(Debug, Clone, PartialEq)]
pub struct ChainGoal {
    /// The chain from its root to its end joint, each joint the parent (or an ancestor) of the
    /// next.
    pub chain: Vec<usize>,
    /// Where the end joint goes, model space.
    pub target: Vec3,
    /// The end joint's model-space rotation, if the goal sets it.
    pub rotation: Option<Quat>,
    /// How much of the solve to apply, 0 to 1.
    pub weight: f32,
}

/// Solves any chain by FABRIK (forward and backward reaching on the joints' positions: the
/// end put on the goal and each joint pulled to its bone's length from the next, then the root
/// put back and each joint pulled from the previous, until the end is within
/// [`CHAIN_TOLERANCE`] or after [`CHAIN_ITERATIONS`] passes), then each joint from the root on
/// turned by the shortest arc taking its child onto its solved position. Returns the end's
/// distance to the goal. An unreachable goal (or one within [`CHAIN_TOLERANCE`] of the chain's
/// reach, where FABRIK converges slowest) leaves the chain straight toward it.
pub fn chain(
    skeleton: &Skeleton,
    locals: &mut [Transform],
    world: &mut [Mat4],
    goal: &ChainGoal,
) -> f32 {
    chain_seeded(skeleton, locals, world, goal, &mut Vec::new())
}

/// [`chain`], FABRIK started from `seed` when it holds one position per joint (each relative to
/// the chain's root, e.g. the last tick's answer: a goal that moved a little is met in a pass
/// or two) instead of the pose's positions; `seed` is then set to this solve's positions. The
/// joints are still turned from the pose they had, so nothing accumulates from tick to tick.
pub fn chain_seeded(
    skeleton: &Skeleton,
    locals: &mut [Transform],
    world: &mut [Mat4],
    goal: &ChainGoal,
    seed: &mut Vec<Vec3>,
) -> f32 {
    let joints = &goal.chain;
    let (Some(&root), Some(&end)) = (joints.first(), joints.last()) else {
        return f32::INFINITY;
    };
    let before: Vec<Quat> = joints.iter().map(|&j| locals[j].rotation).collect();
    let mut p: Vec<Vec3> = joints.iter().map(|&j| position(world, j)).collect();
    let lengths: Vec<f32> = p.windows(2).map(|w| w[1].distance(w[0])).collect();
    let span: f32 = lengths.iter().sum();
    let base = p[0];
    let k = p.len() - 1;
    if seed.len() == p.len() && seed.iter().all(|s| s.is_finite()) {
        for (p, s) in p.iter_mut().zip(seed.iter()).skip(1) {
            *p = base + *s;
        }
    }
    let toward = |from: Vec3, to: Vec3, length: f32, fallback: Vec3| {
        from + length * direction(to - from).unwrap_or(fallback)
    };
    if !goal.target.is_finite() || goal.target.distance(base) >= span - CHAIN_TOLERANCE {
        // Out of reach: straight at the goal.
        let n = direction(goal.target - base).unwrap_or(Vec3::Y);
        for i in 1..=k {
            p[i] = p[i - 1] + lengths[i - 1] * n;
        }
    } else {
        for _ in 0..CHAIN_ITERATIONS {
            if p[k].distance(goal.target) <= CHAIN_TOLERANCE {
                break;
            }
            p[k] = goal.target;
            for i in (0..k).rev() {
                p[i] = toward(p[i + 1], p[i], lengths[i], Vec3::Y);
            }
            p[0] = base;
            for i in 1..=k {
                p[i] = toward(p[i - 1], p[i], lengths[i - 1], Vec3::Y);
            }
        }
    }
    for i in 0..k {
        let here = position(world, joints[i]);
        turn(
            locals,
            world,
            joints[i],
            arc(position(world, joints[i + 1]) - here, p[i + 1] - here),
        );
        update_world(skeleton, locals, world, joints[i]);
    }
    seed.clear();
    seed.extend(p.iter().map(|q| *q - base));
    if let Some(r) = goal.rotation {
        set_model_rotation(skeleton, locals, world, end, r);
    }
    blend(locals, &before, joints, goal.weight);
    update_world(skeleton, locals, world, root);
    position(world, end).distance(goal.target)
}

/// The joints of a gaze, any of them absent: the neck, the head, the eyes.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Gaze {
    /// The neck (H-Anim `vc4`), turned [`NECK_SHARE`] of the way.
    pub neck: Option<usize>,
    /// The head (`skullbase`), turned the rest of the way.
    pub head: Option<usize>,
    /// The eyes (`l_eyeball_joint`, `r_eyeball_joint`), each aimed at the target.
    pub eyes: [Option<usize>; 2],
}

/// The share of a gaze's turn the neck takes; the head takes the rest.
pub const NECK_SHARE: f32 = 0.4;

/// The forward axis of a head or an eye in its own frame: +Z (a normalised rig faces +Z with
/// identity rest rotations, so every joint's rest frame is the model's).
pub const FORWARD: Vec3 = Vec3::Z;

/// Turns the gaze's joints so the head (then the eyes) face `target` (model space), blended
/// by `weight`.
pub fn look_at(
    skeleton: &Skeleton,
    locals: &mut [Transform],
    world: &mut [Mat4],
    gaze: &Gaze,
    target: Vec3,
    weight: f32,
) {
    let joints: Vec<usize> = [gaze.neck, gaze.head, gaze.eyes[0], gaze.eyes[1]]
        .into_iter()
        .flatten()
        .collect();
    let Some(&first) = joints.iter().min() else {
        return;
    };
    let before: Vec<Quat> = joints.iter().map(|&j| locals[j].rotation).collect();
    let aim = |world: &[Mat4], j: usize| {
        let forward = rotation(world, j) * FORWARD;
        arc(forward, target - position(world, j))
    };
    if let (Some(neck), Some(head)) = (gaze.neck, gaze.head) {
        let full = aim(world, head);
        turn(locals, world, neck, Quat::IDENTITY.slerp(full, NECK_SHARE));
        update_world(skeleton, locals, world, neck);
    }
    for j in [gaze.head, gaze.eyes[0], gaze.eyes[1]]
        .into_iter()
        .flatten()
    {
        let r = aim(world, j);
        turn(locals, world, j, r);
        update_world(skeleton, locals, world, j);
    }
    blend(locals, &before, &joints, weight);
    update_world(skeleton, locals, world, first);
}

#[cfg(test)]
mod tests;
