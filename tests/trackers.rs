//! Tracker driving end to end (issue 29 goal 2): `drive … trackers`, tracker poses as JSON and
//! binary messages, the body the server solves from them as viewers decode it (a binary and a
//! JSON subscriber, world matrices rebuilt from the streamed local rotations), bad trackers
//! refused with typed errors that change nothing, and `calibrate_trackers`.
//!
//! The reference is the built-in avatar's own skeleton: a tracker is its joint (`skullbase`,
//! `l_wrist`, …) in the scene's space, so trackers taken from the avatar's world transforms
//! in a pose it can take must be met — head and wrists (and hips and ankles) within 1 mm, the
//! head's and wrists' rotations within 0.5°, as an IK goal is.

#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use common::{Ws, command_to};
use futures_util::{SinkExt, StreamExt};
use glam::{Mat4, Quat, Vec3};
use posecast_client::net::{Client, ClientOptions};
use posecast_proto::Transform;
use posecast_proto::fk::forward_kinematics;
use posecast_proto::live::BinaryPose;
use posecast_proto::msg::Encoding;
use posecast_proto::quant::MAX_ERROR_DEGREES;
use posecast_server::rig::Rig;
use posecast_testkit::TestServer;
use serde_json::{Value, json};
use std::collections::BTreeMap;
use std::net::SocketAddr;
use std::time::Duration;
use tokio_tungstenite::tungstenite::Message;

const TICK_HZ: f32 = 60.0;
const AVATAR: &str = "avatar";

/// The solver's bound (1 mm) plus what the binary wire's 48-bit rotations may move a joint:
/// each of the ~8 joints from the root to a wrist off by ≤ 0.0075°, at most 1.5 m from it.
const POSITION_BOUND: f32 = 1e-3 + 8.0 * 1.5 * (MAX_ERROR_DEGREES as f32).to_radians();
/// The solver's bound for rotations (0.5°) plus the wire's, joint by joint down to a wrist.
const ANGLE_BOUND: f64 = 0.5 + 8.0 * MAX_ERROR_DEGREES;

/// A server with the built-in avatar, placed off the origin and turned, whose drives outlast
/// the test (one pose holds the trackers for as long as it runs).
async fn server() -> TestServer {
    let server = common::kit_builder(TICK_HZ)
        .configure(|c| c.drive_timeout = Duration::from_secs(600))
        .start()
        .await
        .unwrap();
    ok(
        server.addr,
        json!({"op": "place_avatar", "avatar": AVATAR, "position": placement().1.to_array(),
               "rotation": placement().0.to_array()}),
    )
    .await;
    server
}

/// The avatar's placement: turned 30° about +Y, half a metre to the side and one back.
fn placement() -> (Quat, Vec3) {
    (
        Quat::from_rotation_y(std::f32::consts::FRAC_PI_6),
        Vec3::new(0.5, 0.0, -1.0),
    )
}

fn placement_matrix() -> Mat4 {
    let (q, p) = placement();
    Mat4::from_rotation_translation(q, p)
}

async fn ok(addr: SocketAddr, body: Value) -> Value {
    let (status, answer) = command_to(addr, &body.to_string()).await;
    assert_eq!(status, 200, "{body} → {answer}");
    answer["result"].clone()
}

async fn viewer(addr: SocketAddr, encoding: Encoding) -> Client {
    viewer_of(addr, "default", encoding).await
}

async fn viewer_of(addr: SocketAddr, scene: &str, encoding: Encoding) -> Client {
    let mut options = ClientOptions::new(format!("ws://{addr}/ws"), scene);
    options.reconnect = false;
    options.encoding = encoding;
    Client::connect(options).await.unwrap()
}

/// The next text message of `ws` as JSON, skipping binary ones; fails after 120 s.
async fn next_json(ws: &mut Ws) -> Value {
    let deadline = tokio::time::Instant::now() + Duration::from_secs(120);
    loop {
        match tokio::time::timeout_at(deadline, ws.next()).await {
            Ok(Some(Ok(Message::Text(t)))) => return serde_json::from_str(&t).unwrap(),
            Ok(Some(Ok(_))) => {}
            other => panic!("no message: {other:?}"),
        }
    }
}

/// Sends command `command` as `id` over `ws`: its result, or its error's `(code, message)`.
async fn command(ws: &mut Ws, id: u64, command: Value) -> Result<Value, (String, String)> {
    let msg = json!({"type": "command", "id": id, "command": command});
    ws.send(Message::Text(msg.to_string().into()))
        .await
        .unwrap();
    loop {
        let v = next_json(ws).await;
        if v["id"] != id {
            continue;
        }
        return match v["type"].as_str() {
            Some("ack") => Ok(v["result"].clone()),
            Some("error") => Err(error_of(&v)),
            _ => continue,
        };
    }
}

