//! Extreme finite inputs to every command that takes a rotation, an angle (DOF values), a
//! placement (`place_avatar`, `add_avatar`'s position and rotation), a root-motion mode, a
//! time, a speed or a fade, interleaved with ticks at extreme clocks: every command either
//! answers `invalid_value` and changes nothing, or its effect is a finite pose. The scene
//! file written afterwards holds no non-finite value and restores in full.
//!
//! Regression: `[2e19, 0, 0, 0]` used to normalise (in f32) to zeros or NaN, was acknowledged
//! as `[null, null, null, null]`, stored as `null`, and the whole scene file was set aside at
//! the next start.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use posecast_proto::command::Command;
use posecast_proto::msg::{ErrorCode, SceneId};
use posecast_proto::testing::finite_f32s;
use posecast_server::config::Config;
use posecast_server::control;
use posecast_server::import::files::FileSet;
use posecast_server::state::Services;
use posecast_server::store::snapshot;
use proptest::prelude::*;
use std::sync::Arc;

/// A CSE169 rig with DOF limits on one joint and none on another.
const SKEL: &str = "balljoint root { offset 0 1 0 \
    balljoint knee { offset 0 -0.5 0 rotxlimit -2 0 rotylimit 0 0 rotzlimit -0.5 0.5 } \
    balljoint free { offset 0.2 0 0 } }";

fn world() -> (tokio::runtime::Runtime, Arc<Services>) {
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    let state = {
        let _enter = rt.enter();
        let state = Services::new(Config::default());
        state
            .world
            .library
            .insert(posecast_server::builtin::rig().unwrap());
        let mut set = FileSet::new();
        set.insert("jointed.skel", SKEL.as_bytes().to_vec())
            .unwrap();
        for rig in posecast_server::library::prepare("jointed", &set).unwrap() {
            state.world.library.insert(rig);
        }
        for json in [
            r#"{"op":"create_scene","scene":"s"}"#,
            r#"{"op":"add_avatar","scene":"s","asset":"avatar","avatar":"a","clip":"idle"}"#,
            r#"{"op":"add_avatar","scene":"s","asset":"jointed","avatar":"k"}"#,
        ] {
            control::execute(&state, &serde_json::from_str(json).unwrap()).unwrap();
        }
        state
    };
    (rt, state)
}

#[derive(Debug, Clone)]
enum Op {
    SetRotation(bool, usize, [f32; 4]),
    RotateLocal(bool, usize, [f32; 4]),
    RotateWorld(bool, usize, [f32; 4]),
    Dofs(Vec<f32>),
    Play(f32, f32, f32, bool),
    Place([f32; 3], [f32; 4], f32),
    AddPlaced([f32; 3], [f32; 4]),
    Seek(f32),
    SetSpeed(f32),
    Tick(f32),
}

fn quat() -> impl Strategy<Value = [f32; 4]> + Clone {
    prop_oneof![
        prop::array::uniform4(finite_f32s()),
        // The reported cases and their neighbours.
        Just([2e19, 0.0, 0.0, 0.0]),
        Just([3e38; 4]),
        Just([f32::MAX, -f32::MAX, f32::MAX, -f32::MAX]),
        Just([1e-30, 0.0, 0.0, 1e-30]),
    ]
}

/// Positions: any finite, and ones near the ±1e6 m bound.
fn position() -> impl Strategy<Value = [f32; 3]> {
    prop_oneof![
        prop::array::uniform3(finite_f32s()),
        prop::array::uniform3(-1.1e6f32..1.1e6),
        Just([1e6, -1e6, 1e6]),
    ]
}

