//! The solvers against hand-derived facts: a reachable goal is met (distance, rotation), an
//! unreachable one is pointed at with the limb straight, the pole decides the swivel, a zero
//! weight changes nothing, a still goal gives a still pose, every value stays finite.

#![allow(clippy::unwrap_used)]

use super::*;
use proptest::prelude::*;

/// A root at the origin with a limb hanging from it: `a` at `offset`, `b` and `c` at the given
/// local translations, every joint with the given local rotations.
fn limb(offset: Vec3, ab: Vec3, bc: Vec3, rotations: [Quat; 3]) -> (Skeleton, Vec<Transform>) {
    let t = |translation: Vec3, rotation: Quat| Transform {
        translation,
        rotation,
        scale: Vec3::ONE,
    };
    let rest = vec![
        t(Vec3::ZERO, Quat::IDENTITY),
        t(offset, rotations[0]),
        t(ab, rotations[1]),
        t(bc, rotations[2]),
    ];
    let skeleton = Skeleton::new(
        ["root", "a", "b", "c"].map(String::from).to_vec(),
        vec![None, Some(0), Some(1), Some(2)],
        rest.clone(),
        vec![Mat4::IDENTITY; 4],
    )
    .unwrap();
    (skeleton, rest)
}

fn fk(skeleton: &Skeleton, locals: &[Transform]) -> Vec<Mat4> {
    let mut world = vec![Mat4::IDENTITY; skeleton.len()];
    update_world(skeleton, locals, &mut world, 0);
    world
}

fn vec3(range: f32) -> impl Strategy<Value = Vec3> {
    (-range..range, -range..range, -range..range).prop_map(|(x, y, z)| Vec3::new(x, y, z))
}

fn rotation_strategy() -> impl Strategy<Value = Quat> {
    (vec3(1.0), -3.1f32..3.1).prop_map(|(axis, angle)| {
        Quat::from_axis_angle(axis.try_normalize().unwrap_or(Vec3::Y), angle)
    })
}

fn bone(min: f32) -> impl Strategy<Value = Vec3> {
    vec3(1.0).prop_filter("a bone has a length", move |v| v.length() > min)
}

fn degrees(a: Quat, b: Quat) -> f32 {
    let d = a.inverse() * b;
    (2.0 * d.xyz().length().atan2(d.w.abs())).to_degrees()
}

