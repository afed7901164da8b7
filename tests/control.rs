//! End-to-end control surface over REST: commands change the pose stream; bad requests get
//! typed errors and change nothing; `/metrics` parses and moves.

#![allow(clippy::unwrap_used)]

mod common;

use common::{client, http, server, wait_for};
use posecast_proto::msg::{AvatarId, Encoding};
use posecast_proto::quant::{MAX_ERROR_DEGREES, angle_between_degrees};

#[tokio::test]
async fn rest_commands_change_the_stream_and_errors_are_typed() {
    let server = server(60.0).await;
    let c = client(&server, Encoding::Binary).await;
    let id = AvatarId("avatar".into());
    assert!(wait_for(3.0, || c.latest(&id).is_some()).await);

    let (status, body) = http(&server, "GET", "/api/scenes", None).await;
    assert_eq!(status, 200, "{body}");
    let scenes: serde_json::Value = serde_json::from_str(&body).unwrap();
    assert_eq!(scenes[0]["scene"], "default");
    assert_eq!(scenes[0]["avatars"][0]["clip"], "idle");

    let set = r#"{"op":"set_joint_rotation","avatar":"avatar","joint":"l_knee","rotation":[0.3826834,0,0,0.9238795]}"#;
    let (status, body) = http(&server, "POST", "/api/commands", Some(set)).await;
    assert_eq!(status, 200, "{body}");
    let knee = c.avatar(&id).unwrap().skeleton.find("l_knee").unwrap();
    let expected = glam::Quat::from_rotation_x(std::f32::consts::FRAC_PI_4);
    assert!(
        wait_for(2.0, || c.latest(&id).is_some_and(
            |p| angle_between_degrees(p.locals[knee].rotation, expected) <= MAX_ERROR_DEGREES
        ))
        .await,
        "the override never reached the stream"
    );

    // Typed errors, nothing changed.
    for (body, status, code) in [
        (
            r#"{"op":"seek","avatar":"nobody","time":1}"#,
            404,
            "unknown_avatar",
        ),
        (
            r#"{"op":"set_joint_rotation","avatar":"avatar","joint":"tail","rotation":[0,0,0,1]}"#,
            404,
            "unknown_joint",
        ),
        (
            r#"{"op":"set_joint_rotation","avatar":"avatar","joint":"l_knee","rotation":[0,0,0,0]}"#,
            400,
            "invalid_value",
        ),
        (r#"{"op":"fly"}"#, 400, "bad_message"),
        ("garbage", 400, "bad_message"),
    ] {
        let (s, b) = http(&server, "POST", "/api/commands", Some(body)).await;
        assert_eq!(s, status, "{body} → {b}");
        let e: serde_json::Value = serde_json::from_str(&b).unwrap();
        assert_eq!(e["code"], code, "{b}");
    }
    let seq = c.latest(&id).unwrap().seq;
    assert!(wait_for(2.0, || c.latest(&id).is_some_and(|p| p.seq > seq + 2)).await);
    assert!(
        angle_between_degrees(c.latest(&id).unwrap().locals[knee].rotation, expected)
            <= MAX_ERROR_DEGREES
    );

    // Metrics parse as Prometheus text and move.
    let (status, metrics) = http(&server, "GET", "/metrics", None).await;
    assert_eq!(status, 200);
    let value = |text: &str, name: &str| -> f64 {
        text.lines()
            .filter(|l| !l.starts_with('#'))
            .find_map(|l| {
                l.strip_prefix(name)
                    .and_then(|rest| rest.trim().parse().ok())
            })
            .unwrap_or_else(|| panic!("no sample {name}"))
    };
    for line in metrics
        .lines()
        .filter(|l| !l.starts_with('#') && !l.is_empty())
    {
        let (name, v) = line.rsplit_once(' ').unwrap();
        assert!(
            !name.is_empty() && v.parse::<f64>().is_ok(),
            "bad sample line {line:?}"
        );
    }
    let commands = value(&metrics, "posecast_commands_total");
    let errors = value(&metrics, "posecast_command_errors_total");
    assert!(
        commands >= 5.0 && errors >= 3.0,
        "commands {commands}, errors {errors}"
    );
    tokio::time::sleep(std::time::Duration::from_millis(100)).await;
    let (_, later) = http(&server, "GET", "/metrics", None).await;
    assert!(
        value(&later, "posecast_frames_offered_total")
            > value(&metrics, "posecast_frames_offered_total")
    );
    server.stop().await;
}

#[tokio::test]
async fn a_bvh_clip_plays_retargeted_on_the_built_in_avatar() {
    let Some(path) = posecast_proto::testing::require_testdata("bvh/cmu/01_01.bvh") else {
        return;
    };
    let server = server(60.0).await;
    let mut asset = posecast_server::import::load_path(&path).unwrap().remove(0);
    asset.name = "cmu".into();
    let clip = asset.clips[0].name().to_string();
    let rig = posecast_server::rig::Rig::from_asset(asset, &Default::default()).unwrap();
    server.state.world.library.insert(rig);
    let c = client(&server, Encoding::Binary).await;
    let id = AvatarId("avatar".into());
    assert!(wait_for(3.0, || c.latest(&id).is_some()).await);
    let before = c.latest(&id).unwrap().locals;
    let play =
        format!(r#"{{"op":"play","avatar":"avatar","clip":"{clip}","from_asset":"cmu","fade":0}}"#);
    let (status, body) = http(&server, "POST", "/api/commands", Some(&play)).await;
    assert_eq!(status, 200, "{body}");
    let (_, state) = http(
        &server,
        "POST",
        "/api/commands",
        Some(r#"{"op":"get_avatar","avatar":"avatar"}"#),
    )
    .await;
    let state: serde_json::Value = serde_json::from_str(&state).unwrap();
    assert_eq!(state["result"]["clip_asset"], "cmu", "{state}");
    let seq = c.latest(&id).unwrap().seq;
    assert!(wait_for(2.0, || c.latest(&id).is_some_and(|p| p.seq > seq + 3)).await);
    let after = c.latest(&id).unwrap().locals;
    assert!(
        after
            .iter()
            .all(|t| t.rotation.is_finite() && t.translation.is_finite())
    );
    let moved = before
        .iter()
        .zip(&after)
        .filter(|(a, b)| a.rotation.dot(b.rotation).abs() < 0.999)
        .count();
    assert!(
        moved >= 5,
        "only {moved} joints changed under the retargeted clip"
    );
    server.stop().await;
}

#[tokio::test]
async fn get_joint_reports_the_file_limits_and_the_clamped_values() {
    let server = server(60.0).await;
    let Some(skel) = common::testdata_bytes("cse169/test.skel") else {
        return;
    };
    let (status, body) =
        common::upload_files(server.addr, "/api/assets/testskel", &[("test.skel", &skel)]).await;
    assert_eq!(status, 200, "{body}");
    for command in [
        r#"{"op":"create_scene","scene":"lab"}"#,
        r#"{"op":"add_avatar","scene":"lab","asset":"testskel","avatar":"t1"}"#,
    ] {
        assert_eq!(common::command_to(server.addr, command).await.0, 200);
    }
    let get = r#"{"op":"get_joint","avatar":"t1","joint":"knee_r"}"#;
    let joint = |v: &serde_json::Value| -> Vec<(f64, Option<f64>, Option<f64>)> {
        v["result"]["dofs"]
            .as_array()
            .unwrap()
            .iter()
            .map(|d| {
                (
                    d["value"].as_f64().unwrap(),
                    d["min"].as_f64(),
                    d["max"].as_f64(),
                )
            })
            .collect()
    };
    // test.skel: knee_r is a balljoint with rotxlimit -2 0, rotylimit 0 0, rotzlimit 0 0 and
    // pose -3 1 2, which the limits clamp to (-2, 0, 0).
    let (status, info) = common::command_to(server.addr, get).await;
    assert_eq!(status, 200, "{info}");
    assert_eq!(info["result"]["joint_type"], "ball_euler");
    assert_eq!(info["result"]["parent"], "hip_r");
    assert_eq!(info["result"]["overridden"], false);
    let dofs = joint(&info);
    let limits: Vec<_> = dofs.iter().map(|d| (d.1, d.2)).collect();
    assert_eq!(
        limits,
        vec![
            (Some(-2.0), Some(0.0)),
            (Some(0.0), Some(0.0)),
            (Some(0.0), Some(0.0))
        ]
    );
    assert!((dofs[0].0 + 2.0).abs() < 1e-4, "{dofs:?}");
    // A value past the limit is clamped; get_joint then reads it back from the pose.
    for (sent, expected) in [(1.0, 0.0), (-1.25, -1.25), (-5.0, -2.0)] {
        let set = format!(
            r#"{{"op":"set_joint_dofs","avatar":"t1","joint":"knee_r","values":[{sent},0.4,0]}}"#
        );
        assert_eq!(common::command_to(server.addr, &set).await.0, 200);
        let (_, info) = common::command_to(server.addr, get).await;
        let dofs = joint(&info);
        assert!((dofs[0].0 - expected).abs() < 1e-4, "{sent}: {dofs:?}");
        assert!(dofs[1].0.abs() < 1e-4, "y is locked at 0: {dofs:?}");
        assert_eq!(info["result"]["overridden"], true);
    }
    // A rig without joint types: no DOFs, set by rotation.
    let (_, info) = common::command_to(
        server.addr,
        r#"{"op":"get_joint","avatar":"avatar","joint":"l_elbow"}"#,
    )
    .await;
    assert_eq!(info["result"]["joint_type"], serde_json::Value::Null);
    assert_eq!(info["result"]["dofs"], serde_json::json!([]));
    assert_eq!(info["result"]["parent"], "l_shoulder");
    server.stop().await;
}

/// `play … from_asset` of a very long clip bakes off the scene locks and off the async
/// workers: while two connections ask for it at once, another scene keeps ticking (no gap of
/// 3 ticks or more in its frame numbers), and a second `play` of the same clip is a cache hit.
#[tokio::test]
async fn a_long_retarget_bake_does_not_stall_other_scenes() {
    use futures_util::{SinkExt, StreamExt};
    use posecast_server::clip::Clip;

    let rate = 20.0;
    let server = server(rate).await;
    // A second humanoid rig whose clip lasts 27,510 s (the reported case): baked at 30 Hz up
    // to the key cap, seconds of CPU in a debug build.
    let mut long = posecast_server::builtin::rig().unwrap();
    let walk = long.clip("walk").unwrap();
    let clip = Clip::new("marathon", walk.channels().to_vec(), Some((0.0, 27_510.0))).unwrap();
    long.name = "long".into();
    long.clips = vec![std::sync::Arc::new(clip)];
    server.state.world.library.insert(long);
    for c in [
        r#"{"op":"create_scene","scene":"other"}"#,
        r#"{"op":"add_avatar","scene":"other","asset":"avatar","avatar":"o"}"#,
    ] {
        assert_eq!(common::command_to(server.addr, c).await.0, 200);
    }

    let mut ws = common::raw(&server, Encoding::Binary).await;
    ws.send(tokio_tungstenite::tungstenite::Message::Text(
        r#"{"type":"subscribe","scene":"default"}"#.into(),
    ))
    .await
    .unwrap();
    let watcher = tokio::spawn(async move {
        // (arrival, seq) of every frame for 60 s or until the test ends it.
        let mut seqs = Vec::new();
        let end = tokio::time::Instant::now() + std::time::Duration::from_secs(60);
        while let Ok(Some(Ok(m))) = tokio::time::timeout_at(end, ws.next()).await {
            if let tokio_tungstenite::tungstenite::Message::Binary(b) = m {
                let (h, _) = posecast_proto::frame::read_header(&b).unwrap();
                seqs.push((std::time::Instant::now(), h.seq));
            }
        }
        seqs
    });
    tokio::time::sleep(std::time::Duration::from_millis(500)).await;

    let play = r#"{"op":"play","avatar":"o","clip":"marathon","from_asset":"long","fade":0}"#;
    let began = std::time::Instant::now();
    let (a, b) = tokio::join!(
        common::command_to(server.addr, play),
        common::command_to(server.addr, play)
    );
    let baked_in = began.elapsed();
    assert_eq!(a.0, 200, "{}", a.1);
    assert_eq!(b.0, 200, "{}", b.1);
    let began_again = std::time::Instant::now();
    assert_eq!(common::command_to(server.addr, play).await.0, 200);
    let cached_in = began_again.elapsed();
    tokio::time::sleep(std::time::Duration::from_millis(300)).await;
    let ended = std::time::Instant::now();
    server.stop().await;
    let seqs = watcher.await.unwrap();

    let during: Vec<u64> = seqs
        .iter()
        .filter(|(at, _)| *at >= began && *at <= ended)
        .map(|&(_, s)| s)
        .collect();
    let worst = during.windows(2).map(|w| w[1] - w[0]).max().unwrap_or(0);
    println!(
        "bake {baked_in:?}, cached play {cached_in:?}, {} frames meanwhile, worst seq gap {worst}",
        during.len()
    );
    // The bake must take several ticks, or this test could not see a stall.
    assert!(
        baked_in.as_secs_f64() > 3.0 / f64::from(rate),
        "bake took only {baked_in:?}"
    );
    assert!(
        during.len() as f64 >= 0.5 * baked_in.as_secs_f64() * f64::from(rate),
        "{} frames in {baked_in:?}",
        during.len()
    );
    assert!(worst < 3, "the other scene stalled: a gap of {worst} ticks");
    assert!(
        cached_in < baked_in / 4,
        "the second play baked again ({cached_in:?} vs {baked_in:?})"
    );
}
