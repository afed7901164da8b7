//! The H-Anim neutral pose on the humanoid test rigs: after the default pipeline,
//! all-identity rotations put upper and lower arms and legs within 5° of −Y and the spine
//! within 10° of +Y, in world space; names map as expected.
//!
//! `cargo test -p posecast-server --test rig_hanim -- --nocapture` prints the angles.

// Helpers outside #[test] fns unwrap too: a failure there is a test failure.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod rig_support;

use glam::{Mat4, Quat, Vec3};
use posecast_proto::fk::forward_kinematics;
use posecast_rigs::asset::Asset;
use posecast_rigs::rig::names::HANIM_SPINE;
use posecast_rigs::rig::{Normalised, PipelineOptions, map_names, normalise};
use rig_support::{builtin, load};

fn humanoids() -> Vec<Asset> {
    let mut out = Vec::new();
    for rel in [
        "gltf/RiggedFigure/glTF-Binary/RiggedFigure.glb",
        "gltf/CesiumMan/glTF-Binary/CesiumMan.glb",
        "bvh/cmu/01_01.bvh",
    ] {
        out.extend(load(rel).into_iter().flatten());
    }
    out.push(builtin());
    out
}

/// World joint positions with every rotation identity (the neutral pose).
fn neutral_positions(asset: &Asset) -> Vec<Vec3> {
    let sk = &asset.skeleton;
    let locals: Vec<_> = sk
        .rest()
        .iter()
        .map(|t| posecast_proto::Transform {
            rotation: Quat::IDENTITY,
            ..*t
        })
        .collect();
    let mut world = vec![Mat4::IDENTITY; sk.len()];
    forward_kinematics(sk, &locals, &mut world);
    world.iter().map(|w| w.w_axis.truncate()).collect()
}

fn angle(a: Vec3, b: Vec3) -> f32 {
    a.normalize()
        .dot(b.normalize())
        .clamp(-1.0, 1.0)
        .acos()
        .to_degrees()
}

fn is_ancestor(asset: &Asset, a: usize, mut b: usize) -> bool {
    while let Some(p) = asset.skeleton.parents()[b] {
        if p == a {
            return true;
        }
        b = p;
    }
    false
}

/// Labelled angles, degrees.
type Angles = Vec<(String, f32)>;

/// (limb angles from −Y, spine angles from +Y).
fn hanim_errors(n: &Normalised) -> (Angles, Angles) {
    let pos = neutral_positions(&n.asset);
    let j = |name: &str| {
        n.hanim
            .iter()
            .position(|h| h.as_deref() == Some(name))
            .unwrap_or_else(|| panic!("{}: {name} not mapped", n.asset.name))
    };
    let mut limbs = Vec::new();
    for side in ["l", "r"] {
        for (a, b) in [
            ("shoulder", "elbow"),
            ("elbow", "wrist"),
            ("hip", "knee"),
            ("knee", "ankle"),
        ] {
            let (a, b) = (format!("{side}_{a}"), format!("{side}_{b}"));
            let d = pos[j(&b)] - pos[j(&a)];
            limbs.push((format!("{a}->{b}"), angle(d, Vec3::NEG_Y)));
        }
    }
    let spine: Vec<usize> = HANIM_SPINE
        .iter()
        .filter_map(|s| n.hanim.iter().position(|h| h.as_deref() == Some(*s)))
        .collect();
    let mut spines = Vec::new();
    for w in spine.windows(2) {
        let d = pos[w[1]] - pos[w[0]];
        if is_ancestor(&n.asset, w[0], w[1]) && d.length() > 1e-4 {
            let label = format!(
                "{}->{}",
                n.hanim[w[0]].as_deref().unwrap_or("?"),
                n.hanim[w[1]].as_deref().unwrap_or("?")
            );
            spines.push((label, angle(d, Vec3::Y)));
        }
    }
    (limbs, spines)
}

