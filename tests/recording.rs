//! Recording (issue 16): `record` … `stop_recording` over REST against a server with a data
//! folder. What the avatar streamed to a subscriber is what the recorded clip holds; the clip
//! plays at once, exports as glTF the Khronos validator accepts and as BVH, and is back on its
//! rig after a restart.

#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use common::{command_to, get_bytes, next_text, test_access};
use futures_util::SinkExt;
use posecast_proto::Transform;
use posecast_proto::msg::{ClientMsg, Encoding, ErrorCode, SceneId, ServerMsg};
use posecast_proto::testing::assert_valid_gltf;
use posecast_server::clip::Clip;
use posecast_server::config::Config;
use posecast_server::startup::Server;
use std::collections::BTreeMap;
use std::path::Path;
use std::time::Duration;
use tokio_tungstenite::tungstenite::Message;

const RATE: f32 = 30.0;

async fn start(data: &Path) -> Server {
    let server = Server::start(Config {
        listen: "127.0.0.1:0".parse().unwrap(),
        tick_rate: RATE,
        access: test_access(),
        data_dir: Some(data.to_owned()),
        ..Config::default()
    })
    .await
    .unwrap();
    server.ready().await.unwrap();
    server
}

async fn ok(server: &Server, json: &str) -> serde_json::Value {
    let (status, body) = command_to(server.addr, json).await;
    assert_eq!(status, 200, "{json} → {body}");
    body["result"].clone()
}

async fn refused(server: &Server, json: &str) -> String {
    let (status, body) = command_to(server.addr, json).await;
    assert_ne!(status, 200, "{json} was accepted: {body}");
    body["code"].as_str().unwrap_or_default().to_owned()
}

/// The recorded clip read back from an export, sampled at each of its keys (one per tick).
fn clip_from_glb(bytes: &[u8], name: &str) -> (Clip, Vec<Transform>) {
    let asset = posecast_server::import::gltf::from_slice("take.glb", bytes)
        .unwrap()
        .remove(0);
    let clip = asset
        .clips
        .iter()
        .find(|c| c.name() == name)
        .unwrap_or_else(|| panic!("no clip {name} in the export"))
        .clone();
    (clip, asset.skeleton.rest().to_vec())
}

