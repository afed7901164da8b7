//! Quotas, the per-connection command rate limit and who may read `/metrics`: every quota is
//! refused with its typed error (`quota_exceeded`, HTTP 429), changes nothing and is counted;
//! a command flood gets `rate_limited` with a retry hint, and the hint is right.

#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use common::{CONTROL, http_as, upload_files};
use futures_util::SinkExt;
use posecast_proto::msg::{AvatarId, ClientMsg, ErrorCode, ServerMsg};
use posecast_server::auth::{Role, Secret, TokenRule};
use posecast_server::config::Config;
use posecast_server::quota::{CommandRate, Quotas};
use posecast_server::startup::Server;
use serde_json::Value;
use std::time::Duration;
use tokio_tungstenite::tungstenite::Message;

const ALICE: &str = "alice-limited-token";

async fn start(quotas: Quotas, command_rate: CommandRate, private: bool) -> Server {
    let mut access = common::test_access();
    let mut alice = TokenRule::new("alice", Secret::new(ALICE), Role::Control);
    alice.avatars = Some(vec![AvatarId("alice".into())]);
    access.add(alice).unwrap();
    if private {
        access.open_view = false;
    }
    let server = Server::start(Config {
        listen: "127.0.0.1:0".parse().unwrap(),
        access,
        quotas,
        command_rate,
        ..Config::default()
    })
    .await
    .unwrap();
    server.ready().await.unwrap();
    server
}

async fn command(server: &Server, token: &str, json: &str) -> (u16, Value) {
    let (s, b) = http_as(server, Some(token), "POST", "/api/commands", Some(json)).await;
    (s, serde_json::from_str(&b).unwrap_or(Value::Null))
}

/// A `.skel` of `joints` joints in a chain (padding spaces bring it to at least `bytes`).
fn skel(joints: usize, bytes: usize) -> Vec<u8> {
    let mut s = String::new();
    for i in 0..joints {
        s += &format!("balljoint j{i} {{ offset 0 0.1 0 ");
    }
    s += &"}".repeat(joints);
    while s.len() < bytes {
        s.push(' ');
    }
    s.into_bytes()
}

/// An `.anim` for a chain of `joints` joints, `seconds` long.
fn anim(joints: usize, seconds: f32) -> Vec<u8> {
    let channels = 3 + 3 * joints;
    let mut s = format!("animation {{\n range 0 {seconds}\n numchannels {channels}\n");
    for _ in 0..channels {
        s += " channel {\n  extrapolate constant constant\n  keys 1 {\n   0 0 linear linear\n  }\n }\n";
    }
    (s + "}\n").into_bytes()
}

async fn quota_refused(server: &Server, quota: &str) -> u64 {
    let (_, text) = http_as(server, Some(CONTROL), "GET", "/metrics", None).await;
    text.lines()
        .find_map(|l| {
            l.strip_prefix(&format!(
                "posecast_quota_refused_total{{quota=\"{quota}\"}} "
            ))
        })
        .and_then(|v| v.parse().ok())
        .unwrap_or_else(|| panic!("no {quota} counter in\n{text}"))
}

fn assert_quota(status: u16, body: &Value, quota: &str) {
    assert_eq!(status, 429, "{body}");
    assert_eq!(body["code"], "quota_exceeded", "{body}");
    assert!(
        body["message"]
            .as_str()
            .unwrap()
            .contains(&format!("quota {quota}")),
        "{body}"
    );
}

