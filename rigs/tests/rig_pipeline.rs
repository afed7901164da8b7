//! The default pipeline on every shared rig: the posed mesh and joints are unchanged (up to
//! the recorded world change), rotation maps convert authored rotations, options parse.
//!
//! `cargo test -p posecast-server --test rig_pipeline -- --nocapture` prints each rig's steps.

// Helpers outside #[test] fns unwrap too: a failure there is a test failure.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod rig_support;

use glam::Quat;
use posecast_rigs::rig::pipeline::ReorientFrame;
use posecast_rigs::rig::{NeutralPose, PipelineOptions, SignedAxis, normalise};
use rig_support::{all_rigs, builtin, deviation, load};

#[test]
fn default_pipeline_keeps_every_rig() {
    for asset in all_rigs() {
        let name = asset.name.clone();
        let n = normalise(asset.clone(), &PipelineOptions::default())
            .unwrap_or_else(|e| panic!("{name}: {e}"));
        let (r, s) = n.world_change;
        let d = deviation(&asset, &n.asset, |p| s * (r * p));
        println!(
            "{name}: deviation ({:.2e}, {:.2e}); {}",
            d.0,
            d.1,
            n.steps.join("; ")
        );
        assert!(d.0 <= 1e-4 && d.1 <= 1e-4, "{name}: {d:?}");
        assert_eq!(n.rotation_maps.len(), asset.skeleton.len());
        assert_eq!(n.hanim.len(), asset.skeleton.len());
        // The rotation maps convert the authored rest rotations to the normalised ones.
        for (j, (pre, post)) in n.rotation_maps.iter().enumerate() {
            let authored = asset.skeleton.rest()[j].rotation;
            let expected = (*pre * authored * *post).normalize();
            let actual = n.asset.skeleton.rest()[j].rotation;
            assert!(
                expected.dot(actual).abs() > 1.0 - 1e-4,
                "{name} joint {j}: {expected} vs {actual}"
            );
        }
    }
}

#[test]
fn bind_pose_of_z_up_gltf_becomes_y_up() {
    let Some(assets) = load("gltf/CesiumMan/glTF-Binary/CesiumMan.glb") else {
        return;
    };
    let n = normalise(assets[0].clone(), &PipelineOptions::default()).unwrap();
    let (lo, hi) = n.asset.meshes[0].mesh.bounds();
    let extent = hi - lo;
    assert!(extent.y > extent.z && extent.y > extent.x, "{extent}");
    assert!(n.steps.iter().any(|s| s.starts_with("re-orient")));
}

#[test]
fn options_parse_from_json_and_configure_steps() {
    let json = r#"{"simplify": false, "up_axis": {"up": "+z", "forward": "-y", "frame": "world"},
        "metres_per_unit": 0.01, "neutral": "keep", "name_map": {"l_hip": "l_hip"}}"#;
    let o: PipelineOptions = serde_json::from_str(json).unwrap();
    assert!(!o.simplify);
    assert_eq!(o.neutral, NeutralPose::Keep);
    let up = o.up_axis.unwrap();
    assert_eq!(
        (up.up, up.forward, up.frame),
        (
            SignedAxis::PosZ,
            Some(SignedAxis::NegY),
            Some(ReorientFrame::World)
        )
    );
    let d: PipelineOptions = serde_json::from_str("{}").unwrap();
    assert_eq!(d, PipelineOptions::default());
    assert!(serde_json::from_str::<PipelineOptions>(r#"{"simplfy": true}"#).is_err());

    let avatar = builtin();
    let n = normalise(avatar.clone(), &o).unwrap();
    let r = SignedAxis::rotation_to_y_up(SignedAxis::PosZ, Some(SignedAxis::NegY)).unwrap();
    assert!(n.world_change.0.dot(r).abs() > 1.0 - 1e-6);
    assert_eq!(n.world_change.1, 0.01);
    assert!(n.neutral_pose.is_none());
    let d = deviation(&avatar, &n.asset, |p| 0.01 * (r * p));
    assert!(d.0 <= 1e-4 && d.1 <= 1e-4, "{d:?}");
    // A rotation given directly.
    let q = Quat::from_rotation_y(0.5);
    let o = PipelineOptions {
        up_axis: Some(posecast_rigs::rig::UpAxisOverride {
            rotation: Some(q.to_array()),
            frame: Some(ReorientFrame::World),
            ..Default::default()
        }),
        neutral: NeutralPose::Keep,
        ..Default::default()
    };
    let n = normalise(avatar.clone(), &o).unwrap();
    let d = deviation(&avatar, &n.asset, |p| q * p);
    assert!(d.0 <= 1e-4, "{d:?}");
}

#[test]
fn hanim_on_a_non_humanoid_is_an_error_and_auto_keeps() {
    let Some(assets) = load("cse169/wasp.skel") else {
        return;
    };
    let wasp = assets[0].clone();
    let n = normalise(wasp.clone(), &PipelineOptions::default()).unwrap();
    assert!(n.neutral_pose.is_none());
    let o = PipelineOptions {
        neutral: NeutralPose::HAnim,
        ..Default::default()
    };
    assert!(normalise(wasp, &o).is_err());
}
