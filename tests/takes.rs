//! Takes of whole scenes (issue 32) end to end: a replay streams, frame for frame, what the
//! recorded scene's live subscribers received; it seeks, pauses and loops; an avatar taken
//! over leaves it while the others go on; a take survives a SIGKILL of the server mid-take;
//! damaged take files get typed errors.

#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use common::watch::{PATIENCE, Watcher, find, same, unprefixed};

use common::child::Posecast;
use common::command_to;
use futures_util::{SinkExt, StreamExt};
use posecast_proto::frame::AvatarPose;
use posecast_proto::msg::{ClientMsg, Encoding, PROTOCOL_VERSION, SceneId};
use serde_json::Value;
use std::collections::BTreeMap;
use std::net::SocketAddr;
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tokio_tungstenite::tungstenite::Message;

async fn ok(addr: SocketAddr, json: &str) -> Value {
    let (status, body) = command_to(addr, json).await;
    assert_eq!(status, 200, "{json} → {body}");
    body["result"].clone()
}

/// A connection watching the scene list: the `(type, scene, avatar)` of every avatar change it
/// hears.
async fn watch_scene_list(addr: SocketAddr) -> Arc<Mutex<Vec<(String, String, String)>>> {
    let (mut ws, _) = tokio_tungstenite::connect_async(format!("ws://{addr}/ws"))
        .await
        .unwrap();
    for msg in [
        ClientMsg::Hello {
            version: PROTOCOL_VERSION,
            encoding: Encoding::Json,
            token: None,
            client: None,
        },
        ClientMsg::WatchScenes,
    ] {
        let text = serde_json::to_string(&msg).unwrap();
        ws.send(Message::Text(text.into())).await.unwrap();
    }
    let heard = Arc::new(Mutex::new(Vec::new()));
    let out = heard.clone();
    tokio::spawn(async move {
        while let Some(Ok(msg)) = ws.next().await {
            let Message::Text(t) = msg else { continue };
            let Ok(v) = serde_json::from_str::<Value>(t.as_str()) else {
                continue;
            };
            let kind = v["type"].as_str().unwrap_or_default().to_owned();
            let avatar = match kind.as_str() {
                "avatar_changed" => v["avatar"]["avatar"].as_str(),
                "avatar_removed" => v["avatar"].as_str(),
                _ => None,
            };
            if let (Some(avatar), Some(scene)) = (avatar, v["scene"].as_str()) {
                out.lock()
                    .unwrap()
                    .push((kind, scene.to_owned(), avatar.to_owned()));
            }
        }
    });
    heard
}

