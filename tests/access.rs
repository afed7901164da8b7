//! Access control end to end: tokens over REST and websocket, scopes, refusals that change
//! nothing (checked on the pose stream and the avatar state).

#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use common::{CONTROL, client, http, http_as, next_text, raw_as, server, server_with, wait_for};
use futures_util::SinkExt;
use glam::Quat;
use posecast_client::net::{Client, ClientError};
use posecast_proto::command::Command;
use posecast_proto::msg::{AvatarId, ClientMsg, Encoding, ErrorCode, SceneId, ServerMsg};
use posecast_proto::quant::angle_between_degrees;
use posecast_server::auth::{AccessConfig, Role, Secret, TokenRule};
use serde_json::Value;
use tokio_tungstenite::tungstenite::Message;

const ALICE: &str = "alice-control-token";
const LOBBY: &str = "lobby-control-token";
const VIEWER: &str = "viewer-token-12345";

fn id(s: &str) -> AvatarId {
    AvatarId(s.into())
}

/// Test access plus: alice may drive only avatar `alice`; `lobby` may drive scene `lobby`;
/// a plain view token.
fn access(open_view: bool) -> AccessConfig {
    let mut a = common::test_access();
    a.open_view = open_view;
    let mut alice = TokenRule::new("alice", Secret::new(ALICE), Role::Control);
    alice.avatars = Some(vec![id("alice")]);
    a.add(alice).unwrap();
    let mut lobby = TokenRule::new("lobby", Secret::new(LOBBY), Role::Control);
    lobby.scenes = Some(vec![SceneId("lobby".into())]);
    a.add(lobby).unwrap();
    a.add(TokenRule::new("viewer", Secret::new(VIEWER), Role::View))
        .unwrap();
    a
}

async fn command_as(
    server: &posecast_server::startup::Server,
    token: Option<&str>,
    command: &str,
) -> (u16, Value) {
    let (status, body) = http_as(server, token, "POST", "/api/commands", Some(command)).await;
    (status, serde_json::from_str(&body).unwrap_or(Value::Null))
}