fn error_of(v: &Value) -> (String, String) {
    (
        v["code"].as_str().unwrap_or_default().to_owned(),
        v["message"].as_str().unwrap_or_default().to_owned(),
    )
}

/// A driver connection that drives the avatar with `trackers`; returns it and the `drive`
/// answer.
async fn tracker_driver(server: &TestServer, trackers: &[&str]) -> (Ws, Value) {
    let mut ws = common::raw_at(server.addr, Encoding::Json, Some(common::CONTROL)).await;
    let info = command(
        &mut ws,
        1,
        json!({"op": "drive", "avatar": AVATAR, "trackers": trackers}),
    )
    .await
    .unwrap_or_else(|e| panic!("drive with {trackers:?}: {e:?}"));
    (ws, info)
}

/// A tracker transform in the scene's space.
type Target = (Vec3, Quat);

/// The scene-space transforms (placement included) of `joints` of `rig` with `rotations`
/// (local, by joint name; the others at the neutral pose, identity — not the rest pose, the
/// built-in avatar's T-pose) and the root lowered by `crouch`.
fn joint_transforms(
    rig: &Rig,
    rotations: &[(&str, Quat)],
    crouch: f32,
    joints: &[&str],
) -> BTreeMap<String, Target> {
    let sk = rig.skeleton();
    let mut locals: Vec<Transform> = sk
        .rest()
        .iter()
        .map(|t| Transform {
            rotation: Quat::IDENTITY,
            ..*t
        })
        .collect();
    for (name, q) in rotations {
        locals[sk.find(name).unwrap()].rotation = *q;
    }
    let root = sk.roots().next().unwrap();
    locals[root].translation.y -= crouch;
    let mut world = vec![Mat4::IDENTITY; sk.len()];
    forward_kinematics(sk, &locals, &mut world);
    joints
        .iter()
        .map(|name| {
            let m = placement_matrix() * world[sk.find(name).unwrap()];
            let (_, r, p) = m.to_scale_rotation_translation();
            ((*name).to_owned(), (p, r))
        })
        .collect()
}

/// The joint each standard tracker stands for.
fn joint_of(tracker: &str) -> &'static str {
    posecast_proto::trackers::STANDARD
        .iter()
        .find(|(t, _)| *t == tracker)
        .map(|(_, j)| *j)
        .unwrap()
}

/// A pose the built-in avatar can take: the hands raised in front of it (elbows bent, the
/// wrists turned; each hand about 20 cm forward of where it hangs), the head nodding. The
/// elbows bend well short of straight, so the arms reach their wrists from wherever the solved
/// spine puts the shoulders.
fn reaching() -> Vec<(&'static str, Quat)> {
    vec![
        ("l_shoulder", Quat::from_rotation_x(-0.35)),
        ("l_elbow", Quat::from_rotation_x(-0.9)),
        ("l_wrist", Quat::from_rotation_y(0.4)),
        ("r_shoulder", Quat::from_rotation_x(-0.25)),
        ("r_elbow", Quat::from_rotation_x(-1.0)),
        ("r_wrist", Quat::from_rotation_z(-0.3)),
        ("skullbase", Quat::from_rotation_x(0.15)),
    ]
}

/// The tracker transforms of `trackers` from the avatar in `rotations`, crouched by `crouch`
/// (the feet stay on the floor: their trackers are the neutral ankles').
fn tracker_targets(
    rig: &Rig,
    trackers: &[&str],
    rotations: &[(&str, Quat)],
    crouch: f32,
) -> BTreeMap<String, Target> {
    let joints: Vec<&str> = trackers.iter().map(|t| joint_of(t)).collect();
    let body = joint_transforms(rig, rotations, crouch, &joints);
    let standing = joint_transforms(rig, &[], 0.0, &joints);
    trackers
        .iter()
        .map(|t| {
            let j = joint_of(t);
            let at = if t.ends_with("_foot") {
                standing[j]
            } else {
                body[j]
            };
            ((*t).to_owned(), at)
        })
        .collect()
}

fn json_pose(time_us: u64, trackers: &BTreeMap<String, Target>) -> Message {
    json_pose_of(AVATAR, time_us, trackers)
}

fn json_pose_of(avatar: &str, time_us: u64, trackers: &BTreeMap<String, Target>) -> Message {
    let trackers: serde_json::Map<String, Value> = trackers
        .iter()
        .map(|(name, (p, q))| {
            (
                name.clone(),
                json!({"position": p.to_array(), "rotation": q.to_array()}),
            )
        })
        .collect();
    Message::Text(
        json!({"type": "pose", "avatar": avatar, "time_us": time_us, "trackers": trackers})
            .to_string()
            .into(),
    )
}

