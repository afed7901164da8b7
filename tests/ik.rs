//! IK goals end to end (`set_ik_goal`, `clear_ik_goal`, `look_at`; seed 002): commands over
//! REST, poses as a viewer decodes them. The reference is the target the command gave, and
//! for a goal relative to another avatar that avatar's joint in the same decoded frame.

#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use common::command_to;
use glam::{Mat4, Quat, Vec3};
use posecast_client::net::{Client, ClientOptions};
use posecast_proto::fk::forward_kinematics;
use posecast_proto::msg::AvatarId;
use posecast_proto::quant::MAX_ERROR_DEGREES;
use posecast_server::auth::{Role, Secret, TokenRule};
use serde_json::{Value, json};
use std::net::SocketAddr;

/// A control token limited to avatar `far`.
const LIMITED: &str = "limited-to-far-token";

/// The solver's bound (1 mm) plus what the wire's 48-bit rotations may move a wrist: each of
/// the ~8 joints from the root to the wrist off by ≤ 0.0075°, at most 1.5 m from it.
const POSITION_BOUND: f32 = 1e-3 + 8.0 * 1.5 * (MAX_ERROR_DEGREES as f32).to_radians();

async fn ok(addr: SocketAddr, body: Value) -> Value {
    let (status, answer) = command_to(addr, &body.to_string()).await;
    assert_eq!(status, 200, "{body} → {answer}");
    answer["result"].clone()
}

async fn refused(addr: SocketAddr, body: Value) -> (u16, String) {
    let (status, answer) = command_to(addr, &body.to_string()).await;
    assert_ne!(status, 200, "{body} must be refused: {answer}");
    (
        status,
        answer["code"].as_str().unwrap_or_default().to_owned(),
    )
}

async fn viewer(addr: SocketAddr) -> Client {
    let mut options = ClientOptions::new(format!("ws://{addr}/ws"), "default");
    options.reconnect = false;
    Client::connect(options).await.unwrap()
}

/// The scene-space matrices of every avatar's joints in one decoded frame at least `ticks`
/// ticks after now (all avatars from the same tick), by avatar.
async fn frame_after(client: &Client, ticks: u64) -> Vec<(String, Vec<String>, Vec<Mat4>)> {
    let mut events = client.events();
    let start = loop {
        if let Some(seq) = client
            .avatars()
            .iter()
            .filter_map(|a| a.latest.as_ref().map(|p| p.seq))
            .max()
        {
            break seq;
        }
        let _ = events.recv().await;
    };
    loop {
        let avatars = client.avatars();
        let seqs: Vec<u64> = avatars
            .iter()
            .filter_map(|a| a.latest.as_ref().map(|p| p.seq))
            .collect();
        if seqs.len() == avatars.len() && seqs.iter().all(|&s| s >= start + ticks && s == seqs[0]) {
            return avatars
                .iter()
                .map(|a| {
                    let pose = a.latest.as_ref().unwrap();
                    let mut world = vec![Mat4::IDENTITY; a.skeleton.len()];
                    forward_kinematics(&a.skeleton, &pose.placed_locals(&a.skeleton), &mut world);
                    (
                        a.description.id.0.clone(),
                        a.skeleton.names().to_vec(),
                        world,
                    )
                })
                .collect();
        }
        let _ = events.recv().await;
    }
}

fn joint(frame: &[(String, Vec<String>, Vec<Mat4>)], avatar: &str, name: &str) -> Mat4 {
    let (_, names, world) = frame.iter().find(|(id, _, _)| id == avatar).unwrap();
    world[names.iter().position(|n| n == name).unwrap()]
}

fn position(m: Mat4) -> Vec3 {
    m.w_axis.truncate()
}

fn rotation(m: Mat4) -> Quat {
    m.to_scale_rotation_translation().1
}

fn degrees(a: Quat, b: Quat) -> f64 {
    let d = a.as_dquat().inverse() * b.as_dquat();
    (2.0 * d.xyz().length().atan2(d.w.abs())).to_degrees()
}

