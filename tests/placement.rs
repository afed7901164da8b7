//! Avatar placement end to end: stored across a `SIGKILL` and restart, the first frame a late
//! joiner gets carries it (binary and JSON), and a timed `place_avatar` streams a linear move.

#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use common::child::Posecast;
use common::{command_to, wait_for};
use futures_util::StreamExt;
use glam::{Quat, Vec3};
use posecast_proto::frame::FrameDecoder;
use posecast_proto::msg::{AvatarId, Encoding, SceneId, ServerMsg};
use posecast_proto::placement::Placement;
use serde_json::Value;
use std::collections::HashMap;
use std::net::SocketAddr;
use std::time::Duration;
use tokio_tungstenite::tungstenite::Message;

async fn ok(addr: SocketAddr, json: &str) -> Value {
    let (status, body) = command_to(addr, json).await;
    assert_eq!(status, 200, "{json} → {body}");
    body["result"].clone()
}

fn placement_of(v: &Value) -> Placement {
    serde_json::from_value(v["placement"].clone()).unwrap()
}

fn near(a: &Placement, b: &Placement) -> bool {
    (a.position - b.position).length() < 1e-5 && a.rotation.dot(b.rotation).abs() > 1.0 - 1e-6
}

/// Subscribes to `scene` and returns each avatar's placement in the very first frame, which
/// must follow `subscribed` and the descriptions with nothing in between.
async fn first_frame(
    addr: SocketAddr,
    encoding: Encoding,
    scene: &str,
) -> HashMap<AvatarId, Placement> {
    let (mut ws, _) = tokio_tungstenite::connect_async(format!("ws://{addr}/ws"))
        .await
        .unwrap();
    common::hello_and_subscribe(&mut ws, encoding, scene, None).await;
    let mut nums: HashMap<u32, AvatarId> = HashMap::new();
    let mut decoder = FrameDecoder::new();
    loop {
        // Bounded for a busy machine: the frame comes at the next tick.
        let msg = tokio::time::timeout(Duration::from_secs(120), ws.next())
            .await
            .expect("a message within 120 s")
            .unwrap()
            .unwrap();
        match msg {
            Message::Binary(bytes) => {
                let frame = decoder.decode(&bytes).unwrap();
                assert_eq!(frame.avatars.len(), nums.len(), "every described avatar");
                return frame
                    .avatars
                    .iter()
                    .map(|p| (nums[&p.avatar_num].clone(), p.placement))
                    .collect();
            }
            Message::Text(t) => match serde_json::from_str::<ServerMsg>(t.as_str()).unwrap() {
                ServerMsg::Welcome { .. } | ServerMsg::Subscribed { .. } => {}
                ServerMsg::Description { avatar, .. } => {
                    nums.insert(avatar.num, avatar.id.clone());
                }
                ServerMsg::Frame(frame) => {
                    assert_eq!(frame.avatars.len(), nums.len(), "every described avatar");
                    return frame
                        .avatars
                        .iter()
                        .map(|p| (p.avatar.clone(), p.placement))
                        .collect();
                }
                other => panic!("unexpected before the first frame: {other:?}"),
            },
            // Round-trip probes of the adaptive rate (answered by the library).
            Message::Ping(_) => {}
            other => panic!("unexpected message {other:?}"),
        }
    }
}

