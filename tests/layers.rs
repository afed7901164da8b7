//! Clip layers (issue 29 goal 4): `play_layer` puts a clip over the avatar's clip on a joint
//! mask, replacing or adding; `stop_layer` fades it out; layers survive a restart. The
//! reference is the built-in rig's clips sampled here, composed by hand as the protocol
//! reference says (`Q ← slerp(Q, L, w)`, additive `Q ← Q · slerp(1, R⁻¹·L, w)`), against what
//! a JSON viewer decodes.

#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use common::child::Posecast;
use common::command_to;
use glam::Quat;
use posecast_client::net::Client;
use posecast_proto::Transform;
use posecast_proto::msg::{AvatarId, Encoding};
use serde_json::{Value, json};
use std::net::SocketAddr;

async fn ok(addr: SocketAddr, body: Value) -> Value {
    let (status, answer) = command_to(addr, &body.to_string()).await;
    assert_eq!(status, 200, "{body} → {answer}");
    answer["result"].clone()
}

/// The angle between two rotations, degrees.
fn angle(a: Quat, b: Quat) -> f32 {
    let d = a.inverse() * b;
    (2.0 * d.xyz().length().atan2(d.w.abs())).to_degrees()
}

/// The built-in rig's pose of `clip` at clip time `t`.
fn sample(rig: &posecast_server::rig::Rig, clip: &str, t: f32) -> Vec<Transform> {
    let clip = rig.clip(clip).unwrap();
    let rest = rig.skeleton().rest();
    let mut out = rest.to_vec();
    clip.sample(clip.start() + t, rest, &mut out);
    out
}

/// Waits until the viewer's latest pose of `avatar` has every joint's rotation within 0.01°
/// of `want`; fails with the worst joint when it never does.
async fn pose_becomes(viewer: &Client, names: &[String], want: &[Quat]) {
    let id = AvatarId("avatar".into());
    let worst = || {
        viewer.latest(&id).map_or((f32::INFINITY, 0), |p| {
            p.locals
                .iter()
                .zip(want)
                .map(|(l, w)| angle(l.rotation, *w))
                .enumerate()
                .fold(
                    (0.0f32, 0),
                    |acc, (j, e)| if e > acc.0 { (e, j) } else { acc },
                )
        })
    };
    let reached = common::wait_for(120.0, || worst().0 <= 0.01).await;
    let (e, j) = worst();
    assert!(reached, "joint {} is {e}° from the expected pose", names[j]);
}