/// A hand reaches a point with a rotation while the avatar walks (the goal over the clip),
/// placed and turned in the scene; clearing the goal gives the clip's pose back exactly.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_hand_reaches_a_point_and_lets_go() {
    let server = common::server(60.0).await;
    let addr = server.addr;
    ok(
        addr,
        json!({"op": "place_avatar", "avatar": "avatar", "position": [1.0, 0.0, -0.5],
        "rotation": [0.0, 0.38268343, 0.0, 0.9238795]}),
    )
    .await;
    ok(
        addr,
        json!({"op": "play", "avatar": "avatar", "clip": "walk", "fade": 0}),
    )
    .await;
    ok(addr, json!({"op": "pause", "avatar": "avatar"})).await;
    let client = viewer(addr).await;
    let before = frame_after(&client, 2).await;
    let shoulder = position(joint(&before, "avatar", "l_shoulder"));
    let wrist_before = joint(&before, "avatar", "l_wrist");

    // In front of the shoulder, within the arm's reach; the palm turned.
    let target = shoulder + Vec3::new(0.15, -0.25, 0.3);
    let turned = Quat::from_rotation_y(0.7) * Quat::from_rotation_x(-0.4);
    ok(
        addr,
        json!({"op": "set_ik_goal", "avatar": "avatar", "effector": "l_wrist",
        "position": target.to_array(), "rotation": turned.to_array(), "pole": [3.0, 0.0, -3.0]}),
    )
    .await;
    let state = ok(addr, json!({"op": "get_avatar", "avatar": "avatar"})).await;
    assert_eq!(state["ik_goals"], json!(["l_wrist"]), "{state}");
    for _ in 0..3 {
        let frame = frame_after(&client, 2).await;
        let wrist = joint(&frame, "avatar", "l_wrist");
        let off = position(wrist).distance(target);
        println!(
            "wrist {off:.2e} m from the goal, {:.4}° from its rotation",
            degrees(rotation(wrist), turned)
        );
        assert!(off <= POSITION_BOUND, "wrist {off} m from the goal");
        assert!(degrees(rotation(wrist), turned) <= 0.5, "wrist rotation");
        // The rest of the body keeps the clip's pose.
        let knee = joint(&frame, "avatar", "l_knee");
        assert!(position(knee).distance(position(joint(&before, "avatar", "l_knee"))) < 1e-4);
    }

    ok(
        addr,
        json!({"op": "clear_ik_goal", "avatar": "avatar", "effector": "l_wrist", "fade": 0.5}),
    )
    .await;
    // Half way through the fade the wrist is on its way back: away from both ends.
    let during = position(joint(&frame_after(&client, 15).await, "avatar", "l_wrist"));
    let (to_goal, to_clip) = (
        during.distance(target),
        during.distance(position(wrist_before)),
    );
    println!("during the fade: {to_goal:.3} m from the goal, {to_clip:.3} m from the clip");
    assert!(
        to_goal > 0.02 && to_clip > 0.02,
        "the goal fades out, not snaps"
    );
    // After it, the clip's pose exactly.
    let after = frame_after(&client, 30).await;
    let wrist = joint(&after, "avatar", "l_wrist");
    assert!(
        position(wrist).distance(position(wrist_before)) < 1e-5,
        "back to the clip's wrist"
    );
    let state = ok(addr, json!({"op": "get_avatar", "avatar": "avatar"})).await;
    assert!(state.get("ik_goals").is_none(), "{state}");
}

/// Out of reach: the arm points straight at the goal, finite, and stays still while the goal
/// is still.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_unreachable_goal_is_pointed_at_without_jitter() {
    let server = common::server(60.0).await;
    let addr = server.addr;
    ok(addr, json!({"op": "stop", "avatar": "avatar"})).await;
    let client = viewer(addr).await;
    let target = [3.0, 2.5, 4.0];
    ok(
        addr,
        json!({"op": "set_ik_goal", "avatar": "avatar", "effector": "r_wrist", "position": target}),
    )
    .await;
    let first = frame_after(&client, 2).await;
    let (s, e, w) = (
        position(joint(&first, "avatar", "r_shoulder")),
        position(joint(&first, "avatar", "r_elbow")),
        position(joint(&first, "avatar", "r_wrist")),
    );
    let to_goal = (Vec3::from_array(target) - s).normalize();
    assert!(
        (w - s).normalize().angle_between(to_goal).to_degrees() < 0.1,
        "pointed at the goal"
    );
    assert!(
        (e - s).normalize().angle_between(to_goal).to_degrees() < 0.5,
        "the arm straight"
    );
    let later = frame_after(&client, 10).await;
    assert!(
        position(joint(&later, "avatar", "r_wrist")).distance(w) < 1e-5,
        "still"
    );
}

/// A hand on another avatar's shoulder follows it when it moves.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_goal_relative_to_another_avatar_follows_it() {
    let server = common::server(60.0).await;
    let addr = server.addr;
    ok(addr, json!({"op": "stop", "avatar": "avatar"})).await;
    // A friend in front, facing the avatar.
    ok(
        addr,
        json!({"op": "add_avatar", "scene": "default", "asset": "avatar", "avatar": "friend",
        "position": [0.0, 0.0, 0.5], "rotation": [0.0, 1.0, 0.0, 0.0]}),
    )
    .await;
    ok(
        addr,
        json!({"op": "play", "avatar": "friend", "clip": "idle"}),
    )
    .await;
    let offset = Vec3::new(0.0, 0.08, 0.0);
    ok(
        addr,
        json!({"op": "set_ik_goal", "avatar": "avatar", "effector": "r_wrist",
        "position": offset.to_array(), "relative_to": {"avatar": "friend", "joint": "l_shoulder"}}),
    )
    .await;
    let client = viewer(addr).await;
    let mut worst = 0.0f32;
    for step in 0..6 {
        if step == 3 {
            ok(
                addr,
                json!({"op": "place_avatar", "avatar": "friend", "position": [0.1, 0.0, 0.45],
                "rotation": [0.0, 0.9961947, 0.0, 0.08715574]}),
            )
            .await;
        }
        let frame = frame_after(&client, 3).await;
        let goal = joint(&frame, "friend", "l_shoulder").transform_point3(offset);
        let off = position(joint(&frame, "avatar", "r_wrist")).distance(goal);
        worst = worst.max(off);
    }
    println!("hand on the shoulder: worst {worst:.2e} m");
    assert!(
        worst <= POSITION_BOUND,
        "the hand left the shoulder by {worst} m"
    );
}