fn op() -> impl Strategy<Value = Op> {
    let joint = (any::<bool>(), 0usize..3, quat());
    prop_oneof![
        joint.clone().prop_map(|(b, j, q)| Op::SetRotation(b, j, q)),
        joint.clone().prop_map(|(b, j, q)| Op::RotateLocal(b, j, q)),
        joint.prop_map(|(b, j, q)| Op::RotateWorld(b, j, q)),
        prop::collection::vec(finite_f32s(), 3).prop_map(Op::Dofs),
        (finite_f32s(), finite_f32s(), finite_f32s(), any::<bool>())
            .prop_map(|(a, b, c, d)| Op::Play(a, b, c, d)),
        (position(), quat(), finite_f32s()).prop_map(|(p, q, d)| Op::Place(p, q, d)),
        (position(), quat()).prop_map(|(p, q)| Op::AddPlaced(p, q)),
        finite_f32s().prop_map(Op::Seek),
        finite_f32s().prop_map(Op::SetSpeed),
        finite_f32s().prop_map(|d| Op::Tick(d.abs())),
    ]
}

fn command(op: &Op) -> Option<Command> {
    let joint = |builtin: bool, j: usize| {
        if builtin {
            ("a", ["humanoid_root", "l_knee", "r_elbow"][j])
        } else {
            ("k", ["root", "knee", "free"][j])
        }
    };
    let json = match op {
        Op::SetRotation(b, j, q) | Op::RotateLocal(b, j, q) | Op::RotateWorld(b, j, q) => {
            let name = match op {
                Op::SetRotation(..) => "set_joint_rotation",
                Op::RotateLocal(..) => "rotate_joint_local",
                _ => "rotate_joint_world",
            };
            let (avatar, joint) = joint(*b, *j);
            serde_json::json!({"op": name, "avatar": avatar, "joint": joint, "rotation": q})
        }
        Op::Dofs(v) => {
            serde_json::json!({"op": "set_joint_dofs", "avatar": "k", "joint": "knee", "values": v})
        }
        Op::Play(speed, start, fade, accumulate) => serde_json::json!({
            "op": "play", "avatar": "a", "clip": "walk", "speed": speed, "start": start, "fade": fade,
            "root_motion": if *accumulate { "accumulate" } else { "in_place" }
        }),
        Op::Place(position, rotation, duration) => serde_json::json!({
            "op": "place_avatar", "avatar": "a", "position": position, "rotation": rotation,
            "duration": duration
        }),
        Op::AddPlaced(position, rotation) => serde_json::json!({
            "op": "add_avatar", "scene": "s", "asset": "avatar", "avatar": "n",
            "position": position, "rotation": rotation
        }),
        Op::Seek(t) => serde_json::json!({"op": "seek", "avatar": "a", "time": t}),
        Op::SetSpeed(s) => serde_json::json!({"op": "set_speed", "avatar": "a", "speed": s}),
        Op::Tick(_) => return None,
    };
    Some(serde_json::from_value(json).unwrap())
}

