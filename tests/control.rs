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
    let path = posecast_proto::testing::testdata("bvh/cmu/01_01.bvh");
    if !path.exists() {
        eprintln!("skipping: {} is absent", path.display());
        return;
    }
    let server = server(60.0).await;
    let mut asset = posecast_server::import::load_path(&path).unwrap().remove(0);
    asset.name = "cmu".into();
    let clip = asset.clips[0].name().to_string();
    let rig = posecast_server::startup::rig_from_asset(asset, &Default::default()).unwrap();
    server.state.library.insert(rig);
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