/// A joiner after `place_avatar` *and a tick* (the window in which the joiner gets the
/// scene's cached keyframe rather than one made for it): its very first frame shows the move,
/// because placing makes the next tick a keyframe. Deterministic: the test waits for ticks.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_joiner_a_tick_after_a_move_sees_it_in_its_first_frame() {
    let server = common::server(30.0).await;
    let scene = server
        .state
        .world
        .scene(&SceneId("default".into()))
        .unwrap();
    let mut ticks = scene.ticks();
    let to = Placement {
        position: Vec3::new(2.0, 0.0, -1.0),
        rotation: Quat::IDENTITY,
    };
    for encoding in [Encoding::Binary, Encoding::Json] {
        for x in [2.0f32, -2.0] {
            let to = Placement {
                position: Vec3::new(x, 0.0, -1.0),
                ..to
            };
            ok(
                server.addr,
                &format!(
                    r#"{{"op":"place_avatar","avatar":"avatar","position":[{x},0,-1],"rotation":[0,0,0,1]}}"#
                ),
            )
            .await;
            // Two ticks: the first after the ack may have been under way before it.
            for _ in 0..2 {
                ticks.changed().await.unwrap();
            }
            let seen = first_frame(server.addr, encoding, "default").await;
            assert!(
                near(&seen[&AvatarId("avatar".into())], &to),
                "{encoding:?}: {seen:?}, wanted {to:?}"
            );
        }
    }
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn placement_survives_sigkill_and_reaches_late_joiners_in_both_encodings() {
    let data = tempfile::tempdir().unwrap();
    let start = || {
        Posecast::start(
            &["--tick-rate", "30", "--data", data.path().to_str().unwrap()],
            &[("POSECAST_CONTROL_TOKEN", common::CONTROL)],
        )
    };
    let server = start();
    let addr = server.addr;
    ok(addr, r#"{"op":"create_scene","scene":"yard"}"#).await;
    ok(
        addr,
        r#"{"op":"add_avatar","scene":"yard","asset":"avatar","avatar":"a","position":[1.5,0,-2],"rotation":[0,0.7071068,0,0.7071068]}"#,
    )
    .await;
    ok(
        addr,
        r#"{"op":"add_avatar","scene":"yard","asset":"avatar","avatar":"b","clip":"walk"}"#,
    )
    .await;
    // An instant move: a joiner right after the ack already sees it.
    ok(
        addr,
        r#"{"op":"place_avatar","avatar":"b","position":[-3,0,4],"rotation":[0,0,0,2]}"#,
    )
    .await;
    let a = Placement {
        position: Vec3::new(1.5, 0.0, -2.0),
        rotation: Quat::from_rotation_y(std::f32::consts::FRAC_PI_2),
    };
    let b = Placement {
        position: Vec3::new(-3.0, 0.0, 4.0),
        rotation: Quat::IDENTITY,
    };
    for encoding in [Encoding::Binary, Encoding::Json] {
        let seen = first_frame(addr, encoding, "yard").await;
        assert!(
            near(&seen[&AvatarId("a".into())], &a),
            "{encoding:?} {seen:?}"
        );
        assert!(
            near(&seen[&AvatarId("b".into())], &b),
            "{encoding:?} {seen:?}"
        );
    }
    server.kill();

    let server = start();
    let addr = server.addr;
    let got = ok(addr, r#"{"op":"get_avatar","avatar":"a"}"#).await;
    assert!(near(&placement_of(&got), &a), "{got}");
    let got = ok(addr, r#"{"op":"get_avatar","avatar":"b"}"#).await;
    assert!(near(&placement_of(&got), &b), "{got}");
    assert_eq!(got["root_motion"], "in_place");
    // Late joiners of the restarted server.
    for encoding in [Encoding::Binary, Encoding::Json] {
        let seen = first_frame(addr, encoding, "yard").await;
        assert!(
            near(&seen[&AvatarId("a".into())], &a),
            "{encoding:?} {seen:?}"
        );
        assert!(
            near(&seen[&AvatarId("b".into())], &b),
            "{encoding:?} {seen:?}"
        );
    }
    server.kill();
}

/// `place_avatar` over 1 s at 30 Hz: every streamed tick of the move is on the straight line
/// at the fraction of the duration its clock has reached, in both encodings.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_timed_move_streams_interpolated_placements() {
    let server = common::server(30.0).await;
    for encoding in [Encoding::Binary, Encoding::Json] {
        let client = common::client(&server, encoding).await;
        let id = AvatarId("avatar".into());
        assert!(wait_for(5.0, || client.latest(&id).is_some()).await);
        let from = client.latest(&id).unwrap().placement;
        let to = Placement {
            position: from.position + Vec3::new(3.0, 0.0, 0.0),
            rotation: from.rotation * Quat::from_rotation_y(1.0),
        };
        let cmd = format!(
            r#"{{"op":"place_avatar","avatar":"avatar","position":{:?},"rotation":{:?},"duration":1.0}}"#,
            to.position.to_array(),
            to.rotation.to_array()
        );
        client
            .command(serde_json::from_str(&cmd).unwrap())
            .await
            .unwrap();
        let mut samples: Vec<(u64, Placement)> = Vec::new();
        let deadline = tokio::time::Instant::now() + Duration::from_secs(4);
        while tokio::time::Instant::now() < deadline {
            if let Some(s) = client.latest(&id)
                && samples.last().is_none_or(|(seq, _)| *seq != s.seq)
            {
                let done = near(&s.placement, &to);
                samples.push((s.seq, s.placement));
                if done {
                    break;
                }
            }
            tokio::time::sleep(Duration::from_millis(3)).await;
        }
        assert!(
            near(&samples.last().unwrap().1, &to),
            "{encoding:?} never arrived"
        );
        // The intermediate ticks: strictly between the ends, on the line, and the fraction
        // (x travelled / 3 m) advances by one tick's share (1/30) per tick.
        let moving: Vec<_> = samples
            .iter()
            .filter(|(_, p)| !near(p, &from) && !near(p, &to))
            .collect();
        assert!(
            moving.len() >= 15,
            "{encoding:?}: only {} moving ticks",
            moving.len()
        );
        for w in moving.windows(2) {
            let (s0, p0) = w[0];
            let (s1, p1) = w[1];
            let f0 = (p0.position.x - from.position.x) / 3.0;
            let f1 = (p1.position.x - from.position.x) / 3.0;
            let per_tick = (f1 - f0) / (s1 - s0) as f32;
            assert!(
                (per_tick - 1.0 / 30.0).abs() < 1e-3,
                "{encoding:?}: {per_tick}"
            );
            for (f, p) in [(f0, p0), (f1, p1)] {
                assert!((p.position.y - from.position.y).abs() < 1e-5);
                // The rotation is the slerp at the same fraction.
                let expected = from.rotation.slerp(to.rotation, f);
                assert!(expected.dot(p.rotation).abs() > 1.0 - 1e-5, "{encoding:?}");
            }
        }
        // Back where it started for the next encoding.
        let back = format!(
            r#"{{"op":"place_avatar","avatar":"avatar","position":{:?},"rotation":{:?}}}"#,
            from.position.to_array(),
            from.rotation.to_array()
        );
        client
            .command(serde_json::from_str(&back).unwrap())
            .await
            .unwrap();
    }
}