fn binary_pose(info: &Value, time_us: u64, trackers: &BTreeMap<String, Target>) -> Message {
    let order: Vec<String> = serde_json::from_value(info["trackers"].clone()).unwrap();
    let pose = BinaryPose {
        avatar_num: u32::try_from(info["avatar_num"].as_u64().unwrap()).unwrap(),
        time_us: Some(time_us),
        root_position: None,
        rotations: Vec::new(),
        weights: Vec::new(),
        trackers: trackers
            .iter()
            .map(|(name, (p, q))| {
                let i = order.iter().position(|n| n == name).unwrap();
                (u8::try_from(i).unwrap(), *p, *q)
            })
            .collect(),
    };
    Message::Binary(pose.encode().into())
}

/// The avatar's joints in scene space as `client` decodes its newest pose (placement and
/// streamed root translation included), by name, and that pose's tick.
fn decoded(client: &Client, avatar: &str) -> Option<(u64, BTreeMap<String, Mat4>)> {
    let a = client
        .avatars()
        .into_iter()
        .find(|a| a.description.id.0 == avatar)?;
    let pose = a.latest.as_ref()?;
    let mut world = vec![Mat4::IDENTITY; a.skeleton.len()];
    forward_kinematics(&a.skeleton, &pose.placed_locals(&a.skeleton), &mut world);
    Some((
        pose.seq,
        a.skeleton.names().iter().cloned().zip(world).collect(),
    ))
}

fn degrees(a: Quat, b: Quat) -> f64 {
    let d = a.as_dquat().inverse() * b.as_dquat();
    (2.0 * d.xyz().length().atan2(d.w.abs())).to_degrees()
}

/// What the decoded joints miss `want` (joint → position, and rotation when given) by, or
/// `None` when every one is within the bounds.
fn misses(joints: &BTreeMap<String, Mat4>, want: &[(String, Target, bool)]) -> Option<String> {
    let mut out = Vec::new();
    for (joint, (p, q), rotation) in want {
        let (_, r, at) = joints[joint].to_scale_rotation_translation();
        let off = at.distance(*p);
        let angle = degrees(r, *q);
        if off > POSITION_BOUND || (*rotation && angle > ANGLE_BOUND) {
            out.push(format!("{joint} {:.2} mm, {angle:.3}° off", off * 1e3));
        }
    }
    (!out.is_empty()).then(|| out.join("; "))
}

/// The largest position and rotation errors of the decoded joints against `want`.
fn worst(joints: &BTreeMap<String, Mat4>, want: &[(String, Target, bool)]) -> String {
    let (mut off, mut angle) = (0.0f32, 0.0f64);
    for (joint, (p, q), rotation) in want {
        let (_, r, at) = joints[joint].to_scale_rotation_translation();
        off = off.max(at.distance(*p));
        if *rotation {
            angle = angle.max(degrees(r, *q));
        }
    }
    format!("worst {:.4} mm, {angle:.4}°", off * 1e3)
}

/// Waits until every subscriber's decoded pose meets `want`, then checks that it still does
/// for 10 more ticks (a still target gives a still body); fails the test after 120 s.
async fn reaches(clients: &[(&str, &Client)], want: &[(String, Target, bool)], label: &str) {
    reaches_of(clients, AVATAR, want, label).await;
}

/// [`reaches`] for avatar `avatar`.
async fn reaches_of(
    clients: &[(&str, &Client)],
    avatar: &str,
    want: &[(String, Target, bool)],
    label: &str,
) {
    for (subscriber, client) in clients {
        let label = format!("{label}, {subscriber} subscriber");
        let mut events = client.events();
        let deadline = tokio::time::Instant::now() + Duration::from_secs(120);
        let mut first_met: Option<u64> = None;
        let mut last = String::from("no pose yet");
        loop {
            if let Some((seq, joints)) = decoded(client, avatar) {
                match misses(&joints, want) {
                    None => {
                        let first = *first_met.get_or_insert(seq);
                        if seq >= first + 10 {
                            println!("{label}: {}", worst(&joints, want));
                            break;
                        }
                    }
                    Some(m) if first_met.is_some() => {
                        panic!("{label}: met at tick {first_met:?}, then at tick {seq}: {m}")
                    }
                    Some(m) => last = m,
                }
            }
            assert!(
                tokio::time::Instant::now() < deadline,
                "{label}: the solved body never met its trackers: {last}"
            );
            let _ = tokio::time::timeout_at(deadline, events.recv()).await;
        }
    }
}

/// `want` for each tracker: its joint at the tracker's transform (rotation checked for the
/// hands and the head, whose rotations the solve gives their joints).
fn wanted(targets: &BTreeMap<String, Target>) -> Vec<(String, Target, bool)> {
    targets
        .iter()
        .map(|(t, at)| {
            (
                joint_of(t).to_owned(),
                *at,
                t.ends_with("_hand") || t == "head",
            )
        })
        .collect()
}

