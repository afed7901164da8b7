//! Scene and avatar changes pushed over the websocket (`watch_scenes`, `scene_created`,
//! `scene_deleted`, `avatar_changed`, `avatar_removed`): who gets them, once each, what they
//! carry, and that a token limited to some scenes hears of no other.

#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use common::{CONTROL, Ws, http_as, raw_as};
use futures_util::{SinkExt, StreamExt};
use posecast_proto::msg::{Encoding, ErrorCode, SceneId, ServerMsg};
use posecast_server::auth::{AccessConfig, Role, Secret, TokenRule};
use serde_json::Value;
use std::time::Duration;
use tokio_tungstenite::tungstenite::Message;

const LOBBY: &str = "lobby-control-token";

async fn send(ws: &mut Ws, json: &str) {
    ws.send(Message::Text(json.into())).await.unwrap();
}

/// The text messages (not frames) `ws` receives within `ms` milliseconds.
async fn drain(ws: &mut Ws, ms: u64) -> Vec<ServerMsg> {
    let deadline = tokio::time::Instant::now() + Duration::from_millis(ms);
    let mut out = Vec::new();
    while let Ok(Some(Ok(m))) = tokio::time::timeout_at(deadline, ws.next()).await {
        if let Message::Text(t) = m {
            let msg: ServerMsg = serde_json::from_str(t.as_str()).unwrap();
            if !matches!(msg, ServerMsg::Frame(_) | ServerMsg::Pong { .. }) {
                out.push(msg);
            }
        }
    }
    out
}

/// Changes among `msgs`, as `(type, scene, avatar)` — descriptions and `subscribed` left out.
fn changes(msgs: &[ServerMsg]) -> Vec<(String, String, String)> {
    msgs.iter()
        .filter_map(|m| {
            let v = serde_json::to_value(m).unwrap();
            let kind = v["type"].as_str().unwrap().to_owned();
            let avatar = match &v["avatar"] {
                Value::String(s) => s.clone(),
                Value::Object(o) => o["avatar"].as_str().unwrap().to_owned(),
                _ => String::new(),
            };
            let scene = v["scene"].as_str().unwrap_or_default().to_owned();
            matches!(
                kind.as_str(),
                "scene_created" | "scene_deleted" | "avatar_changed" | "avatar_removed"
            )
            .then_some((kind, scene, avatar))
        })
        .collect()
}

fn change(kind: &str, scene: &str, avatar: &str) -> (String, String, String) {
    (kind.into(), scene.into(), avatar.into())
}

async fn command(server: &posecast_server::startup::Server, json: &str) -> Value {
    let (status, body) = http_as(server, Some(CONTROL), "POST", "/api/commands", Some(json)).await;
    assert_eq!(status, 200, "{json}: {body}");
    serde_json::from_str(&body).unwrap()
}