proptest! {
    /// Any reachable goal is met within 1 mm (typically 10⁻⁶ m), and its rotation within 0.01°.
    #[test]
    fn reachable_limb_goals_are_met(
        offset in vec3(0.5), ab in bone(0.05), bc in bone(0.05),
        rotations in [rotation_strategy(), rotation_strategy(), rotation_strategy()],
        direction in bone(0.01), along in 0.0f32..1.0, goal_rotation in rotation_strategy(),
        pole in proptest::option::of(vec3(2.0)),
    ) {
        let (skeleton, mut locals) = limb(offset, ab, bc, rotations);
        let mut world = fk(&skeleton, &locals);
        let (l1, l2) = (ab.length(), bc.length());
        let (near, far) = ((l1 - l2).abs() + 1e-3, l1 + l2 - 1e-3);
        prop_assume!(far > near);
        let pa = world[1].w_axis.truncate();
        let target = pa + direction.normalize() * (near + along * (far - near));
        let goal = LimbGoal { target, rotation: Some(goal_rotation), pole, weight: 1.0 };
        two_bone(&skeleton, &mut locals, &mut world, [1, 2, 3], &goal);
        let check = fk(&skeleton, &locals);
        prop_assert!(world.iter().zip(&check).all(|(a, b)| a.abs_diff_eq(*b, 1e-5)), "world kept up to date");
        let end = check[3].w_axis.truncate();
        prop_assert!(end.distance(target) < 1e-3, "end {end} target {target}: {} m off", end.distance(target));
        let (_, r, _) = check[3].to_scale_rotation_translation();
        prop_assert!(degrees(r, goal_rotation) < 0.01, "rotation {}° off", degrees(r, goal_rotation));
        // The limb keeps its bone lengths (only rotations change).
        let pb = check[2].w_axis.truncate();
        prop_assert!((pb.distance(pa) - l1).abs() < 1e-4 && (end.distance(pb) - l2).abs() < 1e-4);
    }

    /// With a pole the middle joint bends toward it: it lies on the pole's side of the line
    /// from the root to the goal.
    #[test]
    fn the_pole_sets_the_swivel(
        ab in bone(0.1), bc in bone(0.1),
        rotations in [rotation_strategy(), rotation_strategy(), rotation_strategy()],
        direction in bone(0.1), along in 0.1f32..0.9, pole in vec3(2.0),
    ) {
        let (skeleton, mut locals) = limb(Vec3::ZERO, ab, bc, rotations);
        let mut world = fk(&skeleton, &locals);
        let (l1, l2) = (ab.length(), bc.length());
        let (near, far) = ((l1 - l2).abs() + 1e-2, l1 + l2 - 1e-2);
        prop_assume!(far > near);
        let target = direction.normalize() * (near + along * (far - near));
        let axis = target.normalize();
        let flat = |v: Vec3| v - axis * v.dot(axis);
        prop_assume!(flat(pole).length() > 0.05);
        let goal = LimbGoal { target, rotation: None, pole: Some(pole), weight: 1.0 };
        two_bone(&skeleton, &mut locals, &mut world, [1, 2, 3], &goal);
        let mid = flat(world[2].w_axis.truncate());
        prop_assume!(mid.length() > 1e-3);
        prop_assert!(mid.normalize().dot(flat(pole).normalize()) > 0.9999, "elbow toward the pole");
    }

    /// An out-of-reach goal: the limb straight (within the reach margin), pointing at it,
    /// everything finite — also for goals a kilometre or 1e30 m away.
    #[test]
    fn unreachable_limb_goals_are_pointed_at(
        ab in bone(0.05), bc in bone(0.05),
        rotations in [rotation_strategy(), rotation_strategy(), rotation_strategy()],
        direction in bone(0.01), beyond in prop_oneof![Just(1e30f32), Just(1e3f32), 1.01f32..5.0],
    ) {
        let (skeleton, mut locals) = limb(Vec3::ZERO, ab, bc, rotations);
        let mut world = fk(&skeleton, &locals);
        let target = direction.normalize() * beyond * (ab.length() + bc.length());
        let goal = LimbGoal { target, rotation: None, pole: None, weight: 1.0 };
        two_bone(&skeleton, &mut locals, &mut world, [1, 2, 3], &goal);
        prop_assert!(locals.iter().all(|t| t.rotation.is_finite()));
        let end = world[3].w_axis.truncate();
        prop_assert!((end.length() - (ab.length() + bc.length())).abs() < 1e-3, "straight");
        prop_assert!(end.normalize().angle_between(direction.normalize()).to_degrees() < 0.05);
    }

    /// Weight 0 changes nothing; the same goal solved again from the solved pose stays put
    /// (a still goal gives a still avatar).
    #[test]
    fn weights_and_still_goals(
        ab in bone(0.1), bc in bone(0.1),
        rotations in [rotation_strategy(), rotation_strategy(), rotation_strategy()],
        target in vec3(1.0), pole in proptest::option::of(vec3(2.0)),
    ) {
        let (skeleton, mut locals) = limb(Vec3::ZERO, ab, bc, rotations);
        let mut world = fk(&skeleton, &locals);
        let start = locals.clone();
        let none = LimbGoal { target, rotation: None, pole, weight: 0.0 };
        two_bone(&skeleton, &mut locals, &mut world, [1, 2, 3], &none);
        for (a, b) in locals.iter().zip(&start) {
            prop_assert!(degrees(a.rotation, b.rotation) < 1e-3);
        }
        let goal = LimbGoal { weight: 1.0, ..none };
        two_bone(&skeleton, &mut locals, &mut world, [1, 2, 3], &goal);
        let once = world.clone();
        two_bone(&skeleton, &mut locals, &mut world, [1, 2, 3], &goal);
        for (a, b) in once.iter().zip(&world) {
            prop_assert!(a.w_axis.truncate().distance(b.w_axis.truncate()) < 1e-4, "jitter");
        }
    }

    /// A chain of five joints meets a reachable goal within 1 mm, straightens toward an
    /// unreachable one, and stays finite. (Goals in the first and last 5 % of a chain's reach are left
    /// out: FABRIK creeps there, a few millimetres short after its passes.)
    #[test]
    fn chains_meet_reachable_goals(
        bones in proptest::collection::vec(bone(0.1), 5),
        rotations in proptest::collection::vec(rotation_strategy(), 6),
        direction in bone(0.01), along in 0.05f32..0.95, far in prop_oneof![Just(false), Just(true)],
    ) {
        let mut names = vec!["root".to_owned()];
        let mut parents = vec![None];
        let mut rest = vec![Transform { translation: Vec3::ZERO, rotation: rotations[0], scale: Vec3::ONE }];
        for (i, b) in bones.iter().enumerate() {
            names.push(format!("j{i}"));
            parents.push(Some(i));
            rest.push(Transform { translation: *b, rotation: rotations[i + 1], scale: Vec3::ONE });
        }
        let skeleton = Skeleton::new(names, parents, rest.clone(), vec![Mat4::IDENTITY; 6]).unwrap();
        let mut locals = rest;
        let mut world = fk(&skeleton, &locals);
        let span: f32 = bones[1..].iter().map(|b| b.length()).sum();
        // The nearest the end can come to the base: the longest bone less all the others.
        let longest = bones[1..].iter().map(|b| b.length()).fold(0.0, f32::max);
        let shortest_reach = (2.0 * longest - span).max(0.0) + 0.01;
        prop_assume!(span - 0.01 > shortest_reach);
        let base = world[1].w_axis.truncate();
        let reach = if far { span * 3.0 } else { shortest_reach + along * (span - 0.01 - shortest_reach) };
        let target = base + direction.normalize() * reach;
        // A straight chain on the goal's own line has no direction to bend in (every pull
        // stays on the line); a rig's pose is never exactly that.
        let end0 = world[5].w_axis.truncate() - base;
        prop_assume!(far || end0.angle_between(target - base).to_degrees() > 0.5);
        let goal = ChainGoal { chain: (1..6).collect(), target, rotation: None, weight: 1.0 };
        let error = chain(&skeleton, &mut locals, &mut world, &goal);
        prop_assert!(locals.iter().all(|t| t.rotation.is_finite()));
        if far {
            let end = world[5].w_axis.truncate() - base;
            prop_assert!((end.length() - span).abs() < 1e-2 * span, "straight toward it");
            prop_assert!(end.normalize().angle_between(direction.normalize()).to_degrees() < 1.0);
        } else {
            prop_assert!(error < 1e-3, "{error} m off");
        }
    }
}

