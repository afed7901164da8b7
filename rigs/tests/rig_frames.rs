//! The H-Anim neutral pose and retargeting do not depend on the joint frames a rig was authored
//! in (issue 18, item 1). A rig and the same rig with random rest rotations on every joint —
//! the mesh and the motion unchanged — give the same neutral pose and the same world-space
//! motion when a clip is retargeted onto them or from them, within 0.05°.
//!
//! "The same rig with random rest rotations" comes in two forms:
//! - **glTF-like**: the generic bind adjustment of seed 000 (`V_i` per joint: rest rotations,
//!   inverse binds and clips change, the posed mesh does not), normalised with and without
//!   bind simplification;
//! - **BVH-like**: the same, then the rest rotations dropped the way a BVH file holds them
//!   (offsets only: the identity pose is the rest pose, which is now a random crumple of the
//!   body, like the Bandai-Namco-style files whose shoulders sit in front of the spine), with
//!   the motion's absolute rotations unchanged.
//!
//! `cargo test -p posecast-server --test rig_frames -- --nocapture` prints the figures.

// Helpers outside #[test] fns unwrap too: a failure there is a test failure.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod rig_support;

use glam::{Mat4, Quat, Vec3};
use posecast_proto::fk::forward_kinematics;
use posecast_proto::testing::arb_quat;
use posecast_proto::{Skeleton, Transform};
use posecast_rigs::asset::{Asset, SourceFormat};
use posecast_rigs::clip::{Clip, Interpolation, RotationChannel, Track};
use posecast_rigs::rig::{
    Normalised, PipelineOptions, RigView, adjust_bind, normalise, retarget, simplify,
};
use proptest::prelude::*;
use rig_support::builtin;

/// The largest difference allowed, degrees.
const MAX_DEGREES: f32 = 0.05;

/// `asset` with its rest rotations held the BVH way: rest rotations identity (the offsets
/// unchanged), inverse binds those of the identity pose, no mesh (it was bound in another
/// pose), every clip's rotations as they were (absolute, so the motion is unchanged).
fn as_bvh(mut asset: Asset) -> Asset {
    let sk = &asset.skeleton;
    let n = sk.len();
    for clip in &mut asset.clips {
        for j in 0..n {
            if !clip.animates_rotation(j) {
                // The joint kept its rest rotation; as a BVH channel it must say so (stored
                // so that the joint's channel map gives it back).
                let map = clip.channels()[j].map;
                let q = map.rot_pre.inverse() * sk.rest()[j].rotation * map.rot_post.inverse();
                let track = Track::new(
                    Interpolation::Linear,
                    vec![clip.start(), clip.end().max(clip.start() + 1e-3)],
                    vec![q, q],
                )
                .unwrap();
                let mut ch = clip.channels()[j].clone();
                ch.rotation = Some(RotationChannel::Keys(track));
                clip.set_channels(j, ch);
            }
        }
    }
    let rest: Vec<Transform> = sk
        .rest()
        .iter()
        .map(|t| Transform {
            rotation: Quat::IDENTITY,
            ..*t
        })
        .collect();
    let mut world = vec![Mat4::IDENTITY; n];
    forward_kinematics(sk, &rest, &mut world);
    asset.skeleton = Skeleton::new(
        sk.names().to_vec(),
        sk.parents().to_vec(),
        rest,
        world.iter().map(Mat4::inverse).collect(),
    )
    .unwrap();
    asset.meshes.clear();
    asset.source.format = SourceFormat::Bvh;
    asset
}

/// The reference rig: the built-in avatar with its bind simplified (rest = bind, so identity
/// rotations are its T-pose), and the clips that animate every joint.
fn reference() -> Asset {
    let (a, _, _) = simplify(builtin()).unwrap();
    a
}