/// Drives the avatar with `trackers` (JSON or binary poses) at the avatar's own joints in
/// the reaching pose, crouched by `crouch`; every subscriber (binary and JSON) must see the
/// solved body meet them.
async fn drive_and_reach(trackers: &[&str], binary: bool, crouch: f32) {
    let server = server().await;
    let rig = server.rig(AVATAR).unwrap();
    let subscribers = [
        viewer(server.addr, Encoding::Binary).await,
        viewer(server.addr, Encoding::Json).await,
    ];
    let (mut ws, info) = tracker_driver(&server, trackers).await;
    let names: Vec<&str> = info["trackers"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_str().unwrap())
        .collect();
    assert_eq!(names, trackers, "{info}");
    let targets = tracker_targets(&rig, trackers, &reaching(), crouch);
    // The hands are raised in front of the body: about 20 cm forward of where they hang.
    let hanging = joint_transforms(&rig, &[], 0.0, &["l_wrist"]);
    let forward = placement().0 * Vec3::Z;
    let raised = (targets["l_hand"].0 - hanging["l_wrist"].0).dot(forward);
    assert!((0.15..0.35).contains(&raised), "{raised}");
    let pose = if binary {
        binary_pose(&info, 1000, &targets)
    } else {
        json_pose(1000, &targets)
    };
    ws.send(pose).await.unwrap();
    let clients = [("binary", &subscribers[0]), ("JSON", &subscribers[1])];
    let label = format!("{trackers:?} (binary poses: {binary})");
    reaches(&clients, &wanted(&targets), &label).await;
    // No error came for the pose.
    let err = tokio::time::timeout(Duration::from_millis(200), next_json(&mut ws)).await;
    assert!(err.is_err(), "{err:?}");
}

/// Three trackers (headset and controllers) as JSON poses: head and wrists where they are,
/// for a binary and a JSON subscriber.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn three_trackers_place_head_and_hands() {
    drive_and_reach(&["head", "l_hand", "r_hand"], false, 0.0).await;
}

/// Six trackers as JSON poses, the user crouching 6 cm: hips, head and hands lowered, the feet
/// on the floor — the knees bend, and every joint meets its tracker.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn six_trackers_place_hips_and_feet_too() {
    drive_and_reach(
        &["head", "l_hand", "r_hand", "hips", "l_foot", "r_foot"],
        false,
        0.06,
    )
    .await;
}

/// The same through binary pose messages, the trackers in another order than the standard
/// one (binary poses index the drive's list, whatever its order).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn binary_tracker_poses_place_the_body() {
    drive_and_reach(&["head", "l_hand", "r_hand"], true, 0.0).await;
    drive_and_reach(
        &["r_foot", "l_hand", "hips", "head", "r_hand", "l_foot"],
        true,
        0.06,
    )
    .await;
}

/// The next `error` message on `ws` (a refused pose): `(code, message)`.
async fn pose_error(ws: &mut Ws) -> (String, String) {
    error_of(&common::next_of_type(ws, "error").await)
}

/// `targets` with the left hand's tracker moved 10 cm up: what a refused pose carries beside
/// its bad tracker, to show that nothing of it was stored.
fn hand_moved(targets: &BTreeMap<String, Target>) -> BTreeMap<String, Target> {
    let mut moved = targets.clone();
    let hand = moved.get_mut("l_hand").unwrap();
    hand.0 += Vec3::Y * 0.1;
    moved
}