#[tokio::test]
async fn layers_replace_on_their_mask_add_on_top_and_fade_out() {
    let server = common::server(30.0).await;
    let addr = server.addr;
    let rig = server.state.world.library.get("avatar").unwrap();
    let skeleton = rig.skeleton();
    let names = skeleton.names().to_vec();
    let rest = skeleton.rest();
    let viewer = common::client(&server, Encoding::Json).await;

    // The clip, held at 0.3 s; an arm layer (right clavicle down, less the hand) holding the
    // wave at 0.5 s; an additive half-weight nod of the head from the wave at 1.0 s.
    ok(
        addr,
        json!({"op": "play", "avatar": "avatar", "clip": "walk", "speed": 0, "start": 0.3, "fade": 0}),
    )
    .await;
    let base = sample(&rig, "walk", 0.3);
    let want_base: Vec<Quat> = base.iter().map(|t| t.rotation).collect();
    pose_becomes(&viewer, &names, &want_base).await;

    ok(
        addr,
        json!({"op": "play_layer", "avatar": "avatar", "layer": "arm", "clip": "wave",
               "mask": {"joints": ["r_sternoclavicular"], "except": ["r_wrist"]},
               "speed": 0, "start": 0.5, "fade": 0}),
    )
    .await;
    ok(
        addr,
        json!({"op": "play_layer", "avatar": "avatar", "layer": "nod", "clip": "wave",
               "mask": {"joints": ["skullbase"]}, "additive": true, "weight": 0.5,
               "speed": 0, "start": 1.0, "fade": 0}),
    )
    .await;
    let wave = sample(&rig, "wave", 0.5);
    let nod = sample(&rig, "wave", 1.0);
    let under = |j: usize, top: &str| {
        std::iter::successors(Some(j), |&k| skeleton.parents()[k]).any(|k| names[k] == top)
    };
    let mut arm = 0;
    let want: Vec<Quat> = (0..names.len())
        .map(|j| {
            if under(j, "r_sternoclavicular") && !under(j, "r_wrist") {
                arm += 1;
                wave[j].rotation
            } else if under(j, "skullbase") {
                let delta = rest[j].rotation.inverse() * nod[j].rotation;
                (base[j].rotation * Quat::IDENTITY.slerp(delta, 0.5)).normalize()
            } else {
                base[j].rotation
            }
        })
        .collect();
    assert!(
        arm >= 3,
        "the mask owns the clavicle, shoulder and elbow at least"
    );
    // The layers change the pose where they own joints (else this test proves nothing).
    let moved = (0..names.len())
        .map(|j| angle(want[j], base[j].rotation))
        .fold(0.0f32, f32::max);
    assert!(moved > 5.0, "the layers move a joint {moved}°");
    pose_becomes(&viewer, &names, &want).await;

    let state = ok(addr, json!({"op": "get_avatar", "avatar": "avatar"})).await;
    let layers = state["layers"].as_array().unwrap();
    assert_eq!(layers.len(), 2, "{state}");
    assert_eq!(layers[0]["layer"], "arm");
    assert_eq!(layers[0]["joints"], arm);
    assert_eq!(layers[1]["additive"], true);

    // Refusals name the problem and change nothing.
    for (body, why) in [
        (
            json!({"op": "play_layer", "avatar": "avatar", "layer": "x", "clip": "wave",
                   "mask": {"joints": ["no_such_joint"]}}),
            "no joint \"no_such_joint\"",
        ),
        (
            json!({"op": "play_layer", "avatar": "avatar", "layer": "x", "clip": "wave",
                   "weight": 1.5}),
            "outside [0, 1]",
        ),
        (
            json!({"op": "play_layer", "avatar": "avatar", "layer": "x", "clip": "nope"}),
            "no clip nope",
        ),
        (
            json!({"op": "stop_layer", "avatar": "avatar", "layer": "x"}),
            "no layer \"x\"",
        ),
    ] {
        let (status, answer) = command_to(addr, &body.to_string()).await;
        assert_ne!(status, 200, "{body} must be refused");
        assert!(
            answer["message"].as_str().unwrap().contains(why),
            "{answer}"
        );
    }
    let again = ok(addr, json!({"op": "get_avatar", "avatar": "avatar"})).await;
    assert_eq!(again["layers"].as_array().unwrap().len(), 2, "{again}");

    // At most MAX_LAYERS.
    for k in 2..posecast_proto::command::MAX_LAYERS {
        ok(
            addr,
            json!({"op": "play_layer", "avatar": "avatar", "layer": format!("l{k}"),
                   "clip": "wave", "weight": 0}),
        )
        .await;
    }
    let (status, answer) = command_to(
        addr,
        &json!({"op": "play_layer", "avatar": "avatar", "layer": "one_more", "clip": "wave"})
            .to_string(),
    )
    .await;
    assert_ne!(status, 200, "{answer}");

    // Stopping with no fade gives the joints back at once.
    ok(
        addr,
        json!({"op": "stop_layer", "avatar": "avatar", "layer": "arm", "fade": 0}),
    )
    .await;
    let no_arm: Vec<Quat> = (0..names.len())
        .map(|j| {
            if under(j, "skullbase") {
                want[j]
            } else {
                base[j].rotation
            }
        })
        .collect();
    pose_becomes(&viewer, &names, &no_arm).await;
}