fn angle(a: [f32; 4], b: glam::Quat) -> f32 {
    let d = glam::Quat::from_array(a).dot(b).abs().min(1.0);
    2.0 * d.acos()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_recording_holds_what_was_streamed_exports_and_survives_a_restart() {
    let data = tempfile::tempdir().unwrap();
    let server = start(data.path()).await;
    ok(
        &server,
        r#"{"op":"play","avatar":"avatar","clip":"walk","root_motion":"accumulate"}"#,
    )
    .await;

    // A JSON subscriber keeps every streamed pose of the avatar, by tick.
    let mut ws = common::raw(&server, Encoding::Json).await;
    let subscribe = ClientMsg::Subscribe {
        scene: SceneId("default".into()),
        avatars: None,
        rate: None,
        joints: None,
        morph_weights: None,
        precision: None,
    };
    ws.send(Message::Text(
        serde_json::to_string(&subscribe).unwrap().into(),
    ))
    .await
    .unwrap();
    let streamed = std::sync::Arc::new(std::sync::Mutex::new(BTreeMap::new()));
    let reader = {
        let streamed = streamed.clone();
        tokio::spawn(async move {
            while let Some(msg) = next_text(&mut ws).await {
                if let ServerMsg::Frame(f) = msg {
                    let pose = f.avatars.into_iter().find(|a| a.avatar.0 == "avatar");
                    if let Some(p) = pose {
                        streamed.lock().unwrap().insert(f.seq, p.rotations);
                    }
                }
            }
        })
    };

    // Bad requests first: none of them starts anything.
    assert_eq!(
        refused(
            &server,
            r#"{"op":"record","avatar":"avatar","clip":"walk"}"#
        )
        .await,
        "conflict"
    );
    assert_eq!(
        refused(&server, r#"{"op":"record","avatar":"avatar","clip":"a/b"}"#).await,
        "invalid_value"
    );
    assert_eq!(
        refused(&server, r#"{"op":"stop_recording","avatar":"avatar"}"#).await,
        "not_allowed_now"
    );
    ok(
        &server,
        r#"{"op":"record","avatar":"avatar","clip":"take"}"#,
    )
    .await;
    assert_eq!(
        refused(
            &server,
            r#"{"op":"record","avatar":"avatar","clip":"again"}"#
        )
        .await,
        "conflict"
    );
    let state = ok(&server, r#"{"op":"get_avatar","avatar":"avatar"}"#).await;
    assert_eq!(state["recording"], "take", "{state}");
    tokio::time::sleep(Duration::from_millis(1500)).await;
    let info = ok(&server, r#"{"op":"stop_recording","avatar":"avatar"}"#).await;
    tokio::time::sleep(Duration::from_millis(200)).await;
    reader.abort();
    let frames = info["frames"].as_u64().unwrap() as usize;
    assert!(frames >= 30, "{info}");
    assert_eq!(
        (info["asset"].as_str(), info["clip"].as_str()),
        (Some("avatar"), Some("take"))
    );

    // Exported as glTF: valid, and holding one key per recorded tick.
    let (status, glb) = get_bytes(server.addr, "/api/assets/avatar/clips/take.glb").await;
    assert_eq!(status, 200, "{}", String::from_utf8_lossy(&glb));
    assert_valid_gltf(&[("recorded-take", glb.clone())]);
    let (clip, rest) = clip_from_glb(&glb, "take");
    let joints = rest.len();

    // The recording is the stream: some run of consecutive streamed ticks equals the clip's
    // poses at 0, 1/rate, 2/rate, … (the JSON stream is not quantised: f32 rounding only).
    let streamed = streamed.lock().unwrap().clone();
    let mut pose = vec![Transform::IDENTITY; joints];
    let recorded: Vec<Vec<glam::Quat>> = (0..frames)
        .map(|k| {
            clip.sample(k as f32 / RATE, &rest, &mut pose);
            pose.iter().map(|t| t.rotation).collect()
        })
        .collect();
    // A subscriber on a busy machine may miss a tick (the newest frame wins in its outbox):
    // compare on the ticks it saw, which must be most of them.
    let worst_at = |first: u64| -> Option<f32> {
        let (mut worst, mut seen) = (0.0f32, 0usize);
        for (k, want) in recorded.iter().enumerate() {
            let Some(got) = streamed.get(&(first + k as u64)) else {
                continue;
            };
            seen += 1;
            for (g, w) in got.iter().zip(want) {
                worst = worst.max(angle(*g, *w));
            }
        }
        (seen * 10 >= recorded.len() * 8).then_some(worst)
    };
    let (first, worst) = streamed
        .keys()
        .filter_map(|&s| worst_at(s).map(|w| (s, w)))
        .min_by(|a, b| a.1.total_cmp(&b.1))
        .expect("the subscriber saw at least 80 % of the recorded ticks");
    eprintln!("recording starts at tick {first}; worst joint difference {worst:.2e} rad");
    assert!(
        worst < 1e-4,
        "the recording differs from the stream by {worst} rad"
    );

    // BVH: the same number of frames.
    let (status, bvh) = get_bytes(server.addr, "/api/assets/avatar/clips/take.bvh").await;
    assert_eq!(status, 200);
    let bvh = String::from_utf8(bvh).unwrap();
    let frames_line = bvh.lines().find(|l| l.starts_with("Frames:")).unwrap();
    assert_eq!(
        frames_line.trim(),
        format!("Frames: {frames}"),
        "{frames_line}"
    );
    let (status, _) = get_bytes(server.addr, "/api/assets/avatar/clips/nope.glb").await;
    assert_eq!(status, 404);

    // Playable at once, by name, on the avatar that recorded it.
    ok(&server, r#"{"op":"play","avatar":"avatar","clip":"take"}"#).await;
    let state = ok(&server, r#"{"op":"get_avatar","avatar":"avatar"}"#).await;
    assert_eq!(state["clip"], "take");
    assert!(state.get("recording").is_none(), "{state}");
    server.stop().await;
    assert!(data.path().join("recordings/avatar/take.glb").is_file());

    // After a restart the clip is back on the rig, the scene still plays it, and it
    // exports to the same poses.
    let server = start(data.path()).await;
    let assets = ok(&server, r#"{"op":"list_assets"}"#).await;
    let clips: Vec<&str> = assets
        .as_array()
        .unwrap()
        .iter()
        .find(|a| a["name"] == "avatar")
        .unwrap()["clips"]
        .as_array()
        .unwrap()
        .iter()
        .filter_map(|c| c["name"].as_str())
        .collect();
    assert!(clips.contains(&"take"), "{clips:?}");
    let state = ok(&server, r#"{"op":"get_avatar","avatar":"avatar"}"#).await;
    assert_eq!(state["clip"], "take", "{state}");
    let (_, again) = get_bytes(server.addr, "/api/assets/avatar/clips/take.glb").await;
    let (back, _) = clip_from_glb(&again, "take");
    let mut other = vec![Transform::IDENTITY; joints];
    for k in 0..frames {
        let t = k as f32 / RATE;
        clip.sample(t, &rest, &mut pose);
        back.sample(t, &rest, &mut other);
        for (a, b) in pose.iter().zip(&other) {
            assert!(a.rotation.angle_between(b.rotation) < 1e-5, "tick {k}");
        }
    }
    server.stop().await;
}

/// Recording changes the world: it needs a control token. Exports are reads.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn recording_needs_control_and_exports_are_reads() {
    let server = common::server(30.0).await;
    let (status, body) = common::http_as(
        &server,
        None,
        "POST",
        "/api/commands",
        Some(r#"{"op":"record","avatar":"avatar","clip":"x"}"#),
    )
    .await;
    assert_eq!(status, 401, "{body}");
    let code: serde_json::Value = serde_json::from_str(&body).unwrap();
    assert_eq!(code["code"], serde_json::json!(ErrorCode::Unauthorized));
    let (status, _) = common::http_as(
        &server,
        None,
        "GET",
        "/api/assets/avatar/clips/walk.bvh",
        None,
    )
    .await;
    assert_eq!(status, 200, "views are open on this server");
    server.stop().await;
}

/// Records `clip` on avatar `avatar` for a few ticks and stops; the stop's answer (status,
/// body). A stop before the first tick ("nothing to keep") is retried with a longer take.
async fn take(server: &Server, avatar: &str, clip: &str) -> (u16, serde_json::Value) {
    let record = serde_json::json!({"op": "record", "avatar": avatar, "clip": clip}).to_string();
    let stop = serde_json::json!({"op": "stop_recording", "avatar": avatar}).to_string();
    for attempt in 1..=20u64 {
        let (status, body) = command_to(server.addr, &record).await;
        assert_eq!(status, 200, "{record} → {body}");
        tokio::time::sleep(Duration::from_millis(100 * attempt)).await;
        let (status, body) = command_to(server.addr, &stop).await;
        if body["code"] != "invalid_value" {
            return (status, body);
        }
    }
    panic!("no tick was recorded in 20 tries");
}

/// The names of rig `rig`'s clips.
async fn clip_names(server: &Server, rig: &str) -> Vec<String> {
    let assets = ok(server, r#"{"op":"list_assets"}"#).await;
    assets
        .as_array()
        .unwrap()
        .iter()
        .find(|a| a["name"] == rig)
        .unwrap()["clips"]
        .as_array()
        .unwrap()
        .iter()
        .filter_map(|c| c["name"].as_str().map(str::to_owned))
        .collect()
}

/// Issue 37: takes named like the store's own files (hidden, parent-ish, its upload prefix
/// and its set-aside suffix) are acknowledged, so they must be back after a clean restart,
/// and an avatar that played one plays it again.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn takes_named_like_the_stores_files_survive_a_restart() {
    let data = tempfile::tempdir().unwrap();
    let server = start(data.path()).await;
    let names = [
        ".hidden",
        "..x",
        ".upload-zz",
        "a.corrupt",
        "b.tmp",
        "c.glb",
        "..",
        ".",
    ];
    for name in names {
        let (status, body) = take(&server, "avatar", name).await;
        assert_eq!(status, 200, "{name}: {body}");
    }
    let play = r#"{"op":"play","avatar":"avatar","clip":".upload-zz"}"#;
    ok(&server, play).await;
    server.stop().await;

    let server = start(data.path()).await;
    let clips = clip_names(&server, "avatar").await;
    for name in names {
        assert!(clips.iter().any(|c| c == name), "{name} lost: {clips:?}");
    }
    let state = ok(&server, r#"{"op":"get_avatar","avatar":"avatar"}"#).await;
    assert_eq!(state["clip"], ".upload-zz", "{state}");
    server.stop().await;
}

/// A tmpfs of `kib` KiB mounted on a new folder, unmounted on drop; `None` (a skip, a
/// failure under `CI=true`) where mounting is not allowed.
struct Tmpfs(tempfile::TempDir);

impl Tmpfs {
    fn mount(kib: u32) -> Option<Self> {
        let dir = tempfile::tempdir().unwrap();
        let status = std::process::Command::new("mount")
            .args(["-t", "tmpfs", "-o", &format!("size={kib}k"), "tmpfs"])
            .arg(dir.path())
            .status();
        match status {
            Ok(s) if s.success() => Some(Self(dir)),
            other => {
                posecast_proto::testing::skip(&format!("cannot mount a tmpfs here: {other:?}"));
                None
            }
        }
    }
}

impl Drop for Tmpfs {
    fn drop(&mut self) {
        let _unmounted = std::process::Command::new("umount")
            .arg(self.0.path())
            .status();
    }
}

/// Fills the file system under `dir` with `dir/filler` until it refuses another byte.
fn fill(dir: &Path) {
    use std::io::Write;
    let mut f = std::fs::File::create(dir.join("filler")).unwrap();
    let chunk = vec![0u8; 4096];
    while f.write_all(&chunk).is_ok() {}
    while f.write_all(&[0]).is_ok() {}
    let _ = f.sync_all();
}

/// Issue 37: a full disk at `stop_recording` answers the typed `storage_full`, leaves no file
/// behind and frees the name: the same take, recorded again once there is room, is stored and
/// restored.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_full_disk_refuses_a_take_with_storage_full_and_frees_its_name() {
    let Some(disk) = Tmpfs::mount(2048) else {
        return;
    };
    let data = disk.0.path().join("data");
    let server = start(&data).await;
    // The disk fills up while the take runs (a full disk refuses `record`'s scene write too).
    ok(
        &server,
        r#"{"op":"record","avatar":"avatar","clip":"full"}"#,
    )
    .await;
    let recorded = common::wait_for(60.0, || {
        server
            .state
            .world
            .find_avatar(&posecast_proto::msg::AvatarId("avatar".into()))
            .ok()
            .and_then(|scene| {
                let s = scene.lock();
                s.avatars
                    .iter()
                    .find(|a| a.id.0 == "avatar")
                    .and_then(|a| a.recording.as_ref().map(|r| r.frames() > 1))
            })
            .unwrap_or(false)
    })
    .await;
    assert!(recorded, "no tick recorded");
    fill(disk.0.path());
    let (status, body) =
        command_to(server.addr, r#"{"op":"stop_recording","avatar":"avatar"}"#).await;
    assert_eq!(
        (status, body["code"].as_str()),
        (507, Some("storage_full")),
        "{body}"
    );
    assert!(
        !clip_names(&server, "avatar")
            .await
            .contains(&"full".to_owned())
    );
    let left: Vec<_> = std::fs::read_dir(data.join("recordings/avatar"))
        .map(|d| d.filter_map(Result::ok).map(|e| e.file_name()).collect())
        .unwrap_or_default();
    assert!(left.is_empty(), "half-written files left: {left:?}");

    std::fs::remove_file(disk.0.path().join("filler")).unwrap();
    let (status, body) = take(&server, "avatar", "full").await;
    assert_eq!(status, 200, "the name stayed taken: {body}");
    server.stop().await;
    let server = start(&data).await;
    assert!(
        clip_names(&server, "avatar")
            .await
            .contains(&"full".to_owned())
    );
    server.stop().await;
}