/// Bad drives, bad tracker poses (JSON and binary) and calibrating what cannot be calibrated
/// get typed errors naming what is wrong, and change nothing: the avatar stays undriven after
/// a refused `drive`, and the body stays on the last good trackers after refused poses whose
/// other trackers moved.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_trackers_are_refused_and_change_nothing() {
    let server = server().await;
    let addr = server.addr;
    let rig = server.rig(AVATAR).unwrap();
    let sub = viewer(addr, Encoding::Binary).await;
    let mut ws = common::raw_at(addr, Encoding::Json, Some(common::CONTROL)).await;
    let three = ["head", "l_hand", "r_hand"];
    let many: Vec<&str> = three
        .into_iter()
        .chain(["hips", "l_foot", "r_foot", "vl5", "vt10", "vt1", "vc4"])
        .chain([
            "l_shoulder",
            "r_shoulder",
            "l_elbow",
            "r_elbow",
            "l_knee",
            "r_knee",
        ])
        .chain(["sacroiliac"])
        .collect();
    assert_eq!(many.len(), 17);
    let drives = [
        (json!(["head", "l_hand"]), None, "invalid_value", "r_hand"),
        (
            json!(["head", "l_hand", "r_hand", "tail"]),
            None,
            "invalid_value",
            "tail",
        ),
        (
            json!(["head", "l_hand", "r_hand", "head"]),
            None,
            "invalid_value",
            "twice",
        ),
        (json!(many), None, "invalid_value", "at most 16"),
        (json!(three), Some("avatar"), "invalid_value", "source"),
    ];
    for (id, (trackers, source, code, mentions)) in (10..).zip(drives) {
        let mut drive = json!({"op": "drive", "avatar": AVATAR, "trackers": trackers});
        if let Some(source) = source {
            drive["source"] = json!(source);
        }
        let (c, m) = command(&mut ws, id, drive.clone()).await.unwrap_err();
        assert_eq!(c, code, "{drive}: {m}");
        assert!(m.contains(mentions), "{drive}: {m}");
    }
    let (c, m) = command(
        &mut ws,
        20,
        json!({"op": "drive", "avatar": AVATAR, "legs": "animated"}),
    )
    .await
    .unwrap_err();
    assert_eq!(c, "invalid_value", "{m}");
    let state = ok(addr, json!({"op": "get_avatar", "avatar": AVATAR})).await;
    assert!(
        state.get("driven").is_none(),
        "a refused drive drives nothing: {state}"
    );
    // Calibrating an avatar no trackers drive.
    let calibrate = json!({"op": "calibrate_trackers", "avatar": AVATAR});
    let (c, m) = command(&mut ws, 21, calibrate.clone()).await.unwrap_err();
    assert_eq!(c, "not_allowed_now", "{m}");

    let info = command(
        &mut ws,
        22,
        json!({"op": "drive", "avatar": AVATAR, "trackers": three}),
    )
    .await
    .unwrap();
    // Nothing to calibrate from yet.
    let (c, m) = command(&mut ws, 23, calibrate).await.unwrap_err();
    assert_eq!(c, "not_allowed_now", "{m}");
    let targets = tracker_targets(&rig, &three, &reaching(), 0.0);
    ws.send(json_pose(1_000_000, &targets)).await.unwrap();
    let want = wanted(&targets);
    reaches(&[("binary", &sub)], &want, "before the bad poses").await;

    // Each bad pose also moves the left hand 10 cm (a second later: the filter would take
    // most of it at once).
    let moved = hand_moved(&targets);
    let mut time_us = 1_000_000;
    let mut json_with = |edit: &dyn Fn(&mut Value)| {
        time_us += 1_000_000;
        let Message::Text(text) = json_pose(time_us, &moved) else {
            unreachable!()
        };
        let mut v: Value = serde_json::from_str(&text).unwrap();
        edit(&mut v);
        v
    };
    let json_cases = [
        (
            json_with(&|v| v["trackers"]["r_hand"]["position"] = json!([1e30, 1.0, 0.0])),
            "invalid_value",
            "r_hand",
        ),
        (
            json_with(&|v| v["trackers"]["r_hand"]["position"] = json!([0.0, 1.0, 10_001.0])),
            "invalid_value",
            "r_hand",
        ),
        (
            json_with(&|v| v["trackers"]["r_hand"]["rotation"] = json!([0.0, 0.0, 0.0, 0.0])),
            "invalid_value",
            "r_hand",
        ),
        (
            json_with(&|v| {
                v["trackers"]["l_foot"] = json!({"position": [0, 0, 0], "rotation": [0, 0, 0, 1]});
            }),
            "unknown_joint",
            "l_foot",
        ),
        (
            json_with(&|v| v["rotations"] = json!({"l_elbow": [0.0, 0.0, 0.0, 1.0]})),
            "invalid_value",
            "driven by trackers",
        ),
        (
            json_with(&|v| v["root_position"] = json!([0.0, 0.9, 0.0])),
            "invalid_value",
            "driven by trackers",
        ),
        (
            json_with(&|v| v["trackers"]["r_hand"]["position"] = json!([null, 1.0, 0.0])),
            "bad_message",
            "",
        ),
        // Good trackers with a weight the avatar lacks: the whole pose is refused.
        (
            json_with(&|v| v["weights"] = json!({"noSuchShape": 0.5})),
            "unknown_expression",
            "noSuchShape",
        ),
    ];
    for (pose, code, mentions) in json_cases {
        ws.send(Message::Text(pose.to_string().into()))
            .await
            .unwrap();
        let (c, m) = pose_error(&mut ws).await;
        assert_eq!(c, code, "{pose}: {m}");
        assert!(m.contains(mentions), "{pose}: {m}");
    }
    // NaN is not JSON.
    let text = json_with(&|_| {})
        .to_string()
        .replacen("1.0", "NaN", 1)
        .replacen("0.0", "NaN", 1);
    assert!(text.contains("NaN"), "{text}");
    ws.send(Message::Text(text.clone().into())).await.unwrap();
    assert_eq!(pose_error(&mut ws).await.0, "bad_message", "{text}");
    // Binary: a NaN position, an index past the drive's trackers, rotations.
    let mut binary_with = |edit: &dyn Fn(&mut BinaryPose)| {
        time_us += 1_000_000;
        let Message::Binary(bytes) = binary_pose(&info, time_us, &moved) else {
            unreachable!()
        };
        let mut pose = BinaryPose::decode(&bytes).unwrap();
        edit(&mut pose);
        Message::Binary(pose.encode().into())
    };
    let r_hand = 2;
    let binary_cases = [
        (
            binary_with(&|p| {
                let t = p.trackers.iter_mut().find(|t| t.0 == r_hand).unwrap();
                t.1 = Vec3::new(f32::NAN, 1.0, 0.0);
            }),
            "invalid_value",
            "r_hand",
        ),
        (
            binary_with(&|p| p.trackers.push((3, Vec3::ONE, Quat::IDENTITY))),
            "unknown_joint",
            "index 3",
        ),
        (
            binary_with(&|p| p.rotations.push((0, Quat::IDENTITY))),
            "invalid_value",
            "driven by trackers",
        ),
    ];
    for (pose, code, mentions) in binary_cases {
        ws.send(pose).await.unwrap();
        let (c, m) = pose_error(&mut ws).await;
        assert_eq!(c, code, "binary: {m}");
        assert!(m.contains(mentions), "binary: {m}");
    }
    // Every refusal is in: the body still meets the last good trackers, tick after tick.
    reaches(&[("binary", &sub)], &want, "after the bad poses").await;

    // Trackers to a drive by rotations.
    command(&mut ws, 30, json!({"op": "drive", "avatar": AVATAR}))
        .await
        .unwrap();
    time_us += 1_000_000;
    ws.send(json_pose(time_us, &targets)).await.unwrap();
    let (c, m) = pose_error(&mut ws).await;
    assert_eq!(c, "invalid_value", "{m}");
    assert!(m.contains("driven by rotations"), "{m}");
}