#[tokio::test]
async fn every_quota_is_refused_with_its_typed_error_and_changes_nothing() {
    let quotas = Quotas {
        max_scenes: 3,
        max_avatars_per_scene: 2,
        max_joints: 6,
        limited_max_joints: 4,
        max_clip_joint_seconds: 100.0,
        max_asset_bytes: 4_000,
        max_upload_total_bytes: 10_000,
    };
    let server = start(quotas, CommandRate::default(), false).await;
    let addr = server.addr;

    // Scenes: `default` plus two more; the fourth is refused and not created.
    for scene in ["s1", "s2"] {
        let json = format!(r#"{{"op":"create_scene","scene":"{scene}"}}"#);
        assert_eq!(command(&server, CONTROL, &json).await.0, 200);
    }
    let (s, b) = command(&server, CONTROL, r#"{"op":"create_scene","scene":"s3"}"#).await;
    assert_quota(s, &b, "scenes");
    let (_, scenes) = command(&server, CONTROL, r#"{"op":"list_scenes"}"#).await;
    assert_eq!(scenes["result"].as_array().unwrap().len(), 3, "{scenes}");
    assert_eq!(quota_refused(&server, "scenes").await, 1);

    // Avatars per scene: `default` holds one; a second fits, a third is refused.
    let add = |scene: &str, avatar: &str, asset: &str| {
        format!(r#"{{"op":"add_avatar","scene":"{scene}","asset":"{asset}","avatar":"{avatar}"}}"#)
    };
    assert_eq!(
        command(&server, CONTROL, &add("default", "b", "avatar"))
            .await
            .0,
        200
    );
    let (s, b) = command(&server, CONTROL, &add("default", "c", "avatar")).await;
    assert_quota(s, &b, "avatars_per_scene");
    let (s, _) = command(&server, CONTROL, r#"{"op":"get_avatar","avatar":"c"}"#).await;
    assert_eq!(s, 404, "the refused avatar exists");

    // A limited token may not place the built-in avatar (more joints than 4) even where it
    // has room, but an unlimited one may.
    let (s, b) = command(&server, ALICE, &add("s1", "alice", "avatar")).await;
    assert_quota(s, &b, "limited_joints");
    let (s, _) = command(&server, ALICE, r#"{"op":"get_avatar","avatar":"alice"}"#).await;
    assert_eq!(s, 404);
    assert_eq!(
        command(&server, CONTROL, &add("s1", "alice", "avatar"))
            .await
            .0,
        200
    );

    // Uploads: joints, clip size, asset bytes, total bytes.
    let (s, b) = upload_files(addr, "/api/assets/big", &[("big.skel", &skel(7, 0))]).await;
    assert_quota(s, &serde_json::from_str(&b).unwrap(), "joints");
    let (s, b) = upload_files(
        addr,
        "/api/assets/long",
        &[("long.skel", &skel(3, 0)), ("walk.anim", &anim(3, 60.0))],
    )
    .await;
    assert_quota(s, &serde_json::from_str(&b).unwrap(), "clip_joint_seconds");
    let (s, b) = upload_files(addr, "/api/assets/fat", &[("fat.skel", &skel(2, 4_001))]).await;
    assert_quota(s, &serde_json::from_str(&b).unwrap(), "asset_bytes");
    for name in ["a1", "a2"] {
        let (s, b) = upload_files(
            addr,
            &format!("/api/assets/{name}"),
            &[("x.skel", &skel(2, 3_900))],
        )
        .await;
        assert_eq!(s, 200, "{b}");
    }
    let (s, b) = upload_files(addr, "/api/assets/a3", &[("x.skel", &skel(2, 3_900))]).await;
    assert_quota(s, &serde_json::from_str(&b).unwrap(), "upload_total_bytes");
    let (_, assets) = http_as(&server, None, "GET", "/api/assets", None).await;
    let names: Vec<String> = serde_json::from_str::<Value>(&assets)
        .unwrap()
        .as_array()
        .unwrap()
        .iter()
        .map(|a| a["name"].as_str().unwrap().to_owned())
        .collect();
    assert_eq!(
        names,
        ["a1", "a2", "avatar"],
        "refused uploads left a trace"
    );
    for (quota, n) in [
        ("avatars_per_scene", 1),
        ("limited_joints", 1),
        ("joints", 1),
        ("clip_joint_seconds", 1),
        ("asset_bytes", 1),
        ("upload_total_bytes", 1),
    ] {
        assert_eq!(quota_refused(&server, quota).await, n, "{quota}");
    }
    server.stop().await;
}

#[tokio::test]
async fn a_command_flood_is_rate_limited_with_a_retry_hint_that_holds() {
    let rate = CommandRate::new(20.0, 5.0).unwrap();
    let server = start(Quotas::default(), rate, false).await;
    let mut ws = common::raw(&server, posecast_proto::msg::Encoding::Json).await;
    let n = 30u64;
    let began = std::time::Instant::now();
    for id in 0..n {
        let c = ClientMsg::Command {
            id,
            idempotency_key: None,
            command: serde_json::from_str(r#"{"op":"set_speed","avatar":"avatar","speed":1.5}"#)
                .unwrap(),
        };
        ws.send(Message::Text(serde_json::to_string(&c).unwrap().into()))
            .await
            .unwrap();
    }
    let (mut acked, mut limited, mut hint) = (0, 0, 0);
    while acked + limited < n {
        match common::next_text(&mut ws)
            .await
            .expect("an answer per command")
        {
            ServerMsg::Ack { .. } => acked += 1,
            ServerMsg::Error(e) => {
                assert_eq!(e.code, ErrorCode::RateLimited, "{e:?}");
                assert!(e.id.is_some(), "{e:?}");
                hint = e.retry_after_ms.expect("a retry hint");
                limited += 1;
            }
            _ => {}
        }
    }
    // The burst of 5 passes, plus what 20/s refills while the flood is read; the rest waits.
    let refilled = (20.0 * began.elapsed().as_secs_f64()).ceil() as u64;
    assert!(
        acked >= 5 && acked <= 5 + refilled && limited > 0,
        "{acked} acked, {limited} limited, {refilled} refilled"
    );
    assert!((1..=50).contains(&hint), "retry after {hint} ms");
    // After the hint (and one token's time), a command passes again.
    tokio::time::sleep(Duration::from_millis(hint + 60)).await;
    let c = ClientMsg::Command {
        id: 99,
        idempotency_key: None,
        command: serde_json::from_str(r#"{"op":"list_scenes"}"#).unwrap(),
    };
    ws.send(Message::Text(serde_json::to_string(&c).unwrap().into()))
        .await
        .unwrap();
    loop {
        match common::next_text(&mut ws).await.expect("an answer") {
            ServerMsg::Ack { id: 99, .. } => break,
            ServerMsg::Error(e) => panic!("still limited: {e:?}"),
            _ => {}
        }
    }
    let (_, text) = http_as(&server, Some(CONTROL), "GET", "/metrics", None).await;
    assert!(
        text.contains(&format!("posecast_rate_limited_total {limited}")),
        "{text}"
    );
    server.stop().await;
}

#[tokio::test]
async fn metrics_hide_scene_names_from_anonymous_callers_and_need_a_token_when_private() {
    let server = start(Quotas::default(), CommandRate::default(), false).await;
    let (s, anonymous) = http_as(&server, None, "GET", "/metrics", None).await;
    assert_eq!(s, 200);
    assert!(!anonymous.contains("scene=\"default\""), "{anonymous}");
    assert!(
        anonymous.contains("posecast_subscribers_total_open "),
        "{anonymous}"
    );
    let (_, named) = http_as(&server, Some(CONTROL), "GET", "/metrics", None).await;
    assert!(
        named.contains("posecast_subscribers{scene=\"default\"}"),
        "{named}"
    );
    server.stop().await;

    let server = start(Quotas::default(), CommandRate::default(), true).await;
    let (s, body) = http_as(&server, None, "GET", "/metrics", None).await;
    assert_eq!(s, 401, "{body}");
    assert_eq!(
        serde_json::from_str::<Value>(&body).unwrap()["code"],
        "unauthorized"
    );
    let (s, _) = http_as(&server, Some(CONTROL), "GET", "/metrics", None).await;
    assert_eq!(s, 200);
    server.stop().await;
}

/// Subscribing costs the scene work under its lock: a subscribe flood is rate-limited like a
/// command flood (no id: subscribes have none).
#[tokio::test]
async fn a_subscribe_flood_is_rate_limited() {
    let rate = CommandRate::new(10.0, 3.0).unwrap();
    let server = start(Quotas::default(), rate, false).await;
    let mut ws = common::raw(&server, posecast_proto::msg::Encoding::Json).await;
    let began = std::time::Instant::now();
    for _ in 0..20 {
        ws.send(Message::Text(
            r#"{"type":"subscribe","scene":"default"}"#.into(),
        ))
        .await
        .unwrap();
    }
    let (mut subscribed, mut limited) = (0, 0);
    while subscribed + limited < 20 {
        match common::next_text(&mut ws)
            .await
            .expect("an answer per subscribe")
        {
            ServerMsg::Subscribed { .. } => subscribed += 1,
            ServerMsg::Error(e) => {
                assert_eq!(e.code, ErrorCode::RateLimited, "{e:?}");
                assert!(e.retry_after_ms.is_some(), "{e:?}");
                limited += 1;
            }
            _ => {}
        }
    }
    let refilled = (10.0 * began.elapsed().as_secs_f64()).ceil() as u32;
    assert!(
        subscribed >= 3 && subscribed <= 3 + refilled && limited > 0,
        "{subscribed} subscribed, {limited} limited, {refilled} refilled"
    );
    server.stop().await;
}

/// The binary on `data` with an access file: the tests' unlimited token and alice, limited to
/// avatar `alice` and to two stored objects of her own.
fn start_binary(data: &std::path::Path, access: &std::path::Path) -> common::child::Posecast {
    common::child::Posecast::start(
        &[
            "--tick-rate",
            "30",
            "--data",
            data.to_str().unwrap(),
            "--access-file",
            access.to_str().unwrap(),
        ],
        &[],
    )
}

/// A command to `addr` as `token`: status and body.
async fn command_at(addr: std::net::SocketAddr, token: &str, json: &str) -> (u16, Value) {
    let (s, b) = common::http_request(
        addr,
        Some(token),
        "POST",
        "/api/commands",
        "application/json",
        json.as_bytes(),
    )
    .await;
    (s, serde_json::from_str(&b).unwrap_or(Value::Null))
}

/// Records `clip` on avatar `alice` as `token` and stops: the stop's status and body. A stop
/// before the first tick is retried with a longer take.
async fn take_as(addr: std::net::SocketAddr, token: &str, clip: &str) -> (u16, Value) {
    let record = format!(r#"{{"op":"record","avatar":"alice","clip":"{clip}"}}"#);
    for attempt in 1..=20u64 {
        let (s, b) = command_at(addr, token, &record).await;
        assert_eq!(s, 200, "{record}: {b}");
        tokio::time::sleep(Duration::from_millis(100 * attempt)).await;
        let (s, b) = command_at(addr, token, r#"{"op":"stop_recording","avatar":"alice"}"#).await;
        if b["code"] != "invalid_value" {
            return (s, b);
        }
    }
    panic!("no tick recorded in 20 tries");
}

/// Issue 37: one limited token cannot fill everyone's room. Its recordings count against its
/// own quota (owner stored with each, so a restart does not reset it); others still record;
/// it deletes only its own, and a delete frees its quota; a clip being played is not deleted.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_tokens_quota_holds_across_a_restart_and_deletes_free_it() {
    let dir = tempfile::tempdir().unwrap();
    let (data, access) = (dir.path().join("data"), dir.path().join("access.toml"));
    std::fs::write(
        &access,
        format!(
            "[[token]]\nname = \"admin\"\nrole = \"control\"\ntoken = \"{CONTROL}\"\n\n\
             [[token]]\nname = \"alice\"\nrole = \"control\"\ntoken = \"{ALICE}\"\n\
             avatars = [\"alice\"]\nmax_objects = 2\n"
        ),
    )
    .unwrap();
    let server = start_binary(&data, &access);
    let addr = server.addr;
    let (s, b) = command_at(
        addr,
        CONTROL,
        r#"{"op":"add_avatar","scene":"default","asset":"avatar","avatar":"alice"}"#,
    )
    .await;
    assert_eq!(s, 200, "{b}");
    for clip in ["a1", "a2"] {
        let (s, b) = take_as(addr, ALICE, clip).await;
        assert_eq!(s, 200, "{clip}: {b}");
    }
    let (s, b) = take_as(addr, ALICE, "a3").await;
    assert_quota(s, &b, "token_objects");
    // Refused: the name is free, and nobody else is affected.
    let (s, b) = take_as(addr, CONTROL, "a3").await;
    assert_eq!(s, 200, "another token is refused too: {b}");
    server.kill();

    let server = start_binary(&data, &access);
    let addr = server.addr;
    let (s, b) = take_as(addr, ALICE, "a4").await;
    assert_quota(s, &b, "token_objects");
    // Not hers to delete.
    let (s, b) = common::http_request(
        addr,
        Some(ALICE),
        "DELETE",
        "/api/assets/avatar/clips/a3",
        "",
        b"",
    )
    .await;
    assert_eq!(s, 403, "{b}");
    // Being played: refused, typed.
    let (s, b) = command_at(
        addr,
        CONTROL,
        r#"{"op":"play","avatar":"alice","clip":"a2"}"#,
    )
    .await;
    assert_eq!(s, 200, "{b}");
    let (s, b) = command_at(
        addr,
        ALICE,
        r#"{"op":"delete_clip","asset":"avatar","clip":"a2"}"#,
    )
    .await;
    assert_eq!((s, b["code"].as_str()), (409, Some("conflict")), "{b}");
    // Hers: deleted, and her quota has room again.
    let (s, b) = common::http_request(
        addr,
        Some(ALICE),
        "DELETE",
        "/api/assets/avatar/clips/a1",
        "",
        b"",
    )
    .await;
    assert_eq!(s, 200, "{b}");
    let (s, b) = take_as(addr, ALICE, "a4").await;
    assert_eq!(s, 200, "the delete freed nothing: {b}");
    server.kill();

    let server = start_binary(&data, &access);
    let (s, b) = command_at(
        server.addr,
        CONTROL,
        r#"{"op":"get_asset","asset":"avatar"}"#,
    )
    .await;
    assert_eq!(s, 200, "{b}");
    let clips: Vec<&str> = b["result"]["clips"]
        .as_array()
        .unwrap()
        .iter()
        .filter_map(|c| c["name"].as_str())
        .collect();
    for clip in ["a2", "a3", "a4"] {
        assert!(clips.contains(&clip), "{clip} lost: {clips:?}");
    }
    assert!(
        !clips.contains(&"a1"),
        "a deleted clip came back: {clips:?}"
    );
    let avatar = command_at(
        server.addr,
        CONTROL,
        r#"{"op":"get_avatar","avatar":"alice"}"#,
    )
    .await;
    assert_eq!(avatar.1["result"]["clip"], "a2", "{:?}", avatar.1);
}
