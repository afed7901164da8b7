//! Seed 002: every value set on a DOF is clamped to its limits — by a clip as well as by a
//! command. A clip that drives a DOF past its limits streams the clamped rotation.
//!
//! Regression: clip values were streamed unclamped (a Y limit of −0.66..−0.66 streamed 0.05)
//! while `get_joint` reported −0.66 next to the contradicting rotation.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use glam::{EulerRot, Quat};
use posecast_proto::msg::SceneId;
use posecast_server::config::Config;
use posecast_server::control;
use posecast_server::import::files::FileSet;
use posecast_server::state::Services;

const SKEL: &str = "balljoint root { offset 0 1 0 \
    balljoint elbow { offset 0.3 0 0 rotxlimit -1 1 rotylimit -0.66 -0.66 rotzlimit 0 0.2 } }";

/// root tx ty tz rx ry rz, elbow rx ry rz: the elbow's X within limits (0.4), Y at 0.05
/// (limit −0.66..−0.66), Z at 0.9 (limit 0..0.2).
fn anim() -> String {
    let values = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.4, 0.05, 0.9];
    let mut s = format!("animation {{\n range 0 1\n numchannels {}\n", values.len());
    for v in values {
        s += &format!(
            " channel {{\n  extrapolate constant constant\n  keys 1 {{\n   0 {v} linear linear\n  }}\n }}\n"
        );
    }
    s + "}\n"
}

#[tokio::test]
async fn clip_values_are_clamped_to_dof_limits() {
    let state = Services::new(Config::default());
    let mut set = FileSet::new();
    set.insert("arm.skel", SKEL.as_bytes().to_vec()).unwrap();
    set.insert("bend.anim", anim().into_bytes()).unwrap();
    for rig in posecast_server::library::prepare("arm", &set).unwrap() {
        state.world.library.insert(rig);
    }
    let rig = state.world.library.get("arm").unwrap();
    let clip = rig.clips[0].name().to_string();
    for json in [
        r#"{"op":"create_scene","scene":"s"}"#.to_string(),
        r#"{"op":"add_avatar","scene":"s","asset":"arm","avatar":"a"}"#.to_string(),
        format!(r#"{{"op":"play","avatar":"a","clip":"{clip}","fade":0}}"#),
    ] {
        control::execute(&state, &serde_json::from_str(&json).unwrap()).unwrap();
    }
    let scene = state.world.scene(&SceneId("s".into())).unwrap();
    scene.tick(1, 0.5, 0, 60);
    let elbow = rig.skeleton().find("elbow").unwrap();
    let limits = rig.limits[elbow].clone().unwrap();
    // The authored rotation with each value clamped by hand: R = Rz(0.2) · Ry(−0.66) · Rx(0.4)
    // (CSE169 applies X, then Y, then Z), mapped into the normalised rig.
    let authored = Quat::from_euler(EulerRot::ZYX, 0.2, -0.66, 0.4);
    let expected = (limits.pre * authored * limits.post).normalize();
    let streamed = scene.lock().avatars[0].locals[elbow].rotation;
    let angle = expected.angle_between(streamed).to_degrees();
    assert!(
        angle < 0.01,
        "streamed {streamed:?}, expected {expected:?} ({angle}°)"
    );
    // And get_joint's values agree with what streams.
    let info = control::execute(
        &state,
        &serde_json::from_str(r#"{"op":"get_joint","avatar":"a","joint":"elbow"}"#).unwrap(),
    )
    .unwrap();
    let posecast_proto::command::CommandResult::Joint(info) = info else {
        panic!("get_joint answered {info:?}");
    };
    let values: Vec<f64> = info.dofs.iter().map(|d| f64::from(d.value)).collect();
    for (got, want) in values.iter().zip([0.4, -0.66, 0.2]) {
        assert!((got - want).abs() < 1e-4, "{values:?}");
    }
}