#[test]
fn hanim_neutral_pose_on_humanoid_rigs() {
    for asset in humanoids() {
        let name = asset.name.clone();
        let n =
            normalise(asset, &PipelineOptions::default()).unwrap_or_else(|e| panic!("{name}: {e}"));
        assert!(n.neutral_pose.is_some(), "{name}: {:?}", n.steps);
        let (limbs, spine) = hanim_errors(&n);
        let worst_limb = limbs.iter().fold(0.0f32, |m, l| m.max(l.1));
        let worst_spine = spine.iter().fold(0.0f32, |m, l| m.max(l.1));
        println!("{name}: steps {:?}", n.steps);
        println!("  limbs from -Y (deg): {limbs:.3?}");
        println!("  spine from +Y (deg): {spine:.3?}");
        println!("  worst limb {worst_limb:.4} deg, worst spine {worst_spine:.4} deg");
        assert!(worst_limb <= 5.0, "{name}: {limbs:?}");
        assert!(!spine.is_empty(), "{name}: no spine segment");
        assert!(worst_spine <= 10.0, "{name}: {spine:?}");
        // Facing +Z: the left hip is at +X.
        let pos = neutral_positions(&n.asset);
        let l = n
            .hanim
            .iter()
            .position(|h| h.as_deref() == Some("l_hip"))
            .unwrap();
        let r = n
            .hanim
            .iter()
            .position(|h| h.as_deref() == Some("r_hip"))
            .unwrap();
        assert!(pos[l].x > pos[r].x, "{name}: not facing +Z");
    }
}

#[test]
fn names_of_the_test_rigs() {
    let expect = |rel: &str, pairs: &[(&str, &str)]| {
        let Some(assets) = load(rel) else { return };
        let a = &assets[0];
        let m = map_names(&a.skeleton, None, &a.name).unwrap();
        println!("{rel}: unmapped {:?}", m.unmapped);
        for (joint, hanim) in pairs {
            let j = a
                .skeleton
                .find(joint)
                .unwrap_or_else(|| panic!("{rel}: no {joint}"));
            assert_eq!(m.hanim[j].as_deref(), Some(*hanim), "{rel}: {joint}");
        }
    };
    expect(
        "bvh/cmu/01_01.bvh",
        &[
            ("Hips", "humanoid_root"),
            ("LeftUpLeg", "l_hip"),
            ("RightLeg", "r_knee"),
            ("LeftFoot", "l_ankle"),
            ("LeftArm", "l_shoulder"),
            ("RightForeArm", "r_elbow"),
            ("LeftHand", "l_wrist"),
            ("LeftShoulder", "l_sternoclavicular"),
            ("Head", "skullbase"),
        ],
    );
    expect(
        "gltf/RiggedFigure/glTF-Binary/RiggedFigure.glb",
        &[
            ("torso_joint_1", "humanoid_root"),
            ("arm_joint_L_1", "l_shoulder"),
            ("arm_joint_L_2", "l_elbow"),
            ("arm_joint_R_3", "r_wrist"),
            ("leg_joint_L_1", "l_hip"),
            ("leg_joint_R_2", "r_knee"),
            ("leg_joint_L_3", "l_ankle"),
        ],
    );
    expect(
        "gltf/CesiumMan/glTF-Binary/CesiumMan.glb",
        &[
            ("Skeleton_torso_joint_1", "humanoid_root"),
            ("Skeleton_arm_joint_L__4_", "l_shoulder"),
            ("Skeleton_arm_joint_L__3_", "l_elbow"),
            ("Skeleton_arm_joint_L__2_", "l_wrist"),
            ("Skeleton_arm_joint_R", "r_shoulder"),
            ("Skeleton_arm_joint_R__3_", "r_wrist"),
            ("leg_joint_R_1", "r_hip"),
        ],
    );
}

#[test]
fn mapping_overrides_and_errors() {
    let a = builtin();
    let mut map = std::collections::BTreeMap::new();
    map.insert("l_wrist".to_owned(), String::new());
    let m = map_names(&a.skeleton, Some(&map), &a.name).unwrap();
    assert!(m.find("l_wrist").is_none());
    assert!(m.unmapped.contains(&"l_wrist".to_owned()));
    map.insert("nope".to_owned(), "l_hip".to_owned());
    assert!(map_names(&a.skeleton, Some(&map), &a.name).is_err());
    let mut dup = std::collections::BTreeMap::new();
    dup.insert("l_knee".to_owned(), "l_elbow".to_owned());
    dup.insert("r_knee".to_owned(), "l_elbow".to_owned());
    assert!(map_names(&a.skeleton, Some(&dup), &a.name).is_err());
}