fn world_positions(n: &Normalised, clip: Option<&Clip>, t: f32) -> Vec<Vec3> {
    let sk = &n.asset.skeleton;
    let mut locals: Vec<Transform> = sk
        .rest()
        .iter()
        .map(|r| Transform {
            rotation: Quat::IDENTITY,
            ..*r
        })
        .collect();
    if let Some(c) = clip {
        let rest = locals.clone();
        c.sample(t, &rest, &mut locals);
    }
    let mut world = vec![Mat4::IDENTITY; sk.len()];
    forward_kinematics(sk, &locals, &mut world);
    world.iter().map(|w| w.w_axis.truncate()).collect()
}

/// The angle between two vectors, degrees (`atan2(|a×b|, a·b)`: exact near 0, where f32
/// `acos` cannot resolve less than 0.03°).
fn angle(a: Vec3, b: Vec3) -> f32 {
    a.cross(b).length().atan2(a.dot(b)).to_degrees()
}

/// The largest angle between the same segment (parent → joint) of two poses of one skeleton,
/// degrees, over segments longer than 1 mm.
fn worst_segment(parents: &[Option<usize>], a: &[Vec3], b: &[Vec3]) -> f32 {
    let mut worst = 0.0f32;
    for (j, p) in parents.iter().enumerate() {
        if let Some(p) = *p {
            let (da, db) = (a[j] - a[p], b[j] - b[p]);
            if da.length() > 1e-3 {
                worst = worst.max(angle(da, db));
            }
        }
    }
    worst
}

/// Compares a variant with the reference: the neutral pose (every segment, and every joint's
/// position within 1e-4 of the height), a clip retargeted onto each of them, and each one's
/// clip retargeted onto the built-in avatar. Returns the worst angles (neutral, onto, from).
fn compare(reference: &Normalised, variant: &Normalised, other: &Normalised) -> (f32, f32, f32) {
    let parents = reference.asset.skeleton.parents();
    let (pa, pb) = (
        world_positions(reference, None, 0.0),
        world_positions(variant, None, 0.0),
    );
    let neutral = worst_segment(parents, &pa, &pb);
    for (a, b) in pa.iter().zip(&pb) {
        assert!((*a - *b).length() < 1.75e-4, "neutral position {a} vs {b}");
    }
    // A clip of another rig retargeted onto each.
    let clip = &other.asset.clips[1];
    let on_a = retarget(RigView::from(other), clip, RigView::from(reference)).unwrap();
    let on_b = retarget(RigView::from(other), clip, RigView::from(variant)).unwrap();
    let mut onto = 0.0f32;
    for t in times(&on_a) {
        let (a, b) = (
            world_positions(reference, Some(&on_a), t),
            world_positions(variant, Some(&on_b), t),
        );
        onto = onto.max(worst_segment(parents, &a, &b));
    }
    // Each one's own clip retargeted onto the other rig.
    let from_a = retarget(
        RigView::from(reference),
        &reference.asset.clips[1],
        RigView::from(other),
    )
    .unwrap();
    let from_b = retarget(
        RigView::from(variant),
        &variant.asset.clips[1],
        RigView::from(other),
    )
    .unwrap();
    let mut own = 0.0f32;
    for t in times(&reference.asset.clips[1]) {
        let (a, b) = (
            world_positions(reference, Some(&reference.asset.clips[1]), t),
            world_positions(variant, Some(&variant.asset.clips[1]), t),
        );
        own = own.max(worst_segment(parents, &a, &b));
    }
    assert!(
        own <= MAX_DEGREES,
        "the variant's own motion differs by {own} deg"
    );
    let mut from = 0.0f32;
    for t in times(&from_a) {
        let (a, b) = (
            world_positions(other, Some(&from_a), t),
            world_positions(other, Some(&from_b), t),
        );
        from = from.max(worst_segment(other.asset.skeleton.parents(), &a, &b));
    }
    (neutral, onto, from)
}