/// A watcher that is not subscribed, a subscriber that does not watch, and a connection that
/// does both each get every change they follow exactly once; after `unwatch_scenes` nothing.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn changes_reach_subscribers_and_watchers_once_each() {
    let server = common::server(30.0).await;
    let mut watcher = raw_as(&server, Encoding::Json, None).await;
    let mut subscriber = raw_as(&server, Encoding::Binary, None).await;
    let mut both = raw_as(&server, Encoding::Binary, None).await;
    send(&mut watcher, r#"{"type":"watch_scenes"}"#).await;
    match drain(&mut watcher, 300).await.as_slice() {
        [ServerMsg::Scenes { scenes }] => {
            assert_eq!(scenes.len(), 1);
            assert_eq!(scenes[0].scene.0, "default");
            assert_eq!(scenes[0].avatars[0].avatar.0, "avatar");
        }
        other => panic!("expected the scene list, got {other:?}"),
    }
    send(&mut subscriber, r#"{"type":"subscribe","scene":"default"}"#).await;
    send(&mut both, r#"{"type":"subscribe","scene":"default"}"#).await;
    send(&mut both, r#"{"type":"watch_scenes"}"#).await;
    drain(&mut subscriber, 300).await;
    drain(&mut both, 300).await;

    let mut step = async |json: &str,
                          expect_all: &[(String, String, String)],
                          expect_watchers: &[(String, String, String)]| {
        command(&server, json).await;
        let w = changes(&drain(&mut watcher, 400).await);
        let s = changes(&drain(&mut subscriber, 10).await);
        let b = changes(&drain(&mut both, 10).await);
        let mut for_watchers = expect_all.to_vec();
        for_watchers.extend_from_slice(expect_watchers);
        assert_eq!(w, for_watchers, "watcher after {json}");
        assert_eq!(b, for_watchers, "watching subscriber after {json}");
        assert_eq!(s, expect_all, "subscriber after {json}");
    };
    step(
        r#"{"op":"create_scene","scene":"lobby"}"#,
        &[],
        &[change("scene_created", "lobby", "")],
    )
    .await;
    step(
        r#"{"op":"add_avatar","scene":"lobby","asset":"avatar","avatar":"guest","position":[1,0,0]}"#,
        &[],
        &[change("avatar_changed", "lobby", "guest")],
    )
    .await;
    step(
        r#"{"op":"play","avatar":"avatar","clip":"walk","speed":1.5}"#,
        &[change("avatar_changed", "default", "avatar")],
        &[],
    )
    .await;
    // A joint dragged: one change when the joint becomes overridden, none for new angles.
    for angle in [0.1f32, 0.2, 0.3, 0.4] {
        let (s, c) = (angle.sin(), angle.cos());
        let json = format!(
            r#"{{"op":"set_joint_rotation","avatar":"avatar","joint":"l_elbow","rotation":[{s},0,0,{c}]}}"#
        );
        let expected = if angle == 0.1 {
            vec![change("avatar_changed", "default", "avatar")]
        } else {
            Vec::new()
        };
        step(&json, &expected, &[]).await;
    }
    step(
        r#"{"op":"release","avatar":"avatar"}"#,
        &[change("avatar_changed", "default", "avatar")],
        &[],
    )
    .await;
    step(
        r#"{"op":"place_avatar","avatar":"guest","position":[2,0,0],"rotation":[0,0,0,1]}"#,
        &[],
        &[change("avatar_changed", "lobby", "guest")],
    )
    .await;
    step(
        r#"{"op":"remove_avatar","avatar":"guest"}"#,
        &[],
        &[change("avatar_removed", "lobby", "guest")],
    )
    .await;
    step(
        r#"{"op":"delete_scene","scene":"lobby"}"#,
        &[],
        &[change("scene_deleted", "lobby", "")],
    )
    .await;
    // A failed command announces nothing.
    let (status, _) = http_as(
        &server,
        Some(CONTROL),
        "POST",
        "/api/commands",
        Some(r#"{"op":"play","avatar":"avatar","clip":"no-such-clip"}"#),
    )
    .await;
    assert_eq!(status, 404);
    assert_eq!(changes(&drain(&mut watcher, 300).await), []);

    send(&mut watcher, r#"{"type":"unwatch_scenes"}"#).await;
    tokio::time::sleep(Duration::from_millis(100)).await;
    command(&server, r#"{"op":"create_scene","scene":"later"}"#).await;
    assert_eq!(changes(&drain(&mut watcher, 300).await), []);
    assert_eq!(
        changes(&drain(&mut both, 10).await),
        [change("scene_created", "later", "")]
    );
    server.stop().await;
}

/// `avatar_changed` carries the state at tick `seq`: the clip time of a later change equals
/// the earlier one advanced by the ticks between them at the clip's speed (the formula a
/// client uses to move its timeline with the stream), and a cross-fade shows as `fade`.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn avatar_changed_times_follow_the_tick_clock() {
    let tick_rate = 30.0;
    let server = common::server(tick_rate).await;
    let mut watcher = raw_as(&server, Encoding::Json, None).await;
    send(&mut watcher, r#"{"type":"watch_scenes"}"#).await;
    drain(&mut watcher, 200).await;
    let changed = async |ws: &mut Ws| -> (u64, Value) {
        let msgs = drain(ws, 300).await;
        let v = msgs
            .iter()
            .map(|m| serde_json::to_value(m).unwrap())
            .find(|v| v["type"] == "avatar_changed")
            .expect("an avatar_changed");
        (v["seq"].as_u64().unwrap(), v["avatar"].clone())
    };
    command(
        &server,
        r#"{"op":"play","avatar":"avatar","clip":"walk","speed":0.5,"start":0.1,"fade":0.5}"#,
    )
    .await;
    let (seq0, a0) = changed(&mut watcher).await;
    assert_eq!(a0["clip"], "walk");
    assert_eq!(a0["fade"]["from"], "idle", "{a0}");
    assert_eq!(a0["fade"]["duration"], 0.5, "{a0}");
    assert!(a0["fade"]["elapsed"].as_f64().unwrap() < 0.05, "{a0}");
    tokio::time::sleep(Duration::from_millis(700)).await;
    command(&server, r#"{"op":"pause","avatar":"avatar"}"#).await;
    let (seq1, a1) = changed(&mut watcher).await;
    assert!(seq1 > seq0 + 10, "{seq0} → {seq1}");
    assert!(a1.get("fade").is_none(), "the fade is over: {a1}");
    let (_, assets) = http_as(&server, None, "GET", "/api/assets", None).await;
    let assets: Value = serde_json::from_str(&assets).unwrap();
    let duration = assets[0]["clips"]
        .as_array()
        .unwrap()
        .iter()
        .find(|c| c["name"] == "walk")
        .unwrap()["duration"]
        .as_f64()
        .unwrap();
    let t0 = a0["time"].as_f64().unwrap();
    let expected = (t0 + (seq1 - seq0) as f64 / f64::from(tick_rate) * 0.5).rem_euclid(duration);
    let t1 = a1["time"].as_f64().unwrap();
    assert!(
        (t1 - expected).abs() < 1e-4,
        "time {t1} at tick {seq1}; {t0} at {seq0} advanced gives {expected}"
    );
    assert_eq!(a1["paused"], true);
    server.stop().await;
}

/// With private views, a token limited to scene `lobby` lists and hears only of `lobby`;
/// an anonymous connection may not watch at all.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_scene_limited_token_hears_only_of_its_scenes() {
    let mut access: AccessConfig = common::test_access();
    access.open_view = false;
    let mut lobby = TokenRule::new("lobby", Secret::new(LOBBY), Role::Control);
    lobby.scenes = Some(vec![SceneId("lobby".into())]);
    access.add(lobby).unwrap();
    let server = common::server_with(30.0, access).await;
    command(&server, r#"{"op":"create_scene","scene":"lobby"}"#).await;

    let mut anonymous = raw_as(&server, Encoding::Json, None).await;
    send(&mut anonymous, r#"{"type":"watch_scenes"}"#).await;
    match drain(&mut anonymous, 300).await.as_slice() {
        [ServerMsg::Error(e)] => assert_eq!(e.code, ErrorCode::Unauthorized),
        other => panic!("expected unauthorized, got {other:?}"),
    }
    let mut limited = raw_as(&server, Encoding::Json, Some(LOBBY)).await;
    send(&mut limited, r#"{"type":"watch_scenes"}"#).await;
    match drain(&mut limited, 300).await.as_slice() {
        [ServerMsg::Scenes { scenes }] => {
            let names: Vec<_> = scenes.iter().map(|s| s.scene.0.as_str()).collect();
            assert_eq!(names, ["lobby"]);
        }
        other => panic!("expected the scene list, got {other:?}"),
    }
    command(&server, r#"{"op":"create_scene","scene":"secret"}"#).await;
    command(
        &server,
        r#"{"op":"add_avatar","scene":"secret","asset":"avatar","avatar":"hidden"}"#,
    )
    .await;
    command(&server, r#"{"op":"pause","avatar":"avatar"}"#).await;
    command(&server, r#"{"op":"remove_avatar","avatar":"hidden"}"#).await;
    command(&server, r#"{"op":"delete_scene","scene":"secret"}"#).await;
    command(
        &server,
        r#"{"op":"add_avatar","scene":"lobby","asset":"avatar","avatar":"guest"}"#,
    )
    .await;
    assert_eq!(
        changes(&drain(&mut limited, 400).await),
        [change("avatar_changed", "lobby", "guest")]
    );
    assert_eq!(changes(&drain(&mut anonymous, 10).await), []);
    server.stop().await;
}