/// `calibrate_trackers`: a user 10 % taller than the avatar, standing in the neutral pose,
/// is measured (their height, the scale 1/1.1) and from then on their head brings the
/// avatar's head to its own height — standing, and crouching 11 cm, which the avatar does by
/// 10 cm (uncalibrated, the avatar's head could not rise to the user's and a crouch of 11 cm
/// would leave it at its own height).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn calibration_scales_a_taller_user_to_the_avatar() {
    let server = server().await;
    let addr = server.addr;
    let rig = server.rig(AVATAR).unwrap();
    let sub = viewer(addr, Encoding::Json).await;
    let trackers = ["head", "l_hand", "r_hand"];
    let (mut ws, _) = tracker_driver(&server, &trackers).await;
    let avatar = tracker_targets(&rig, &trackers, &[], 0.0);
    // The user: the avatar's neutral pose grown by 10 % about the floor under the head.
    let under_head = avatar["head"].0 * Vec3::new(1.0, 0.0, 1.0);
    let user: BTreeMap<String, Target> = avatar
        .iter()
        .map(|(t, (p, q))| (t.clone(), (under_head + 1.1 * (*p - under_head), *q)))
        .collect();
    ws.send(json_pose(1_000_000, &user)).await.unwrap();
    // Uncalibrated, the avatar's head cannot reach the user's (hips no higher than at rest).
    let head_at =
        |client: &Client| decoded(client, AVATAR).map(|(_, j)| j["skullbase"].w_axis.truncate());
    let mut events = sub.events();
    let deadline = tokio::time::Instant::now() + Duration::from_secs(120);
    let mut seen = 0;
    while seen < 10 {
        if events.recv().await.is_ok() && head_at(&sub).is_some() {
            seen += 1;
        }
        assert!(tokio::time::Instant::now() < deadline, "no frames");
    }
    let before = head_at(&sub).unwrap();
    let own = avatar["head"].0;
    println!(
        "uncalibrated: the head {:.1} mm from its own place, {:.1} mm below the user's",
        before.distance(own) * 1e3,
        (user["head"].0.y - before.y) * 1e3
    );
    assert!(
        user["head"].0.y - before.y > 0.05,
        "{before} vs {:?}",
        user["head"]
    );

    let (status, answer) = command_to(
        addr,
        &json!({"op": "calibrate_trackers", "avatar": AVATAR, "pose": "neutral"}).to_string(),
    )
    .await;
    assert_eq!(status, 200, "{answer}");
    assert_eq!(answer["kind"], "calibration", "{answer}");
    let measured = &answer["result"];
    println!("calibration: {measured}");
    let number = |k: &str| measured[k].as_f64().unwrap() as f32;
    assert_eq!(measured["avatar"], AVATAR);
    assert!((number("scale") - 1.0 / 1.1).abs() < 1e-4, "{measured}");
    assert!(
        (number("arm_scale") - number("scale")).abs() < 1e-6,
        "{measured}"
    );
    assert!(
        (number("user_height") - user["head"].0.y).abs() < 1e-4,
        "{measured}"
    );
    assert_eq!(measured["trackers"], json!(trackers));
    // The head where the avatar's own is, tick after tick (the user keeps standing).
    let want = vec![("skullbase".to_owned(), avatar["head"], false)];
    reaches(&[("JSON", &sub)], &want, "calibrated").await;
    // The user crouches 11 cm (head and hands; the feet stay): the avatar's head goes down
    // 10 cm. A few samples a second apart on the driver's clock, so the input filter settles.
    let crouched: BTreeMap<String, Target> = user
        .iter()
        .map(|(t, (p, q))| (t.clone(), (*p - Vec3::Y * 0.11, *q)))
        .collect();
    for k in 0..6 {
        ws.send(json_pose(2_000_000 + k * 1_000_000, &crouched))
            .await
            .unwrap();
    }
    let (p, q) = avatar["head"];
    let want = vec![("skullbase".to_owned(), (p - Vec3::Y * 0.1, q), false)];
    reaches(&[("JSON", &sub)], &want, "calibrated, crouching").await;
}

