//! Persistence end to end with the real binary: acknowledged changes survive `SIGKILL` right
//! after the last acknowledgement, and unreadable stored files are reported, set aside and
//! skipped while everything else restores.
//!
//! What SIGKILL proves is *write before ack* against a process crash: the kernel's page cache
//! outlives the process, so these tests cannot tell whether `sync_all` ran (a power loss
//! could); the fsync calls are covered by `store::atomic`'s tests of the write path.

#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use common::child::Posecast;
use common::{command_to, http_to, testdata_bytes, upload_files};
use serde_json::Value;
use std::net::SocketAddr;
use std::path::Path;
use std::time::{Duration, Instant};

/// The binary on `data`, with the tests' control token.
fn start(data: &Path) -> Posecast {
    let data = data.to_str().unwrap();
    Posecast::start(
        &["--tick-rate", "30", "--data", data],
        &[("POSECAST_CONTROL_TOKEN", common::CONTROL)],
    )
}

/// A command that must succeed; its result.
async fn ok(addr: SocketAddr, json: &str) -> Value {
    let (status, body) = command_to(addr, json).await;
    assert_eq!(status, 200, "{json} → {body}");
    body["result"].clone()
}

async fn avatar(addr: SocketAddr, id: &str) -> Value {
    ok(addr, &format!(r#"{{"op":"get_avatar","avatar":"{id}"}}"#)).await
}

fn quat(v: &Value) -> [f64; 4] {
    let a = v.as_array().unwrap();
    std::array::from_fn(|i| a[i].as_f64().unwrap())
}

/// Same rotation (q and −q alike) within `tol` per component.
fn same_rotation(a: [f64; 4], b: [f64; 4], tol: f64) -> bool {
    let dot: f64 = a.iter().zip(&b).map(|(x, y)| x * y).sum();
    let s = if dot < 0.0 { -1.0 } else { 1.0 };
    a.iter().zip(&b).all(|(x, y)| (x - s * y).abs() <= tol)
}

/// The rotation an override holds now: a local increment by the identity returns the current
/// local rotation, which is the override.
async fn override_of(addr: SocketAddr, avatar: &str, joint: &str) -> [f64; 4] {
    let r = ok(
        addr,
        &format!(r#"{{"op":"rotate_joint_local","avatar":"{avatar}","joint":"{joint}","rotation":[0,0,0,1]}}"#),
    )
    .await;
    quat(&r["rotation"])
}

async fn scene_ids(addr: SocketAddr) -> Vec<String> {
    let scenes = ok(addr, r#"{"op":"list_scenes"}"#).await;
    scenes
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s["scene"].as_str().unwrap().to_owned())
        .collect()
}

async fn asset_names(addr: SocketAddr) -> Vec<String> {
    let (s, b) = http_to(addr, "GET", "/api/assets", "application/json", b"").await;
    assert_eq!(s, 200, "{b}");
    let v: Value = serde_json::from_str(&b).unwrap();
    v.as_array()
        .unwrap()
        .iter()
        .map(|a| a["name"].as_str().unwrap().to_owned())
        .collect()
}

async fn upload_wasp(addr: SocketAddr, name: &str) -> bool {
    let (Some(skel), Some(skin), Some(walk)) = (
        testdata_bytes("cse169/wasp.skel"),
        testdata_bytes("cse169/wasp.skin"),
        testdata_bytes("cse169/wasp_walk.anim"),
    ) else {
        return false;
    };
    let (s, b) = upload_files(
        addr,
        &format!("/api/assets/{name}"),
        &[
            ("wasp.skel", &skel),
            ("wasp.skin", &skin),
            ("wasp_walk.anim", &walk),
        ],
    )
    .await;
    assert_eq!(s, 200, "{b}");
    true
}

/// A command over a websocket; waits for its ack.
async fn ws_command(addr: SocketAddr, json: &str) {
    use futures_util::{SinkExt, StreamExt};
    use posecast_proto::msg::{ClientMsg, Encoding, PROTOCOL_VERSION, ServerMsg};
    use tokio_tungstenite::tungstenite::Message;
    let (mut ws, _) = tokio_tungstenite::connect_async(format!("ws://{addr}/ws"))
        .await
        .unwrap();
    for msg in [
        ClientMsg::Hello {
            version: PROTOCOL_VERSION,
            encoding: Encoding::Json,
            token: Some(common::CONTROL.into()),
            client: None,
        },
        ClientMsg::Command {
            id: 7,
            idempotency_key: None,
            command: serde_json::from_str(json).unwrap(),
        },
    ] {
        let text = serde_json::to_string(&msg).unwrap();
        ws.send(Message::Text(text.into())).await.unwrap();
    }
    let deadline = tokio::time::Instant::now() + Duration::from_secs(5);
    loop {
        let msg = tokio::time::timeout_at(deadline, ws.next())
            .await
            .expect("no ack")
            .unwrap()
            .unwrap();
        if let Message::Text(t) = msg {
            match serde_json::from_str::<ServerMsg>(t.as_str()).unwrap() {
                ServerMsg::Ack { id: 7, .. } => return,
                ServerMsg::Error(e) => panic!("{json}: {e:?}"),
                _ => {}
            }
        }
    }
}

#[tokio::test]
async fn acknowledged_changes_survive_sigkill() {
    let data = tempfile::tempdir().unwrap();
    let server = start(data.path());
    let addr = server.addr;
    // First start: the built-in default scene exists (and is stored).
    assert_eq!(scene_ids(addr).await, vec!["default"]);

    ok(addr, r#"{"op":"create_scene","scene":"stage"}"#).await;
    if !upload_wasp(addr, "wasp").await {
        return;
    }
    ok(
        addr,
        r#"{"op":"add_avatar","scene":"stage","asset":"wasp","avatar":"w1"}"#,
    )
    .await;
    ok(
        addr,
        r#"{"op":"play","avatar":"w1","clip":"wasp_walk","looping":true}"#,
    )
    .await;
    // The websocket's acknowledgements are durable too.
    ws_command(addr, r#"{"op":"set_speed","avatar":"w1","speed":0.5}"#).await;
    let rot_w = quat(
        &ok(addr, r#"{"op":"set_joint_rotation","avatar":"w1","joint":"tail_01","rotation":[0.2588190,0,0,0.9659258]}"#)
            .await["rotation"],
    );
    ok(
        addr,
        r#"{"op":"add_avatar","scene":"stage","asset":"avatar","avatar":"b1"}"#,
    )
    .await;
    ok(
        addr,
        r#"{"op":"play","avatar":"b1","clip":"wave","speed":2.0,"looping":false,"start":0.3}"#,
    )
    .await;
    ok(addr, r#"{"op":"pause","avatar":"b1"}"#).await;
    let rot_b = quat(
        &ok(addr, r#"{"op":"set_joint_rotation","avatar":"b1","joint":"l_knee","rotation":[0.3826834,0,0,0.9238795]}"#)
            .await["rotation"],
    );
    let b_before = avatar(addr, "b1").await;
    let w_before = avatar(addr, "w1").await;
    let t0 = Instant::now();
    // The last change, over the websocket (nothing else touches scene default's file after
    // it); SIGKILL right after its acknowledgement.
    ws_command(addr, r#"{"op":"delete_scene","scene":"default"}"#).await;
    server.kill();

    let server = start(data.path());
    let addr = server.addr;
    assert_eq!(
        scene_ids(addr).await,
        vec!["stage"],
        "deleting default persists"
    );
    assert!(asset_names(addr).await.contains(&"wasp".to_owned()));

    let b = avatar(addr, "b1").await;
    assert_eq!(b["clip"], "wave");
    assert_eq!(b["paused"], true);
    assert_eq!(b["looping"], false);
    assert_eq!(b["speed"], 2.0);
    assert_eq!(b["time"], b_before["time"], "a paused clock stands still");
    assert_eq!(b["overrides"], serde_json::json!(["l_knee"]));

    let w = avatar(addr, "w1").await;
    let t1 = t0.elapsed().as_secs_f64();
    assert_eq!(w["clip"], "wasp_walk");
    assert_eq!(w["paused"], false);
    assert_eq!(w["looping"], true);
    assert_eq!(w["speed"], 0.5);
    assert_eq!(w["overrides"], serde_json::json!(["tail_01"]));
    // The clock went on while the server was down: where it would be had it kept running.
    let expected = (w_before["time"].as_f64().unwrap() + 0.5 * t1).rem_euclid(4.0);
    let got = w["time"].as_f64().unwrap();
    let diff = (got - expected).rem_euclid(4.0);
    assert!(
        diff.min(4.0 - diff) < 0.15,
        "clip time {got}, expected about {expected}"
    );

    assert!(same_rotation(
        override_of(addr, "w1", "tail_01").await,
        rot_w,
        1e-4
    ));
    assert!(same_rotation(
        override_of(addr, "b1", "l_knee").await,
        rot_b,
        1e-4
    ));
    server.kill();
}

#[tokio::test]
async fn unreadable_files_are_reported_set_aside_and_skipped() {
    let Some(sinus) = testdata_bytes("bvh/fairmotion/sinusoidal.bvh") else {
        return;
    };
    let data = tempfile::tempdir().unwrap();
    let server = start(data.path());
    let addr = server.addr;
    for scene in ["a", "b"] {
        ok(
            addr,
            &format!(r#"{{"op":"create_scene","scene":"{scene}"}}"#),
        )
        .await;
    }
    if !upload_wasp(addr, "wasp").await {
        return;
    }
    let (s, b) = upload_files(addr, "/api/assets/sin", &[("sinusoidal.bvh", &sinus)]).await;
    assert_eq!(s, 200, "{b}");
    ok(
        addr,
        r#"{"op":"add_avatar","scene":"a","asset":"avatar","avatar":"a1"}"#,
    )
    .await;
    ok(
        addr,
        r#"{"op":"add_avatar","scene":"b","asset":"sin","avatar":"s1","clip":"sinusoidal"}"#,
    )
    .await;
    ok(
        addr,
        r#"{"op":"add_avatar","scene":"b","asset":"wasp","avatar":"w1","clip":"wasp_walk"}"#,
    )
    .await;
    server.kill();

    // A scene file cut short, an asset meta cut short, a scene file from a future version.
    let truncate = |path: &Path| {
        let bytes = std::fs::read(path).unwrap();
        std::fs::write(path, &bytes[..bytes.len() / 2]).unwrap();
    };
    let scenes = data.path().join("scenes");
    truncate(&scenes.join("a.json"));
    truncate(&data.path().join("assets/sin/meta.json"));
    std::fs::write(
        scenes.join("c.json"),
        r#"{"format": 99, "scene": "c", "saved_us": 0, "avatars": []}"#,
    )
    .unwrap();

    let server = start(data.path());
    let addr = server.addr;
    assert_eq!(scene_ids(addr).await, vec!["b", "default"]);
    let assets = asset_names(addr).await;
    assert!(
        assets.contains(&"wasp".to_owned()) && !assets.contains(&"sin".to_owned()),
        "{assets:?}"
    );
    // Scene b restores without the avatar whose asset is gone.
    let b = ok(addr, r#"{"op":"list_scenes"}"#).await;
    let b = b
        .as_array()
        .unwrap()
        .iter()
        .find(|s| s["scene"] == "b")
        .unwrap();
    let ids: Vec<&str> = b["avatars"]
        .as_array()
        .unwrap()
        .iter()
        .map(|a| a["avatar"].as_str().unwrap())
        .collect();
    assert_eq!(ids, vec!["w1"]);
    assert_eq!(avatar(addr, "w1").await["clip"], "wasp_walk");

    // Nothing lost: the bad files are beside their old names; the log names each.
    assert!(scenes.join("a.json.corrupt").is_file() && !scenes.join("a.json").exists());
    assert!(scenes.join("c.json.corrupt").is_file());
    assert!(data.path().join("assets/sin.corrupt/meta.json").is_file());
    let log = server.output();
    for name in ["a.json", "c.json", "sin"] {
        assert!(
            log.iter().any(|l| l.contains("WARN") && l.contains(name)),
            "no warning naming {name}: {log:#?}"
        );
    }
    server.kill();
}

/// Twenty connections at once, each changing its own joint thirty times under a command rate
/// limit: acks are group-committed and some commands are refused with `rate_limited` (then
/// retried after the hint). SIGKILL right after the last ack: every joint holds the rotation
/// of its last *acknowledged* command.
#[tokio::test]
async fn grouped_and_rate_limited_acks_survive_sigkill() {
    use futures_util::{SinkExt, StreamExt};
    use posecast_proto::msg::{ClientMsg, Encoding, ErrorCode, PROTOCOL_VERSION, ServerMsg};
    use tokio_tungstenite::tungstenite::Message;

    let data = tempfile::tempdir().unwrap();
    let dir = data.path().to_str().unwrap().to_owned();
    let server = Posecast::start(
        &[
            "--tick-rate",
            "30",
            "--data",
            &dir,
            "--command-rate",
            "50",
            "--command-burst",
            "10",
        ],
        &[("POSECAST_CONTROL_TOKEN", common::CONTROL)],
    );
    let addr = server.addr;
    let rig = posecast_server::builtin::rig().unwrap();
    let joints: Vec<String> = rig.skeleton().names()[..20].to_vec();
    let tasks: Vec<_> = joints
        .iter()
        .enumerate()
        .map(|(i, joint)| {
            let joint = joint.clone();
            tokio::spawn(async move {
                let (mut ws, _) = tokio_tungstenite::connect_async(format!("ws://{addr}/ws"))
                    .await
                    .unwrap();
                let hello = ClientMsg::Hello {
                    version: PROTOCOL_VERSION,
                    encoding: Encoding::Json,
                    token: Some(common::CONTROL.into()),
                    client: None,
                };
                let text = serde_json::to_string(&hello).unwrap();
                ws.send(Message::Text(text.into())).await.unwrap();
                let (mut last, mut limited) = (None, 0);
                for k in 0..30u64 {
                    let angle = 0.01 * (k + 1) as f64 + 0.001 * i as f64;
                    let q = [(angle / 2.0).sin(), 0.0, 0.0, (angle / 2.0).cos()];
                    let json = format!(
                        r#"{{"op":"set_joint_rotation","avatar":"avatar","joint":"{joint}","rotation":[{},{},{},{}]}}"#,
                        q[0], q[1], q[2], q[3]
                    );
                    loop {
                        let c = ClientMsg::Command {
                            id: k,
                            idempotency_key: None,
                            command: serde_json::from_str(&json).unwrap(),
                        };
                        let text = serde_json::to_string(&c).unwrap();
                        ws.send(Message::Text(text.into())).await.unwrap();
                        let answer = loop {
                            let msg = tokio::time::timeout(Duration::from_secs(10), ws.next())
                                .await
                                .expect("an answer")
                                .unwrap()
                                .unwrap();
                            if let Message::Text(t) = msg
                                && let m @ (ServerMsg::Ack { .. } | ServerMsg::Error(_)) =
                                    serde_json::from_str::<ServerMsg>(t.as_str()).unwrap()
                            {
                                break m;
                            }
                        };
                        match answer {
                            ServerMsg::Ack { result, .. } => {
                                last = Some(quat(&result.to_value()["rotation"]));
                                break;
                            }
                            ServerMsg::Error(e) if e.code == ErrorCode::RateLimited => {
                                limited += 1;
                                let wait = e.retry_after_ms.expect("a retry hint");
                                tokio::time::sleep(Duration::from_millis(wait)).await;
                            }
                            other => panic!("{other:?}"),
                        }
                    }
                }
                (joint, last.unwrap(), limited)
            })
        })
        .collect();
    let mut acked = Vec::new();
    for t in tasks {
        acked.push(t.await.unwrap());
    }
    server.kill();
    let limited: u32 = acked.iter().map(|a| a.2).sum();
    assert!(limited > 0, "the rate limit never engaged");

    let server = start(data.path());
    let addr = server.addr;
    for (joint, rotation, _) in &acked {
        let stored = override_of(addr, "avatar", joint).await;
        assert!(
            same_rotation(stored, *rotation, 1e-4),
            "{joint}: stored {stored:?}, acked {rotation:?}"
        );
    }
    server.kill();
}

/// One data folder, one server: a second server on it refuses to start and names the folder
/// and the holder, and the folder is free again once the first has stopped.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_second_server_on_the_same_data_folder_refuses_to_start() {
    let data = tempfile::tempdir().unwrap();
    let config = || posecast_server::config::Config {
        listen: "127.0.0.1:0".parse().unwrap(),
        data_dir: Some(data.path().to_owned()),
        ..posecast_server::config::Config::default()
    };
    let first = posecast_server::startup::Server::start(config())
        .await
        .unwrap();
    first.ready().await.unwrap();
    let refused = posecast_server::startup::Server::start(config())
        .await
        .expect_err("a second server started on a folder in use");
    let message = refused.to_string();
    assert!(
        message.contains(&data.path().display().to_string())
            && message.contains("another posecast server")
            && message.contains(&std::process::id().to_string()),
        "{message}"
    );
    first.stop().await;
    let again = posecast_server::startup::Server::start(config())
        .await
        .unwrap();
    again.ready().await.unwrap();
    again.stop().await;
}

/// A busy port is reported with its address, before the data folder is touched.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_busy_port_is_named_and_the_data_folder_left_alone() {
    let taken = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = taken.local_addr().unwrap();
    let parent = tempfile::tempdir().unwrap();
    let data = parent.path().join("data");
    let refused = posecast_server::startup::Server::start(posecast_server::config::Config {
        listen: addr,
        data_dir: Some(data.clone()),
        ..posecast_server::config::Config::default()
    })
    .await
    .expect_err("started on a busy port");
    assert!(refused.to_string().contains(&addr.to_string()), "{refused}");
    assert!(
        !data.exists(),
        "the data folder was created before listening"
    );
}

/// The avatars of scene `scene` as `addr` lists them.
async fn avatars_of(addr: SocketAddr, scene: &str) -> Vec<String> {
    let scenes = ok(addr, r#"{"op":"list_scenes"}"#).await;
    scenes
        .as_array()
        .unwrap()
        .iter()
        .find(|s| s["scene"] == scene)
        .map(|s| {
            s["avatars"]
                .as_array()
                .unwrap()
                .iter()
                .map(|a| a["avatar"].as_str().unwrap().to_owned())
                .collect()
        })
        .unwrap_or_default()
}

/// A server on its own (issue 37, goal 2): a command sent again with its idempotency key
/// after an unknown outcome is answered with the first answer and applied once — also after
/// the server was SIGKILLed right after the answer (the answer is stored with the change);
/// the key used for another op is a conflict, and a new key applies again.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_keyed_command_applies_once_also_after_sigkill() {
    use common::cluster::try_post;
    let data = tempfile::tempdir().unwrap();
    let server = start(data.path());
    let addr = server.addr;
    // No avatar id: a second application would add a second avatar.
    let add = r#"{"op":"add_avatar","scene":"default","asset":"avatar"}"#;
    let before = avatars_of(addr, "default").await.len();
    let (status, first) = try_post(addr, add, Some("retry-1")).await.unwrap();
    assert_eq!(status, 200, "{first}");
    let (status, again) = try_post(addr, add, Some("retry-1")).await.unwrap();
    assert_eq!((status, &again), (200, &first));
    assert_eq!(avatars_of(addr, "default").await.len(), before + 1);
    let added = first["result"]["avatar"].as_str().unwrap().to_owned();
    let remove = format!(r#"{{"op":"remove_avatar","avatar":"{added}"}}"#);
    let (status, body) = try_post(addr, &remove, Some("retry-1")).await.unwrap();
    assert_eq!(
        (status, body["code"].as_str()),
        (409, Some("conflict")),
        "{body}"
    );

    server.kill();
    let server = start(data.path());
    let addr = server.addr;
    let (status, after) = try_post(addr, add, Some("retry-1")).await.unwrap();
    assert_eq!(
        (status, &after),
        (200, &first),
        "answered from the stored scene"
    );
    assert_eq!(avatars_of(addr, "default").await.len(), before + 1);
    let (status, other) = try_post(addr, add, Some("retry-2")).await.unwrap();
    assert_eq!(status, 200, "{other}");
    assert_ne!(other, first);
    assert_eq!(avatars_of(addr, "default").await.len(), before + 2);
}