/// Records the built-in scene while avatars come and go and move, replays the take, and
/// checks that every frame of the replay is a frame the live subscriber received, in order,
/// with nothing the take had skipped. Then seeks, pauses, and takes one avatar over.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_replay_streams_what_live_subscribers_received() {
    let server = common::server(30.0).await;
    let addr = server.addr;
    ok(
        addr,
        r#"{"op":"add_avatar","scene":"default","asset":"avatar","avatar":"b"}"#,
    )
    .await;
    ok(
        addr,
        r#"{"op":"play","avatar":"b","clip":"wave","speed":0.7}"#,
    )
    .await;
    let live = Watcher::start(addr, "default").await;
    live.until("live frames", |f| f.len() >= 3).await;
    let started = ok(
        addr,
        r#"{"op":"record_scene","scene":"default","take":"rehearsal"}"#,
    )
    .await;
    assert_eq!(started["recording"], true, "{started}");
    let first = live.frames().len();
    live.until("20 frames recorded", |f| f.len() >= first + 20)
        .await;
    ok(
        addr,
        r#"{"op":"place_avatar","avatar":"avatar","position":[1.5,0,-2],"rotation":[0,0.3826834,0,0.9238795],"duration":0.5}"#,
    )
    .await;
    ok(
        addr,
        r#"{"op":"add_avatar","scene":"default","asset":"avatar","avatar":"c"}"#,
    )
    .await;
    live.until("c on stage", |f| {
        f.last().is_some_and(|s| s.poses.contains_key("c"))
    })
    .await;
    let at = live.frames().len();
    live.until("20 more frames", |f| f.len() >= at + 20).await;
    ok(addr, r#"{"op":"remove_avatar","avatar":"b"}"#).await;
    live.until("b gone", |f| {
        f.last().is_some_and(|s| !s.poses.contains_key("b"))
    })
    .await;
    let at = live.frames().len();
    live.until("20 frames after", |f| f.len() >= at + 20).await;
    let take = ok(addr, r#"{"op":"stop_recording_scene","scene":"default"}"#).await;
    assert_eq!(take["recording"], false, "{take}");
    let frames = take["frames"].as_u64().unwrap() as usize;
    assert!(frames >= 60, "{take}");
    assert_eq!(take["avatars"], serde_json::json!(["avatar", "b", "c"]));
    let listed = ok(addr, r#"{"op":"list_takes"}"#).await;
    assert_eq!(listed[0]["take"], "rehearsal", "{listed}");
    live.stop();
    let live = live.frames();

    // The replay, at the recorded speed: every frame it streams is one the live subscriber
    // got, in the order it got them.
    let list = watch_scene_list(addr).await;
    let replay = ok(addr, r#"{"op":"replay","take":"rehearsal","scene":"r"}"#).await;
    assert_eq!(replay["take"], "rehearsal", "{replay}");
    let duration = replay["duration"].as_f64().unwrap();
    assert!(
        (duration - (frames - 1) as f64 / 30.0).abs() < 0.5,
        "{replay}"
    );
    let watcher = Watcher::start(addr, "r").await;
    // To the end (it holds the last frame when not looping), and a few frames more.
    let ended = tokio::time::timeout(PATIENCE, async {
        loop {
            let state = ok(addr, r#"{"op":"control_replay","scene":"r"}"#).await;
            if state["time"].as_f64().unwrap() >= duration {
                return;
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    })
    .await;
    assert!(ended.is_ok(), "the replay reaches its end");
    let n = watcher.frames().len();
    watcher
        .until("frames at the end", |f| f.len() >= n + 3)
        .await;
    let replayed = watcher.frames();
    let last = live
        .iter()
        .rev()
        .find(|s| same(&s.poses, &unprefixed(&replayed.last().unwrap().poses, "r")));
    assert!(last.is_some(), "the replay's last frame is a live one");
    let mut at = 0;
    let mut matched = 0;
    for (k, s) in replayed.iter().enumerate() {
        let poses = unprefixed(&s.poses, "r");
        match find(&live, at, &poses) {
            Some(i) => {
                at = i;
                matched += 1;
            }
            None => panic!(
                "replay frame {k} (tick {}) with avatars {:?} is no live frame from {at} on",
                s.seq,
                poses.keys().collect::<Vec<_>>()
            ),
        }
    }
    assert!(matched >= replayed.len() / 2 && matched > 30, "{matched}");
    // The avatars came and went with the take.
    let casts: Vec<Vec<String>> = replayed
        .iter()
        .map(|s| s.poses.keys().cloned().collect())
        .collect();
    assert!(
        casts
            .iter()
            .any(|c| c.contains(&"r.b".to_owned()) && !c.contains(&"r.c".to_owned()))
    );
    assert!(
        casts
            .iter()
            .any(|c| c.contains(&"r.c".to_owned()) && !c.contains(&"r.b".to_owned()))
    );
    // The scene list's watchers heard them come and go too.
    let heard = list.lock().unwrap().clone();
    let heard_of = |kind: &str, avatar: &str| {
        heard
            .iter()
            .any(|(k, s, a)| k == kind && s == "r" && a == avatar)
    };
    assert!(heard_of("avatar_changed", "r.avatar"), "{heard:?}");
    assert!(heard_of("avatar_changed", "r.c"), "{heard:?}");
    assert!(heard_of("avatar_removed", "r.b"), "{heard:?}");

    // A second replay of the same take at once, at twice the speed: its frames are the
    // take's too, and the first replay goes on.
    ok(
        addr,
        r#"{"op":"replay","take":"rehearsal","scene":"r2","speed":2}"#,
    )
    .await;
    let second = Watcher::start(addr, "r2").await;
    second
        .until("frames of the second replay", |f| f.len() >= 10)
        .await;
    for s in second.frames() {
        let poses = unprefixed(&s.poses, "r2");
        assert!(
            find(&live, 0, &poses).is_some(),
            "the second replay's tick {} is a live frame",
            s.seq
        );
    }
    drop(second);
    ok(addr, r#"{"op":"delete_scene","scene":"r2"}"#).await;

    // Seek and pause: the frame shown is the take's at that time, and stays.
    let seek = ok(
        addr,
        r#"{"op":"control_replay","scene":"r","time":0.5,"paused":true}"#,
    )
    .await;
    assert_eq!(seek["paused"], true, "{seek}");
    assert!(
        (seek["time"].as_f64().unwrap() - 0.5).abs() < 1e-9,
        "{seek}"
    );
    let n = watcher.frames().len();
    watcher
        .until("frames while paused", |f| f.len() >= n + 10)
        .await;
    let paused = watcher.frames();
    let held = unprefixed(&paused.last().unwrap().poses, "r");
    for s in &paused[paused.len() - 5..] {
        assert!(
            same(&unprefixed(&s.poses, "r"), &held),
            "paused frames stay"
        );
    }
    // Half a second into the take: the live frame 15 ticks after the first recorded one.
    let first_seq = live
        .iter()
        .position(|s| same(&s.poses, &unprefixed(&replayed[0].poses, "r")))
        .unwrap();
    let expected = &live[first_seq..]
        .iter()
        .find(|s| s.seq >= live[first_seq].seq + 15)
        .unwrap()
        .poses;
    assert!(same(&held, expected), "the frame at 0.5 s");

    // Take one avatar over with a clip: it leaves the replay, the other keeps replaying.
    ok(
        addr,
        r#"{"op":"control_replay","scene":"r","paused":false,"loop":true}"#,
    )
    .await;
    ok(addr, r#"{"op":"play","avatar":"r.avatar","clip":"wave"}"#).await;
    let n = watcher.frames().len();
    watcher
        .until("frames after the take-over", |f| f.len() >= n + 20)
        .await;
    let after = watcher.frames();
    let mut free = 0;
    for s in &after[n + 5..] {
        let poses = unprefixed(&s.poses, "r");
        let b = poses.get("b").or(poses.get("c")).unwrap();
        let a = &poses["avatar"];
        let live_has = |id: &str, p: &AvatarPose| {
            live.iter().any(|l| {
                l.poses
                    .get(id)
                    .is_some_and(|q| q.rotations == p.rotations && q.placement == p.placement)
            })
        };
        let other = if poses.contains_key("b") { "b" } else { "c" };
        assert!(
            live_has(other, b),
            "the avatar not taken over still replays"
        );
        if !live_has("avatar", a) {
            free += 1;
        }
    }
    assert!(
        free > 5,
        "the avatar taken over plays its clip, not the take"
    );
    drop(watcher);
    // Deleting a replayed take is refused; after the replay's scene goes it is not.
    let (status, body) = command_to(addr, r#"{"op":"delete_take","take":"rehearsal"}"#).await;
    assert_eq!(status, 409, "{body}");
    ok(addr, r#"{"op":"delete_scene","scene":"r"}"#).await;
    ok(addr, r#"{"op":"delete_take","take":"rehearsal"}"#).await;
    let (status, body) = command_to(addr, r#"{"op":"get_take","take":"rehearsal"}"#).await;
    assert_eq!(
        (status, body["code"].as_str()),
        (404, Some("unknown_take")),
        "{body}"
    );
}

/// A server killed while it records keeps the take up to its last complete frame: after the
/// restart it is listed, not recording, and replays.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_take_survives_a_sigkill_mid_take() {
    let data = tempfile::tempdir().unwrap();
    let server = Posecast::on_data(data.path());
    let addr = server.addr;
    ok(
        addr,
        r#"{"op":"record_scene","scene":"default","take":"killed"}"#,
    )
    .await;
    let path = data.path().join("takes").join("killed.take");
    // Until the file holds a few seconds of frames (the writer appends as the scene ticks).
    let grew = tokio::time::timeout(PATIENCE, async {
        loop {
            if std::fs::metadata(&path).is_ok_and(|m| m.len() > 20_000) {
                return;
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    })
    .await;
    assert!(grew.is_ok(), "the take grows on disk while recording");
    server.kill();
    let size = std::fs::metadata(&path).unwrap().len();
    // Beside it, a file that is no take and a take damaged in the middle.
    let bytes = std::fs::read(&path).unwrap();
    let mut broken = bytes.clone();
    broken[bytes.len() / 2] ^= 0x5a;
    std::fs::write(data.path().join("takes/broken.take"), &broken).unwrap();
    std::fs::write(data.path().join("takes/junk.take"), b"not a take at all").unwrap();
    let again = Posecast::on_data(data.path());
    let addr = again.addr;
    let listed = ok(addr, r#"{"op":"list_takes"}"#).await;
    let names: Vec<&str> = listed
        .as_array()
        .unwrap()
        .iter()
        .filter_map(|t| t["take"].as_str())
        .collect();
    assert_eq!(names, ["killed"], "unreadable takes are left out: {listed}");
    for json in [
        r#"{"op":"get_take","take":"junk"}"#,
        r#"{"op":"get_take","take":"broken"}"#,
        r#"{"op":"replay","take":"broken","scene":"b"}"#,
        r#"{"op":"replay","take":"nothing","scene":"b"}"#,
    ] {
        let (status, body) = command_to(addr, json).await;
        assert_eq!(
            (status, body["code"].as_str()),
            (404, Some("unknown_take")),
            "{json}: {body}"
        );
    }
    let (_, body) = command_to(addr, r#"{"op":"get_take","take":"broken"}"#).await;
    assert!(
        body["message"].as_str().unwrap().contains("corrupt")
            || body["message"].as_str().unwrap().contains("damaged"),
        "{body}"
    );
    let info = ok(addr, r#"{"op":"get_take","take":"killed"}"#).await;
    assert_eq!(info["recording"], false, "{info}");
    assert_eq!(info["bytes"].as_u64(), Some(size), "{info}");
    assert!(info["frames"].as_u64().unwrap() > 10, "{info}");
    ok(addr, r#"{"op":"replay","take":"killed","scene":"again"}"#).await;
    let watcher = Watcher::start(addr, "again").await;
    watcher
        .until("replayed frames", |f| {
            f.len() >= 5
                && f.last()
                    .is_some_and(|s| s.poses.contains_key("again.avatar"))
        })
        .await;
}

/// Radians between two rotations, precise near zero.
fn angle(a: glam::Quat, b: glam::Quat) -> f32 {
    let d = a.conjugate() * b;
    2.0 * glam::Vec3::new(d.x, d.y, d.z).length().min(1.0).asin()
}

/// The take's own frames as the reference for its exports: each avatar's pose at each frame
/// time (seconds from the take's first frame), decoded from the take.
fn take_frames(
    server: &posecast_server::startup::Server,
    take: &str,
) -> Vec<(f64, BTreeMap<String, AvatarPose>)> {
    let index = server.state.takes.index(take).unwrap();
    let source = server.state.takes.source(take).unwrap();
    let first = index.first_seq().unwrap();
    let rate = f64::from(index.header.tick_rate);
    let mut reader = posecast_server::stream::take::TakeReader::new(source, index.clone());
    (0..index.frames.len())
        .map(|i| {
            let poses = reader.poses(i).unwrap();
            let t = (index.frames[i].seq - first) as f64 / rate;
            let poses = poses
                .iter()
                .map(|p| (p.description.id.0.clone(), p.pose.clone()))
                .collect();
            (t, poses)
        })
        .collect()
}

/// Records two avatars (one moving across the scene, the other driven live for a while): the
/// take names its driver. Exported as BVH and glTF, every frame's local rotations are the
/// take's within the formats' precision, the roots carrying the placement (scene space); a
/// range exports only its frames. Replayed, an avatar can be driven live over the replay.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_take_notes_its_drivers_and_exports_in_scene_space() {
    let server = common::server(30.0).await;
    let addr = server.addr;
    ok(
        addr,
        r#"{"op":"add_avatar","scene":"default","asset":"avatar","avatar":"b"}"#,
    )
    .await;
    ok(addr, r#"{"op":"play","avatar":"b","clip":"wave"}"#).await;
    let scene = server
        .state
        .world
        .scene(&SceneId("default".into()))
        .unwrap();
    let mut ticks = scene.ticks();
    ok(
        addr,
        r#"{"op":"record_scene","scene":"default","take":"t"}"#,
    )
    .await;
    ok(
        addr,
        r#"{"op":"place_avatar","avatar":"avatar","position":[2,0,-1],"rotation":[0,0.7071068,0,0.7071068],"duration":1}"#,
    )
    .await;
    // Avatar b driven live for a while: the take notes who drove it.
    let driver = posecast_client::net::Driver::connect(
        &format!("ws://{addr}/ws"),
        Some(common::CONTROL.to_owned()),
    )
    .await
    .unwrap();
    let b = posecast_proto::msg::AvatarId("b".into());
    driver.drive(&b, None, None).await.unwrap();
    for k in 0..20u64 {
        let q = glam::Quat::from_rotation_x(0.02 * k as f32);
        driver
            .send_pose(&b, [("l_elbow".into(), q.to_array())], None, Some(k))
            .await
            .unwrap();
        ticks.changed().await.unwrap();
    }
    drop(driver);
    for _ in 0..40 {
        ticks.changed().await.unwrap();
    }
    let info = ok(addr, r#"{"op":"stop_recording_scene","scene":"default"}"#).await;
    assert_eq!(
        info["drivers"],
        serde_json::json!([{"avatar": "b", "name": "test", "via": "websocket"}]),
        "{info}"
    );
    let frames = take_frames(&server, "t");
    assert!(frames.len() >= 50, "{}", frames.len());

    let (status, bvh) = common::get_bytes(addr, "/api/takes/t/avatar.bvh").await;
    assert_eq!(status, 200, "{}", String::from_utf8_lossy(&bvh));
    let text = String::from_utf8(bvh).unwrap();
    let back = posecast_server::import::bvh::parse("t.bvh", &text).unwrap();
    let rig = server.state.world.library.get("avatar").unwrap();
    let names = rig.skeleton().names();
    let d = &server
        .state
        .world
        .scene(&SceneId("default".into()))
        .unwrap()
        .lock()
        .avatars[0]
        .description
        .clone();
    let clip = &back.clips[0];
    let mut got = back.skeleton.rest().to_vec();
    let (mut worst, mut worst_root, mut moved) = (0.0f32, 0.0f32, 0.0f32);
    for (t, poses) in &frames {
        let want = &poses["avatar"];
        clip.sample(*t as f32, back.skeleton.rest(), &mut got);
        for (j, name) in names.iter().enumerate() {
            let k = back.skeleton.find(name).unwrap();
            let parent_is_root = d.parents[j] < 0;
            let w = if parent_is_root {
                want.placement.rotation * want.rotations[j]
            } else {
                want.rotations[j]
            };
            let a = angle(w, got[k].rotation).to_degrees();
            if parent_is_root {
                worst_root = worst_root.max(a);
                let at = d
                    .translated_joints
                    .iter()
                    .position(|&tj| usize::from(tj) == j);
                if let Some(at) = at {
                    let p =
                        want.placement.position + want.placement.rotation * want.translations[at];
                    // The BVH holds centimetres; its raw import keeps them.
                    let cm = posecast_server::export::bvh::CENTIMETRES_PER_METRE;
                    let back = got[k].translation / cm;
                    assert!(
                        (p - back).length() < 1e-4,
                        "root at {t}: {p} against {back}"
                    );
                    moved = moved.max(want.placement.position.length());
                }
            } else {
                worst = worst.max(a);
            }
        }
    }
    eprintln!("BVH against the take: worst {worst:.4}° (joints), {worst_root:.4}° (root)");
    assert!(worst < 0.01 && worst_root < 0.01, "{worst} {worst_root}");
    assert!(moved > 1.0, "the placement moved the root in scene space");

    // The whole take as glTF: valid, every avatar a skin of its own, and the one animation
    // moving each as the take does.
    let (status, glb) = common::get_bytes(addr, "/api/takes/t.glb").await;
    assert_eq!(status, 200, "{}", String::from_utf8_lossy(&glb));
    posecast_proto::testing::assert_valid_gltf(&[("take", glb.clone())]);
    let assets = posecast_server::import::gltf::from_slice("t.glb", &glb).unwrap();
    assert_eq!(assets.len(), 2, "one rig per avatar");
    let mut checked = 0;
    for asset in &assets {
        let id = ["avatar", "b"]
            .into_iter()
            .find(|id| asset.name.ends_with(&format!("#{id}")) || asset.name == *id)
            .unwrap_or_else(|| panic!("asset {} is named after no avatar", asset.name));
        let clip = &asset.clips[0];
        let mut got = asset.skeleton.rest().to_vec();
        let mut worst = 0.0f32;
        for (t, poses) in &frames {
            let want = &poses[id];
            clip.sample(*t as f32, asset.skeleton.rest(), &mut got);
            for (j, name) in names.iter().enumerate() {
                let k = asset.skeleton.find(name).unwrap();
                let w = if d.parents[j] < 0 {
                    want.placement.rotation * want.rotations[j]
                } else {
                    want.rotations[j]
                };
                worst = worst.max(angle(w, got[k].rotation).to_degrees());
            }
        }
        eprintln!("glTF against the take, {id}: worst {worst:.6}°");
        assert!(worst < 1e-3, "{id}: {worst}°");
        checked += 1;
    }
    assert_eq!(checked, 2);

    // A range: only its frames.
    let (status, part) = common::get_bytes(addr, "/api/takes/t/avatar.bvh?from=0.5&to=1").await;
    assert_eq!(status, 200);
    let part = String::from_utf8(part).unwrap();
    let n: usize = part
        .lines()
        .find_map(|l| l.strip_prefix("Frames: "))
        .unwrap()
        .trim()
        .parse()
        .unwrap();
    assert!((14..=17).contains(&n), "half a second at 30 Hz: {n} frames");
    // A replayed avatar driven live: the driver's pose over the replay, the other avatar
    // still replaying the take.
    ok(
        addr,
        r#"{"op":"replay","take":"t","scene":"rr","loop":true}"#,
    )
    .await;
    let watcher = Watcher::start(addr, "rr").await;
    let driver = posecast_client::net::Driver::connect(
        &format!("ws://{addr}/ws"),
        Some(common::CONTROL.to_owned()),
    )
    .await
    .unwrap();
    let rb = posecast_proto::msg::AvatarId("rr.b".into());
    driver.drive(&rb, None, None).await.unwrap();
    let elbow = rig.skeleton().find("l_elbow").unwrap();
    let q = glam::Quat::from_rotation_z(1.0);
    let mut rr_ticks = server
        .state
        .world
        .scene(&SceneId("rr".into()))
        .unwrap()
        .ticks();
    let mut k = 0u64;
    let driven = tokio::time::timeout(PATIENCE, async {
        loop {
            driver
                .send_pose(&rb, [("l_elbow".into(), q.to_array())], None, Some(k))
                .await
                .unwrap();
            k += 1;
            rr_ticks.changed().await.unwrap();
            let seen = watcher.frames();
            let driven = seen.iter().rev().take(3).any(|s| {
                s.poses
                    .get("rr.b")
                    .is_some_and(|p| angle(p.rotations[elbow], q).to_degrees() < 0.01)
            });
            if driven {
                return seen;
            }
        }
    })
    .await
    .expect("the driver's pose shows on the replayed avatar");
    let last = driven.last().unwrap();
    let replaying = frames.iter().any(|(_, poses)| {
        let (want, got) = (&poses["avatar"], &last.poses["rr.avatar"]);
        want.rotations == got.rotations && want.placement == got.placement
    });
    assert!(replaying, "the avatar not driven still replays the take");
    drop(driver);
    drop(watcher);

    for (path, code) in [
        ("/api/takes/t/nobody.bvh", 404),
        ("/api/takes/none/avatar.bvh", 404),
        ("/api/takes/t/avatar.bvh?from=2&to=1", 400),
    ] {
        let (status, body) = common::get_bytes(addr, path).await;
        assert_eq!(status, code, "{path}: {}", String::from_utf8_lossy(&body));
    }
}

/// A take's bytes count toward the data quota: with room for only a few seconds it ends by
/// itself, its bytes within the quota, and an upload after it is refused for the bytes it holds;
/// deleting it gives them back.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_take_ends_at_the_data_quota_and_holds_its_bytes() {
    const QUOTA: u64 = 100_000;
    let data = tempfile::tempdir().unwrap();
    let server = common::kit_builder(60.0)
        .data_dir(data.path())
        .configure(|c| c.quotas.max_upload_total_bytes = QUOTA)
        .start()
        .await
        .unwrap()
        .into_server();
    let addr = server.addr;
    let started = ok(
        addr,
        r#"{"op":"record_scene","scene":"default","take":"big"}"#,
    )
    .await;
    assert_eq!(started["recording"], true);
    assert_eq!(common::metric(addr, "posecast_takes_recording").await, 1.0);
    let ended = tokio::time::timeout(PATIENCE, async {
        loop {
            let info = ok(addr, r#"{"op":"get_take","take":"big"}"#).await;
            if info["recording"] == false {
                return info;
            }
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    })
    .await
    .expect("the take ends by itself at the quota");
    let bytes = ended["bytes"].as_u64().unwrap();
    assert!(bytes <= QUOTA && bytes > QUOTA / 2, "{ended}");
    assert_eq!(
        common::metric(addr, "posecast_takes_ended_by_themselves_total").await,
        1.0
    );
    assert_eq!(common::metric(addr, "posecast_takes_recording").await, 0.0);
    let info = ok(addr, r#"{"op":"stop_recording_scene","scene":"default"}"#).await;
    assert_eq!(info["bytes"].as_u64(), Some(bytes), "{info}");
    let file = data.path().join("takes/big.take");
    assert_eq!(std::fs::metadata(&file).unwrap().len(), bytes);
    assert_eq!(
        server.state.takes.held_bytes(),
        bytes,
        "the take holds its bytes"
    );
    for name in [
        "posecast_takes_held_bytes",
        "posecast_take_bytes_written_total",
    ] {
        assert_eq!(common::metric(addr, name).await, bytes as f64, "{name}");
    }
    // A second take has no room left.
    let (status, body) = command_to(
        addr,
        r#"{"op":"record_scene","scene":"default","take":"more"}"#,
    )
    .await;
    assert_eq!(
        (status, body["code"].as_str()),
        (429, Some("quota_exceeded")),
        "{body}"
    );
    ok(addr, r#"{"op":"delete_take","take":"big"}"#).await;
    assert!(!file.exists());
    assert_eq!(common::metric(addr, "posecast_takes_held_bytes").await, 0.0);
    ok(
        addr,
        r#"{"op":"record_scene","scene":"default","take":"more"}"#,
    )
    .await;
}

/// A take shows the scene it recorded: with private views, a token limited to another scene
/// neither lists it, reads it, replays it nor exports it; the control token does all four.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_take_shows_only_to_who_may_watch_its_scene() {
    use posecast_server::auth::{Role, Secret, TokenRule};
    const LOBBY: &str = "lobby-control-token";
    let mut access = common::test_access();
    access.open_view = false;
    let mut lobby = TokenRule::new("lobby", Secret::new(LOBBY), Role::Control);
    lobby.scenes = Some(vec![SceneId("lobby".into())]);
    access.add(lobby).unwrap();
    let server = common::server_with(30.0, access).await;
    let addr = server.addr;
    let scene = server
        .state
        .world
        .scene(&SceneId("default".into()))
        .unwrap();
    let mut ticks = scene.ticks();
    ok(
        addr,
        r#"{"op":"record_scene","scene":"default","take":"private"}"#,
    )
    .await;
    for _ in 0..5 {
        ticks.changed().await.unwrap();
    }
    ok(addr, r#"{"op":"stop_recording_scene","scene":"default"}"#).await;
    let as_lobby = |method: &'static str, path: String, body: Option<&'static str>| async move {
        let (status, body) = common::http_request(
            addr,
            Some(LOBBY),
            method,
            &path,
            "application/json",
            body.unwrap_or("").as_bytes(),
        )
        .await;
        (status, body)
    };
    let (status, body) = as_lobby(
        "POST",
        "/api/commands".into(),
        Some(r#"{"op":"list_takes"}"#),
    )
    .await;
    assert_eq!(status, 200, "{body}");
    assert!(!body.contains("private"), "{body}");
    for (method, path, command) in [
        (
            "POST",
            "/api/commands",
            Some(r#"{"op":"get_take","take":"private"}"#),
        ),
        (
            "POST",
            "/api/commands",
            Some(r#"{"op":"replay","take":"private","scene":"lobby"}"#),
        ),
        ("GET", "/api/takes/private", None),
        ("GET", "/api/takes/private.glb", None),
        ("GET", "/api/takes/private/avatar.bvh", None),
    ] {
        let (status, body) = as_lobby(method, path.to_owned(), command).await;
        assert_eq!(status, 403, "{path} {command:?}: {body}");
    }
    let listed = ok(addr, r#"{"op":"list_takes"}"#).await;
    assert_eq!(listed[0]["take"], "private", "{listed}");
    let (status, _) = common::get_bytes(addr, "/api/takes/private/avatar.bvh").await;
    assert_eq!(status, 200);
}