/// A tracker drive through a cluster's relay: the driver is connected to B, the avatar ticked
/// by A. `drive … trackers` is answered through B; JSON trackers (names resolved at B) and
/// binary ones reach viewers on A and B where they are; a tracker the drive lacks is refused
/// at B; `calibrate_trackers` sent to B is run by A.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tracker_poses_through_a_relay_reach_every_viewer() {
    use common::child::Posecast;
    use common::nats::Nats;
    let Some(nats) = Nats::start() else { return };
    let node = |name: &str| {
        let url = nats.url();
        Posecast::start(
            &[
                "--nats",
                &url,
                "--node",
                name,
                "--lease",
                "1",
                "--no-persist",
                "--tick-rate",
                "60",
                "--control-token",
                common::CONTROL,
                "--drive-timeout",
                "600",
            ],
            &[],
        )
    };
    let (a, b) = (node("a"), node("b"));
    ok(a.addr, json!({"op": "create_scene", "scene": "stage"})).await;
    ok(
        a.addr,
        json!({"op": "add_avatar", "scene": "stage", "asset": AVATAR, "avatar": "dancer",
               "position": placement().1.to_array(), "rotation": placement().0.to_array()}),
    )
    .await;
    // B lists the scene (and its owner) before its viewer subscribes to it.
    let listed = async {
        loop {
            let scenes = ok(b.addr, json!({"op": "list_scenes"})).await;
            let owner = scenes
                .as_array()
                .and_then(|s| s.iter().find(|s| s["scene"] == "stage"))
                .map(|s| s["owner"].clone());
            if owner == Some(json!("a")) {
                break;
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    };
    tokio::time::timeout(Duration::from_secs(120), listed)
        .await
        .expect("B never listed stage, owned by A");
    let on_a = viewer_of(a.addr, "stage", Encoding::Binary).await;
    let on_b = viewer_of(b.addr, "stage", Encoding::Json).await;
    // B drives only an avatar whose relayed description it has.
    let described = || {
        on_b.avatars()
            .iter()
            .any(|v| v.description.id.0 == "dancer")
    };
    assert!(
        common::wait_for(120.0, described).await,
        "B never described the dancer"
    );
    let mut ws = common::raw_at(b.addr, Encoding::Json, Some(common::CONTROL)).await;
    let trackers = ["l_hand", "head", "r_hand"];
    let info = command(
        &mut ws,
        1,
        json!({"op": "drive", "avatar": "dancer", "trackers": trackers}),
    )
    .await
    .unwrap();
    assert_eq!(info["trackers"], json!(trackers), "{info}");
    let rig = posecast_server::builtin::rig().unwrap();
    let targets = tracker_targets(&rig, &trackers, &reaching(), 0.0);
    let clients = [("binary, on A", &on_a), ("JSON, on B", &on_b)];
    ws.send(json_pose_of("dancer", 1_000_000, &targets))
        .await
        .unwrap();
    reaches_of(&clients, "dancer", &wanted(&targets), "JSON through B").await;
    // Binary, the hands lowered 10 cm (the elbows bend more); the filter settles over a few
    // samples a second apart.
    let lowered: BTreeMap<String, Target> = targets
        .iter()
        .map(|(t, (p, q))| {
            let down = if t.ends_with("_hand") { 0.1 } else { 0.0 };
            (t.clone(), (*p - Vec3::Y * down, *q))
        })
        .collect();
    for k in 0..6 {
        ws.send(binary_pose(&info, 2_000_000 + k * 1_000_000, &lowered))
            .await
            .unwrap();
    }
    reaches_of(&clients, "dancer", &wanted(&lowered), "binary through B").await;
    // Refused at B: a tracker the drive lacks.
    let mut unknown = lowered.clone();
    unknown.insert("l_foot".into(), lowered["head"]);
    ws.send(json_pose_of("dancer", 9_000_000, &unknown))
        .await
        .unwrap();
    let (code, message) = pose_error(&mut ws).await;
    assert_eq!(code, "unknown_joint", "{message}");
    assert!(message.contains("l_foot"), "{message}");
    // Calibrated on A, asked of B.
    let (status, answer) = command_to(
        b.addr,
        &json!({"op": "calibrate_trackers", "avatar": "dancer"}).to_string(),
    )
    .await;
    assert_eq!(status, 200, "{answer}");
    assert_eq!(answer["kind"], "calibration", "{answer}");
    assert_eq!(answer["result"]["trackers"], json!(trackers), "{answer}");
}

/// `legs: "locomotion"`: a user walking plays the walk clip on the legs at the matching rate,
/// standing plays idle; the `@locomotion` layer shows in `get_avatar`; locomotion lists that
/// cannot be played are refused and drive nothing.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn locomotion_legs_follow_the_hips_speed() {
    let server = server().await;
    let addr = server.addr;
    let rig = server.rig(AVATAR).unwrap();
    let mut ws = common::raw_at(addr, Encoding::Json, Some(common::CONTROL)).await;
    let three = ["head", "l_hand", "r_hand"];
    let refused = [
        json!({"legs": "locomotion"}),
        json!({"legs": "locomotion", "locomotion": [{"clip": "moonwalk", "speed": 1.0}]}),
        json!({"legs": "locomotion", "locomotion": [{"clip": "walk", "speed": -1.0}]}),
        json!({"legs": "planted", "locomotion": [{"clip": "walk", "speed": 1.0}]}),
    ];
    for (id, extra) in (30..).zip(refused) {
        let mut drive = json!({"op": "drive", "avatar": AVATAR, "trackers": three});
        for (k, v) in extra.as_object().unwrap() {
            drive[k] = v.clone();
        }
        let (code, m) = command(&mut ws, id, drive.clone()).await.unwrap_err();
        assert_eq!(code, "invalid_value", "{drive}: {m}");
        assert!(m.contains("locomotion"), "{drive}: {m}");
    }
    let state = ok(addr, json!({"op": "get_avatar", "avatar": AVATAR})).await;
    assert!(state.get("driven").is_none(), "{state}");

    let drive = json!({"op": "drive", "avatar": AVATAR, "trackers": three, "legs": "locomotion",
        "locomotion": [{"clip": "idle", "speed": 0.0}, {"clip": "walk", "speed": 1.2}]});
    command(&mut ws, 40, drive).await.unwrap();
    let standing = tracker_targets(&rig, &three, &[], 0.0);
    // Where the trackers are `t` seconds into the walk (1.5 m/s forward along the scene's
    // +Z, then still after `stop` seconds).
    let at = |t: f32, stop: f32| -> BTreeMap<String, Target> {
        let walked = Vec3::Z * 1.5 * t.min(stop);
        standing
            .iter()
            .map(|(n, (p, q))| (n.clone(), (*p + walked, *q)))
            .collect()
    };
    let started = std::time::Instant::now();
    let locomotion = |state: &Value| -> Option<(String, f64)> {
        let layer = state["layers"]
            .as_array()?
            .iter()
            .find(|l| l["layer"] == "@locomotion" && l["weight"].as_f64() > Some(0.99))?;
        Some((layer["clip"].as_str()?.to_owned(), layer["speed"].as_f64()?))
    };
    // Walking: the walk clip at 1.5 / 1.2 = 1.25 its rate. Poses follow the wall clock (the
    // scene's clock runs with it), so a stall of the test changes only how far the user got.
    let mut walking = None;
    let mut stopped_at = None;
    let mut idle = false;
    let deadline = started + Duration::from_secs(120);
    while std::time::Instant::now() < deadline && !idle {
        let t = started.elapsed().as_secs_f32();
        let stop = stopped_at.unwrap_or(f32::INFINITY);
        let time_us = started.elapsed().as_micros() as u64;
        ws.send(json_pose(time_us, &at(t, stop))).await.unwrap();
        tokio::time::sleep(Duration::from_millis(16)).await;
        let state = ok(addr, json!({"op": "get_avatar", "avatar": AVATAR})).await;
        match (locomotion(&state), stopped_at) {
            (Some((clip, speed)), None) if clip == "walk" && (speed - 1.25).abs() < 0.1 => {
                walking = Some(speed);
                stopped_at = Some(t);
            }
            (Some((clip, _)), Some(_)) if clip == "idle" => idle = true,
            _ => {}
        }
    }
    assert!(
        walking.is_some(),
        "the walk clip never played at 1.25× its rate"
    );
    assert!(idle, "standing still never went back to idle");
    // Released: the layer fades out and goes; the avatar's own clip plays the legs again.
    command(
        &mut ws,
        41,
        json!({"op": "release_drive", "avatar": AVATAR}),
    )
    .await
    .unwrap();
    let deadline = std::time::Instant::now() + Duration::from_secs(120);
    let mut gone = false;
    while !gone && std::time::Instant::now() < deadline {
        let state = ok(addr, json!({"op": "get_avatar", "avatar": AVATAR})).await;
        gone = state["layers"]
            .as_array()
            .is_none_or(|l| l.iter().all(|l| l["layer"] != "@locomotion"));
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    assert!(gone, "the locomotion layer outlived its drive");
}