/// Layers are kept with the scene: after a SIGKILL the arm layer is back at its clip time.
#[tokio::test]
async fn layers_survive_a_sigkill() {
    let data = tempfile::tempdir().unwrap();
    let start = || Posecast::on_data(data.path());
    let server = start();
    ok(
        server.addr,
        json!({"op": "play_layer", "avatar": "avatar", "layer": "arm", "clip": "wave",
               "mask": {"joints": ["r_shoulder"]}, "speed": 0, "start": 0.5, "fade": 0}),
    )
    .await;
    server.kill();
    let server = start();
    let state = ok(server.addr, json!({"op": "get_avatar", "avatar": "avatar"})).await;
    let layers = state["layers"].as_array().unwrap();
    assert_eq!(layers.len(), 1, "{state}");
    assert_eq!(layers[0]["layer"], "arm");
    assert_eq!(layers[0]["clip"], "wave");
    assert!(
        (layers[0]["time"].as_f64().unwrap() - 0.5).abs() < 1e-3,
        "{state}"
    );
    server.kill();
}

/// A live driver may own some joints (`drive … joints`) while the clip and its layers keep the
/// rest: the driver's right arm over the clip held still, a nod layer still on the head; a
/// mask naming no joint of the rig is refused.
#[tokio::test]
async fn a_driver_owns_its_joints_and_the_clip_keeps_the_rest() {
    use futures_util::SinkExt;
    use tokio_tungstenite::tungstenite::Message;
    let server = common::server(30.0).await;
    let addr = server.addr;
    let rig = server.state.world.library.get("avatar").unwrap();
    let skeleton = rig.skeleton();
    let names = skeleton.names().to_vec();
    let viewer = common::client(&server, Encoding::Json).await;
    ok(
        addr,
        json!({"op": "play", "avatar": "avatar", "clip": "walk", "speed": 0, "start": 0.3, "fade": 0}),
    )
    .await;
    let base = sample(&rig, "walk", 0.3);

    let mut driver = common::raw_at(addr, Encoding::Json, Some(common::CONTROL)).await;
    let send = |v: Value| Message::Text(v.to_string().into());
    driver
        .send(send(
            json!({"type": "command", "id": 1, "command": {"op": "drive",
            "avatar": "avatar", "joints": {"joints": ["nowhere"]}}}),
        ))
        .await
        .unwrap();
    let refused = common::next_of_type(&mut driver, "error").await;
    assert_eq!(refused["type"], "error", "{refused}");
    assert!(
        refused["message"].as_str().unwrap().contains("nowhere"),
        "{refused}"
    );
    driver
        .send(send(
            json!({"type": "command", "id": 2, "command": {"op": "drive",
            "avatar": "avatar", "joints": {"joints": ["r_shoulder"]}}}),
        ))
        .await
        .unwrap();
    // The driver sends every joint at a quarter turn about X; only its arm takes them.
    let turn = Quat::from_rotation_x(std::f32::consts::FRAC_PI_2);
    let rotations: serde_json::Map<String, Value> = names
        .iter()
        .map(|n| (n.clone(), json!(turn.to_array())))
        .collect();
    let under = |j: usize, top: &str| {
        std::iter::successors(Some(j), |&k| skeleton.parents()[k]).any(|k| names[k] == top)
    };
    let want: Vec<Quat> = (0..names.len())
        .map(|j| {
            if under(j, "r_shoulder") {
                turn
            } else {
                base[j].rotation
            }
        })
        .collect();
    let pose = json!({"type": "pose", "avatar": "avatar", "rotations": rotations});
    let id = AvatarId("avatar".into());
    let worst = || {
        viewer.latest(&id).map_or(f32::INFINITY, |p| {
            p.locals
                .iter()
                .zip(&want)
                .map(|(l, w)| angle(l.rotation, *w))
                .fold(0.0, f32::max)
        })
    };
    // Poses keep coming (a drive ends when its driver goes silent) until the viewer sees them.
    let mut reached = false;
    for _ in 0..1200 {
        driver.send(send(pose.clone())).await.unwrap();
        if worst() <= 0.01 {
            reached = true;
            break;
        }
        tokio::time::sleep(std::time::Duration::from_millis(100)).await;
    }
    assert!(
        reached,
        "the arm is the driver's, the rest the clip's: {}°",
        worst()
    );
}