fn random_rotations() -> impl Strategy<Value = Vec<Quat>> {
    prop::collection::vec(arb_quat(), rig_support::builtin().skeleton.len())
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 12, ..ProptestConfig::default() })]

    #[test]
    fn random_rest_rotations_change_nothing(v in random_rotations()) {
        let base = reference();
        let other = normalise(builtin(), &PipelineOptions::default()).unwrap();
        let (turned, _, _) = adjust_bind(base.clone(), &v).unwrap();
        let keep_frames = PipelineOptions { simplify: false, ..PipelineOptions::default() };
        let cases = [
            ("glTF-like", base.clone(), turned.clone(), PipelineOptions::default()),
            ("glTF-like, not simplified", base.clone(), turned.clone(), keep_frames),
            ("BVH-like", as_bvh(base), as_bvh(turned), PipelineOptions::default()),
        ];
        for (what, a, b, options) in cases {
            let na = normalise(a, &PipelineOptions::default()).unwrap();
            let nb = normalise(b, &options).unwrap();
            prop_assert!(nb.neutral_pose.is_some(), "{what}: {:?}", nb.steps);
            let (neutral, onto, from) = compare(&na, &nb, &other);
            println!("{what}: neutral {neutral:.4} deg, onto {onto:.4} deg, from {from:.4} deg");
            prop_assert!(neutral <= MAX_DEGREES, "{what}: neutral pose differs by {neutral} deg");
            prop_assert!(onto <= MAX_DEGREES, "{what}: retargeted onto it differs by {onto} deg");
            prop_assert!(from <= MAX_DEGREES, "{what}: retargeted from it differs by {from} deg");
        }
    }
}

/// The H-Anim pose the alignment promises, on the crumpled BVH-like rig: clavicles along ±X,
/// the shoulder line along X, upper and lower arms and legs along −Y, spine along +Y, feet
/// along +Z.
#[test]
fn every_mapped_segment_is_aligned_from_a_crumpled_rest_pose() {
    let v: Vec<Quat> = (0..reference().skeleton.len())
        .map(|j| Quat::from_euler(glam::EulerRot::XYZ, 0.7 * j as f32, 1.3, -0.4 * j as f32))
        .collect();
    let (turned, _, _) = adjust_bind(reference(), &v).unwrap();
    let n = normalise(as_bvh(turned), &PipelineOptions::default()).unwrap();
    let pos = world_positions(&n, None, 0.0);
    let j = |name: &str| {
        n.hanim
            .iter()
            .position(|h| h.as_deref() == Some(name))
            .unwrap()
    };
    let seg = |a: &str, b: &str| pos[j(b)] - pos[j(a)];
    let mut checks = vec![
        ("shoulder line", seg("r_shoulder", "l_shoulder"), Vec3::X),
        ("spine", seg("vl5", "vt10"), Vec3::Y),
        ("neck", seg("vc4", "skullbase"), Vec3::Y),
    ];
    for (s, lateral) in [("l", Vec3::X), ("r", Vec3::NEG_X)] {
        let f = |p: &str| format!("{s}_{p}");
        checks.push((
            "clavicle",
            seg(&f("sternoclavicular"), &f("shoulder")),
            lateral,
        ));
        checks.push(("upper arm", seg(&f("shoulder"), &f("elbow")), Vec3::NEG_Y));
        checks.push(("forearm", seg(&f("elbow"), &f("wrist")), Vec3::NEG_Y));
        checks.push(("thigh", seg(&f("hip"), &f("knee")), Vec3::NEG_Y));
        checks.push(("shank", seg(&f("knee"), &f("ankle")), Vec3::NEG_Y));
        checks.push(("foot", seg(&f("ankle"), &f("midtarsal")), Vec3::Z));
    }
    for (what, got, want) in checks {
        let e = angle(got, want);
        assert!(e < MAX_DEGREES, "{what}: {e} deg from {want}");
    }
}

fn times(c: &Clip) -> Vec<f32> {
    (0..=20)
        .map(|i| c.start() + c.duration() * i as f32 / 20.0)
        .collect()
}