/// The head turns to face a point: its forward axis (+Z) through the target.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn look_at_turns_the_head_to_the_target() {
    let server = common::server(60.0).await;
    let addr = server.addr;
    let target = Vec3::new(-1.5, 2.2, 1.0);
    ok(
        addr,
        json!({"op": "look_at", "avatar": "avatar", "target": target.to_array()}),
    )
    .await;
    let client = viewer(addr).await;
    let frame = frame_after(&client, 2).await;
    let head = joint(&frame, "avatar", "skullbase");
    let forward = rotation(head) * Vec3::Z;
    let off = forward.angle_between(target - position(head)).to_degrees();
    assert!(off < 0.5, "the head looks {off}° off the target");
    let state = ok(addr, json!({"op": "get_avatar", "avatar": "avatar"})).await;
    assert_eq!(state["looking"], true);
    ok(
        addr,
        json!({"op": "look_at", "avatar": "avatar", "target": [0, 0, 0], "weight": 0}),
    )
    .await;
    let state = ok(addr, json!({"op": "get_avatar", "avatar": "avatar"})).await;
    assert!(
        state.get("looking").is_none(),
        "weight 0 ends the gaze: {state}"
    );
}

/// Bad goals get typed errors and change nothing.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_goals_are_refused_and_change_nothing() {
    let mut access = common::test_access();
    let mut limited = TokenRule::new("limited", Secret::new(LIMITED), Role::Control);
    limited.avatars = Some(vec![AvatarId("far".into())]);
    access.add(limited).unwrap();
    let server = common::server_with(60.0, access).await;
    let addr = server.addr;
    ok(addr, json!({"op": "create_scene", "scene": "elsewhere"})).await;
    ok(
        addr,
        json!({"op": "add_avatar", "scene": "elsewhere", "asset": "avatar", "avatar": "far"}),
    )
    .await;
    let goal = |extra: Value| {
        let mut body = json!({"op": "set_ik_goal", "avatar": "avatar", "effector": "l_wrist", "position": [0.3, 1.2, 0.3]});
        for (k, v) in extra.as_object().unwrap() {
            body[k] = v.clone();
        }
        body
    };
    for (body, code) in [
        (goal(json!({"position": [1e30, 0.0, 0.0]})), "invalid_value"),
        (goal(json!({"pole": [0.0, -1e7, 0.0]})), "invalid_value"),
        (
            goal(json!({"rotation": [0.0, 0.0, 0.0, 0.0]})),
            "invalid_value",
        ),
        (goal(json!({"weight": 1.5})), "invalid_value"),
        (goal(json!({"weight": -0.1})), "invalid_value"),
        (goal(json!({"effector": "no_such_joint"})), "unknown_joint"),
        (goal(json!({"effector": "humanoid_root"})), "invalid_value"),
        (
            goal(json!({"effector": "vc4", "chain": 1})),
            "invalid_value",
        ),
        (
            goal(json!({"effector": "vc4", "chain": 40})),
            "invalid_value",
        ),
        (
            goal(json!({"relative_to": {"avatar": "far", "joint": "l_shoulder"}})),
            "invalid_value",
        ),
        (
            goal(json!({"relative_to": {"avatar": "avatar", "joint": "nope"}})),
            "unknown_joint",
        ),
        (goal(json!({"avatar": "nobody"})), "unknown_avatar"),
        (
            json!({"op": "look_at", "avatar": "avatar", "target": [0.0, f32::MAX, 0.0]}),
            "invalid_value",
        ),
        (
            json!({"op": "clear_ik_goal", "avatar": "avatar", "effector": "nope"}),
            "unknown_joint",
        ),
        (
            json!({"op": "clear_ik_goal", "avatar": "avatar", "fade": -1.0}),
            "invalid_value",
        ),
    ] {
        let (_, got) = refused(addr, body.clone()).await;
        assert_eq!(got, code, "{body}");
    }
    let state = ok(addr, json!({"op": "get_avatar", "avatar": "avatar"})).await;
    assert!(
        state.get("ik_goals").is_none() && state.get("looking").is_none(),
        "{state}"
    );

    // A token limited to another avatar may not set goals on this one.
    let (status, body) = common::http_request(
        addr,
        Some(LIMITED),
        "POST",
        "/api/commands",
        "application/json",
        goal(json!({})).to_string().as_bytes(),
    )
    .await;
    assert_eq!(status, 403, "{body}");
}