/// Every avatar's pose and state is finite and every rotation a unit quaternion.
fn assert_finite(state: &Services, after: &Op) {
    let scene = state.world.scene(&SceneId("s".into())).unwrap();
    let info = scene.info();
    for a in &info.avatars {
        assert!(
            a.time.is_finite() && a.speed.is_finite(),
            "{a:?} after {after:?}"
        );
    }
    let mut s = scene.lock();
    for a in &mut s.avatars {
        for (j, t) in a.locals.iter().enumerate() {
            assert!(t.is_finite(), "{} joint {j}: {t:?} after {after:?}", a.id);
            assert!(
                (t.rotation.length() - 1.0).abs() < 1e-3,
                "{} joint {j}: {:?} after {after:?}",
                a.id,
                t.rotation
            );
        }
        assert!(a.world().iter().all(|m| m.is_finite()));
        let p = a.placing.current();
        assert!(
            posecast_proto::Placement::try_new(p.position.to_array(), p.rotation.to_array())
                .is_ok_and(|v| (v.rotation.dot(p.rotation).abs() - 1.0).abs() < 1e-3),
            "{} placement {p:?} after {after:?}",
            a.id
        );
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    #[test]
    fn extreme_finite_inputs_are_refused_or_give_finite_poses(ops in prop::collection::vec(op(), 1..24)) {
        let (rt, state) = world();
        let _enter = rt.enter();
        let scene = state.world.scene(&SceneId("s".into())).unwrap();
        let mut clock = 0.0f64;
        let mut seq = 0u64;
        for op in &ops {
            match command(op) {
                Some(c) => match control::execute(&state, &c).map(|r| r.to_value()) {
                    Ok(result) => {
                        // A rotation in the ack is four numbers (it used to be four nulls).
                        if let Some(q) = result.get("rotation") {
                            let q: Vec<f64> = q.as_array().unwrap().iter().filter_map(serde_json::Value::as_f64).collect();
                            prop_assert!(q.len() == 4, "{:?} acked {}", op, result);
                        }
                    }
                    Err(e) => prop_assert_eq!(e.code(), ErrorCode::InvalidValue, "{:?}: {}", op, e.to_string()),
                },
                None => {
                    if let Op::Tick(d) = op {
                        clock += f64::from(*d);
                    }
                    seq += 1;
                    scene.tick(seq, clock, 0, 60);
                }
            }
            assert_finite(&state, op);
            if matches!(op, Op::AddPlaced(..)) {
                // Keep the scene's two avatars for the restore check below.
                control::execute(&state, &serde_json::from_str(r#"{"op":"remove_avatar","avatar":"n"}"#).unwrap()).ok();
            }
        }
        // The stored file holds only finite values and restores in full.
        let file = snapshot::snapshot(&scene, 1_000_000);
        for a in &file.avatars {
            for q in a.overrides.values() {
                prop_assert!(posecast_proto::unit_quat(*q).is_some(), "{:?}", a);
            }
            if let Some(p) = &a.playback {
                prop_assert!(p.time.is_finite() && p.speed.is_finite(), "{:?}", a);
            }
        }
        let text = serde_json::to_string(&file).unwrap();
        let (parsed, dropped) = snapshot::parse_lenient(&serde_json::from_str(&text).unwrap()).unwrap();
        prop_assert!(dropped.is_empty(), "{dropped:?}");
        let (rt2, fresh) = world();
        let _enter2 = rt2.enter();
        control::execute(&fresh, &Command::DeleteScene { scene: SceneId("s".into()) }).unwrap();
        snapshot::restore(&fresh.world, &parsed, 1_000_000).unwrap();
        let again = snapshot::snapshot(&fresh.world.scene(&SceneId("s".into())).unwrap(), 1_000_000);
        prop_assert_eq!(again.avatars.len(), 2);
        for (x, y) in again.avatars.iter().zip(&file.avatars) {
            prop_assert_eq!(x.overrides.keys().collect::<Vec<_>>(), y.overrides.keys().collect::<Vec<_>>());
            prop_assert_eq!(x.playback.is_some(), y.playback.is_some());
        }
    }
}

/// The exact report: `[2e19, 0, 0, 0]` is a rotation by π about X, acknowledged as such.
#[test]
fn huge_quaternion_is_normalised_not_zeroed() {
    let (rt, state) = world();
    let _enter = rt.enter();
    for avatar_joint in [("a", "l_knee"), ("k", "free")] {
        let c: Command = serde_json::from_value(serde_json::json!({
            "op": "set_joint_rotation", "avatar": avatar_joint.0, "joint": avatar_joint.1,
            "rotation": [2e19, 0, 0, 0]
        }))
        .unwrap();
        let result = control::execute(&state, &c).unwrap().to_value();
        let q: Vec<f64> = result["rotation"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_f64().expect("a number, not null"))
            .collect();
        assert!(
            (q[0].abs() - 1.0).abs() < 1e-6 && q[1..].iter().all(|c| c.abs() < 1e-6),
            "{q:?}"
        );
    }
}