/// A gaze turns the head's forward axis onto the target, the neck taking part of the turn.
#[test]
fn look_at_faces_the_target() {
    let t = |y: f32| Transform {
        translation: Vec3::new(0.0, y, 0.0),
        rotation: Quat::IDENTITY,
        scale: Vec3::ONE,
    };
    let skeleton = Skeleton::new(
        ["root", "vc4", "skullbase"].map(String::from).to_vec(),
        vec![None, Some(0), Some(1)],
        vec![t(1.4), t(0.1), t(0.1)],
        vec![Mat4::IDENTITY; 3],
    )
    .unwrap();
    let mut locals = skeleton.rest().to_vec();
    let mut world = fk(&skeleton, &locals);
    let gaze = Gaze {
        neck: Some(1),
        head: Some(2),
        eyes: [None, None],
    };
    let target = Vec3::new(2.0, 2.5, 1.0);
    look_at(&skeleton, &mut locals, &mut world, &gaze, target, 1.0);
    let head = world[2].w_axis.truncate();
    let (_, r, _) = world[2].to_scale_rotation_translation();
    let off = (r * FORWARD).angle_between(target - head).to_degrees();
    assert!(off < 0.01, "head {off}° off the target");
    let neck_turn = 2.0
        * locals[1]
            .rotation
            .xyz()
            .length()
            .atan2(locals[1].rotation.w.abs());
    assert!(
        neck_turn > 0.1,
        "the neck takes part of the turn: {neck_turn} rad"
    );
}