async fn avatar_state(server: &posecast_server::startup::Server, avatar: &str) -> Value {
    let (status, body) = command_as(
        server,
        Some(CONTROL),
        &format!(r#"{{"op":"get_avatar","avatar":"{avatar}"}}"#),
    )
    .await;
    assert_eq!(status, 200, "{body}");
    body["result"].clone()
}

/// The streamed rotation of `joint` of `avatar`, after at least two more frames.
async fn streamed(c: &Client, avatar: &AvatarId, joint: &str) -> Quat {
    let seq = c.latest(avatar).map_or(0, |p| p.seq);
    assert!(wait_for(3.0, || c.latest(avatar).is_some_and(|p| p.seq > seq + 1)).await);
    let j = c.avatar(avatar).unwrap().skeleton.find(joint).unwrap();
    c.latest(avatar).unwrap().locals[j].rotation
}

#[tokio::test]
async fn commands_need_a_control_token_and_refusals_change_nothing() {
    let server = server(60.0).await;
    let watcher = client(&server, Encoding::Binary).await;
    let avatar = id("avatar");
    assert!(wait_for(3.0, || watcher.latest(&avatar).is_some()).await);
    watcher
        .command(Command::Pause {
            avatar: avatar.clone(),
        })
        .await
        .unwrap();
    let before_state = avatar_state(&server, "avatar").await;
    let before = streamed(&watcher, &avatar, "l_elbow").await;

    let rotate = r#"{"op":"set_joint_rotation","avatar":"avatar","joint":"l_elbow","rotation":[0,0,0.7071068,0.7071068]}"#;
    // REST: no token, an unknown token, a malformed header.
    let (status, body) = command_as(&server, None, rotate).await;
    assert_eq!((status, body["code"].as_str()), (401, Some("unauthorized")));
    let (status, body) = command_as(&server, Some("not-a-real-token"), rotate).await;
    assert_eq!((status, body["code"].as_str()), (401, Some("unauthorized")));
    // Listing stays open: views are open by default.
    assert_eq!(
        http_as(&server, None, "GET", "/api/scenes", None).await.0,
        200
    );

    // Websocket: anonymous hello, then a command → typed error with the command's id.
    let mut ws = raw_as(&server, Encoding::Json, None).await;
    let msg = serde_json::json!({"type": "command", "id": 7, "command": serde_json::from_str::<Value>(rotate).unwrap()});
    ws.send(Message::Text(msg.to_string().into()))
        .await
        .unwrap();
    match next_text(&mut ws).await {
        Some(ServerMsg::Error(e)) => {
            assert_eq!(e.code, ErrorCode::Unauthorized);
            assert_eq!(e.id, Some(7));
        }
        other => panic!("expected unauthorized, got {other:?}"),
    }

    // Nothing changed: the joint streams the same rotation and the state is the same.
    let after = streamed(&watcher, &avatar, "l_elbow").await;
    assert!(
        angle_between_degrees(before, after) < 1e-3,
        "the refused command moved the elbow"
    );
    assert_eq!(avatar_state(&server, "avatar").await, before_state);

    // The refusals are counted: two over REST, one over the websocket.
    let (_, metrics) = http(&server, "GET", "/metrics", None).await;
    let refused = |code: &str| -> u64 {
        let key = format!("posecast_refused_total{{code=\"{code}\"}} ");
        metrics
            .lines()
            .find_map(|l| l.strip_prefix(key.as_str()))
            .and_then(|v| v.trim().parse().ok())
            .unwrap_or_else(|| panic!("{key} missing:\n{metrics}"))
    };
    assert_eq!((refused("unauthorized"), refused("forbidden")), (3, 0));

    // The control token works, on both surfaces.
    let (status, _) = command_as(&server, Some(CONTROL), rotate).await;
    assert_eq!(status, 200);
    let moved = streamed(&watcher, &avatar, "l_elbow").await;
    assert!(
        angle_between_degrees(moved, Quat::from_rotation_z(std::f32::consts::FRAC_PI_2)) < 0.05
    );
    server.stop().await;
}

#[tokio::test]
async fn a_token_limited_to_avatar_a_cannot_command_avatar_b() {
    let server = server_with(60.0, access(true)).await;
    for name in ["alice", "bob"] {
        let add = format!(
            r#"{{"op":"add_avatar","scene":"default","asset":"avatar","avatar":"{name}","clip":"idle"}}"#
        );
        assert_eq!(command_as(&server, Some(CONTROL), &add).await.0, 200);
        let pause = format!(r#"{{"op":"pause","avatar":"{name}"}}"#);
        assert_eq!(command_as(&server, Some(CONTROL), &pause).await.0, 200);
    }
    let watcher = client(&server, Encoding::Binary).await;
    let (alice, bob) = (id("alice"), id("bob"));
    assert!(
        wait_for(3.0, || watcher.latest(&bob).is_some()
            && watcher.latest(&alice).is_some())
        .await
    );
    let bob_before = streamed(&watcher, &bob, "r_shoulder").await;
    let bob_state = avatar_state(&server, "bob").await;

    let rotate = |who: &str| {
        format!(
            r#"{{"op":"set_joint_rotation","avatar":"{who}","joint":"r_shoulder","rotation":[0.5,0,0,0.8660254]}}"#
        )
    };
    // REST: 403 for bob, 200 for alice.
    let (status, body) = command_as(&server, Some(ALICE), &rotate("bob")).await;
    assert_eq!(
        (status, body["code"].as_str()),
        (403, Some("forbidden")),
        "{body}"
    );
    assert!(body["message"].as_str().unwrap().contains("bob"));
    let (status, body) = command_as(&server, Some(ALICE), &rotate("alice")).await;
    assert_eq!(status, 200, "{body}");
    // Scene-level commands are not an avatar token's to run.
    let create = r#"{"op":"create_scene","scene":"mine"}"#;
    assert_eq!(command_as(&server, Some(ALICE), create).await.0, 403);
    let remove = r#"{"op":"remove_avatar","avatar":"bob"}"#;
    assert_eq!(command_as(&server, Some(ALICE), remove).await.0, 403);

    // Uploads need an unlimited control token; nothing is read or stored otherwise.
    let bvh = "HIERARCHY\nROOT hips\n{\n OFFSET 0 0 0\n CHANNELS 3 Xrotation Yrotation Zrotation\n End Site\n {\n  OFFSET 0 1 0\n }\n}\nMOTION\nFrames: 1\nFrame Time: 0.1\n0 0 0\n";
    for (token, status) in [(Some(ALICE), 403), (Some(VIEWER), 403), (None, 401)] {
        let (got, body) = http_as(
            &server,
            token,
            "POST",
            "/api/assets/stick?format=bvh",
            Some(bvh),
        )
        .await;
        assert_eq!(got, status, "{token:?}: {body}");
    }
    let (_, assets) = http(&server, "GET", "/api/assets", None).await;
    assert!(!assets.contains("stick"), "{assets}");
    let (got, body) = http(&server, "POST", "/api/assets/stick?format=bvh", Some(bvh)).await;
    assert_eq!(got, 200, "the control token uploads: {body}");

    // Websocket with alice's token: the library client reports the typed error.
    let mut options = posecast_client::net::ClientOptions::new(server.ws_url(), "default");
    options.reconnect = false;
    options.token = Some(ALICE.into());
    let a = Client::connect(options).await.unwrap();
    let refused = a
        .command(Command::Play {
            avatar: bob.clone(),
            clip: "walk".into(),
            from_asset: None,
            speed: None,
            looping: None,
            start: None,
            fade: None,
            root_motion: None,
        })
        .await;
    match refused {
        Err(ClientError::Server(e)) => assert_eq!(e.code, ErrorCode::Forbidden),
        other => panic!("expected forbidden, got {other:?}"),
    }
    a.command(Command::Resume {
        avatar: alice.clone(),
    })
    .await
    .unwrap();

    // Bob streams what he did before and his state is unchanged; alice moved.
    let bob_after = streamed(&watcher, &bob, "r_shoulder").await;
    assert!(angle_between_degrees(bob_before, bob_after) < 1e-3);
    assert_eq!(avatar_state(&server, "bob").await, bob_state);
    let alice_state = avatar_state(&server, "alice").await;
    assert_eq!(alice_state["paused"], Value::Bool(false), "{alice_state}");
    server.stop().await;
}

#[tokio::test]
async fn scene_tokens_view_tokens_and_private_views() {
    let server = server_with(60.0, access(false)).await;
    // A scene token creates its scene and drives avatars in it, and nothing else.
    let create = r#"{"op":"create_scene","scene":"lobby"}"#;
    assert_eq!(command_as(&server, Some(LOBBY), create).await.0, 200);
    let add =
        r#"{"op":"add_avatar","scene":"lobby","asset":"avatar","avatar":"guest","clip":"wave"}"#;
    assert_eq!(command_as(&server, Some(LOBBY), add).await.0, 200);
    let pause = r#"{"op":"pause","avatar":"guest"}"#;
    assert_eq!(command_as(&server, Some(LOBBY), pause).await.0, 200);
    let pause_default = r#"{"op":"pause","avatar":"avatar"}"#;
    assert_eq!(command_as(&server, Some(LOBBY), pause_default).await.0, 403);
    let delete = r#"{"op":"delete_scene","scene":"default"}"#;
    assert_eq!(command_as(&server, Some(LOBBY), delete).await.0, 403);
    // A view token reads but never commands.
    let (status, body) = command_as(&server, Some(VIEWER), pause_default).await;
    assert_eq!((status, body["code"].as_str()), (403, Some("forbidden")));
    let get = r#"{"op":"get_avatar","avatar":"avatar"}"#;
    assert_eq!(command_as(&server, Some(VIEWER), get).await.0, 200);
    assert_eq!(
        avatar_state(&server, "avatar").await["paused"],
        Value::Bool(false)
    );

    // With private views, a scene token lists only its scenes.
    let (_, listed) = command_as(&server, Some(LOBBY), r#"{"op":"list_scenes"}"#).await;
    let names: Vec<_> = listed["result"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s["scene"].as_str().unwrap().to_owned())
        .collect();
    assert_eq!(names, vec!["lobby"]);
    let (_, all) = http_as(&server, Some(VIEWER), "GET", "/api/scenes", None).await;
    assert!(
        all.contains("\"default\"") && all.contains("\"lobby\""),
        "{all}"
    );

    // Views are private here: anonymous reads get 401 with a bearer challenge.
    let (status, _) = http_as(&server, None, "GET", "/api/scenes", None).await;
    assert_eq!(status, 401);
    assert_eq!(
        http_as(&server, Some(VIEWER), "GET", "/api/scenes", None)
            .await
            .0,
        200
    );
    assert_eq!(command_as(&server, None, get).await.0, 401);

    // Websocket: an anonymous subscribe is refused; an unknown token is reported after the
    // welcome, and the connection stays (anonymous) rather than being dropped.
    let mut ws = raw_as(&server, Encoding::Json, None).await;
    let subscribe = ClientMsg::Subscribe {
        scene: SceneId("default".into()),
        avatars: None,
        rate: None,
        joints: None,
        morph_weights: None,
        precision: None,
    };
    let text = serde_json::to_string(&subscribe).unwrap();
    ws.send(Message::Text(text.clone().into())).await.unwrap();
    match next_text(&mut ws).await {
        Some(ServerMsg::Error(e)) => assert_eq!(e.code, ErrorCode::Unauthorized),
        other => panic!("expected unauthorized, got {other:?}"),
    }
    let (mut bad, _) = tokio_tungstenite::connect_async(server.ws_url())
        .await
        .unwrap();
    let hello = ClientMsg::Hello {
        version: posecast_proto::msg::PROTOCOL_VERSION,
        encoding: Encoding::Json,
        token: Some("wrong-token-xyz".into()),
        client: None,
    };
    bad.send(Message::Text(serde_json::to_string(&hello).unwrap().into()))
        .await
        .unwrap();
    match next_text(&mut bad).await {
        Some(ServerMsg::Welcome { access, .. }) => {
            assert!(!access.view && !access.control && access.name.is_none());
        }
        other => panic!("expected welcome, got {other:?}"),
    }
    match next_text(&mut bad).await {
        Some(ServerMsg::Error(e)) => assert_eq!(e.code, ErrorCode::Unauthorized),
        other => panic!("expected unauthorized, got {other:?}"),
    }

    // The lobby token watches its own scene only; the welcome says so.
    let mut lobby = raw_as(&server, Encoding::Json, Some(LOBBY)).await;
    lobby.send(Message::Text(text.into())).await.unwrap();
    match next_text(&mut lobby).await {
        Some(ServerMsg::Error(e)) => assert_eq!(e.code, ErrorCode::Forbidden),
        other => panic!("expected forbidden, got {other:?}"),
    }
    let own = ClientMsg::Subscribe {
        scene: SceneId("lobby".into()),
        avatars: None,
        rate: None,
        joints: None,
        morph_weights: None,
        precision: None,
    };
    lobby
        .send(Message::Text(serde_json::to_string(&own).unwrap().into()))
        .await
        .unwrap();
    match next_text(&mut lobby).await {
        Some(ServerMsg::Subscribed { scene, .. }) => assert_eq!(scene.0, "lobby"),
        other => panic!("expected subscribed, got {other:?}"),
    }
    server.stop().await;
}

#[tokio::test]
async fn a_server_without_control_tokens_refuses_every_command() {
    let server = server_with(60.0, AccessConfig::default()).await;
    let (status, body) = command_as(&server, None, r#"{"op":"pause","avatar":"avatar"}"#).await;
    assert_eq!((status, body["code"].as_str()), (401, Some("unauthorized")));
    // The common helper's token is not configured on this server.
    assert_eq!(http(&server, "GET", "/api/scenes", None).await.0, 401);
    server.stop().await;
}

/// The binary with no token configured generates one, prints it once (with a dashboard link
/// carrying it), and accepts only it.
#[tokio::test]
async fn the_binary_generates_and_prints_a_control_token_when_none_is_given() {
    let server = common::child::Posecast::start(&["--no-persist"], &[]);
    // The token lines follow the URL line the harness waited for.
    wait_for(5.0, || {
        server.output().iter().any(|l| l.contains("dashboard:"))
    })
    .await;
    let output = server.output();
    let token = output
        .iter()
        .find_map(|l| l.trim().strip_prefix("control token (generated): "))
        .unwrap_or_else(|| panic!("no token printed: {output:?}"))
        .to_owned();
    assert_eq!(token.len(), 32, "128 bits in hex: {token}");
    assert!(
        output
            .iter()
            .any(|l| l.contains(&format!("/#control={token}"))),
        "{output:?}"
    );
    let pause = br#"{"op":"pause","avatar":"avatar"}"#;
    let post = |token: Option<String>| async move {
        let (status, _) = common::http_request(
            server.addr,
            token.as_deref(),
            "POST",
            "/api/commands",
            "application/json",
            pause,
        )
        .await;
        status
    };
    assert_eq!(post(None).await, 401);
    assert_eq!(post(Some(CONTROL.into())).await, 401);
    assert_eq!(post(Some(token.clone())).await, 200);
    // The token is printed for the operator, never logged.
    let logged = server
        .output()
        .iter()
        .filter(|l| l.contains(&token))
        .count();
    assert_eq!(
        logged, 2,
        "the token appears only in the two start-up lines"
    );
    server.kill();
}
