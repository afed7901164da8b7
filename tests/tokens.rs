//! Minted tokens end to end (issue 39): `POST /api/tokens` needs an admin token; a minted token
//! does what its rights and limits say and nothing else; revoking or expiring it refuses it at
//! once and closes the connections holding it; tokens and revocations survive a restart.

#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use common::{CONTROL, http_as, http_request, next_text, raw_as, server_with, test_access};
use futures_util::{SinkExt, StreamExt};
use posecast_proto::msg::{ClientMsg, Encoding, ErrorCode, ServerMsg};
use posecast_proto::tokens::{MintedToken, Right, TokenInfo};
use posecast_server::auth::{AccessConfig, Role, Secret, TokenRule};
use posecast_server::startup::Server;
use serde_json::{Value, json};
use tokio_tungstenite::tungstenite::Message;

const LOBBY: &str = "lobby-control-token";

/// Views closed (so the view right matters), the test's admin token and a configured control
/// token limited to scene `lobby`.
fn access() -> AccessConfig {
    let mut a = test_access();
    a.open_view = false;
    let mut lobby = TokenRule::new("lobby", Secret::new(LOBBY), Role::Control);
    lobby.scenes = Some(vec![posecast_proto::msg::SceneId("lobby".into())]);
    a.add(lobby).unwrap();
    a
}

async fn mint(server: &Server, token: Option<&str>, request: &Value) -> (u16, Value) {
    let (status, body) = http_as(
        server,
        token,
        "POST",
        "/api/tokens",
        Some(&request.to_string()),
    )
    .await;
    (status, serde_json::from_str(&body).unwrap_or(Value::Null))
}

async fn minted(server: &Server, request: Value) -> MintedToken {
    let (status, body) = mint(server, Some(CONTROL), &request).await;
    assert_eq!(status, 201, "{body}");
    serde_json::from_value(body).unwrap()
}

async fn command(server: &Server, token: &str, command: &str) -> (u16, Value) {
    let (status, body) = http_as(server, Some(token), "POST", "/api/commands", Some(command)).await;
    (status, serde_json::from_str(&body).unwrap_or(Value::Null))
}

async fn listed(server: &Server) -> Vec<TokenInfo> {
    let (status, body) = http_as(server, Some(CONTROL), "GET", "/api/tokens", None).await;
    assert_eq!(status, 200, "{body}");
    serde_json::from_str(&body).unwrap()
}

/// A websocket that said hello with `token`: its welcome's access, and the socket.
async fn hello(server: &Server, token: &str) -> (posecast_proto::msg::Access, common::Ws) {
    hello_at(server.addr, token).await
}

async fn hello_at(
    addr: std::net::SocketAddr,
    token: &str,
) -> (posecast_proto::msg::Access, common::Ws) {
    let (mut ws, _) = tokio_tungstenite::connect_async(format!("ws://{addr}/ws"))
        .await
        .unwrap();
    let hello = ClientMsg::Hello {
        version: posecast_proto::msg::PROTOCOL_VERSION,
        encoding: Encoding::Json,
        token: Some(token.into()),
        client: None,
    };
    ws.send(Message::Text(serde_json::to_string(&hello).unwrap().into()))
        .await
        .unwrap();
    match next_text(&mut ws).await {
        Some(ServerMsg::Welcome { access, .. }) => (access, ws),
        other => panic!("expected welcome, got {other:?}"),
    }
}

/// Reads until the server's close frame (skipping frames), returning the errors seen on
/// the way and the close reason (empty when the server never closed).
async fn until_closed(ws: &mut common::Ws) -> (Vec<ErrorCode>, String) {
    let mut errors = Vec::new();
    // A bound far above what any machine needs (the token has 20 s to live), so that a server
    // that never closes fails the test instead of hanging it.
    let deadline = tokio::time::Instant::now() + std::time::Duration::from_secs(120);
    while let Ok(Some(m)) = tokio::time::timeout_at(deadline, ws.next()).await {
        match m.unwrap() {
            Message::Text(t) => {
                if let Ok(ServerMsg::Error(e)) = serde_json::from_str(t.as_str()) {
                    errors.push(e.code);
                }
            }
            Message::Close(frame) => {
                return (
                    errors,
                    frame.map(|f| f.reason.to_string()).unwrap_or_default(),
                );
            }
            _ => {}
        }
    }
    (errors, String::new())
}

#[tokio::test]
async fn only_an_admin_mints_and_a_minted_token_does_what_its_rights_say() {
    let server = server_with(60.0, access()).await;
    let request =
        json!({"name": "alice", "rights": ["view", "drive"], "avatars": ["avatar"], "ttl_s": 600});

    // Nobody, a limited control token: refused, and nothing is minted.
    assert_eq!(mint(&server, None, &request).await.0, 401);
    let (status, body) = mint(&server, Some(LOBBY), &request).await;
    assert_eq!(
        (status, body["code"].as_str()),
        (403, Some("forbidden")),
        "{body}"
    );
    assert!(listed(&server).await.is_empty());
    // Requests outside the limits: typed errors.
    for (bad, code) in [
        (json!({"name": "", "rights": ["view"]}), 400),
        (json!({"name": "test", "rights": ["view"]}), 400), // a configured token's name
        (json!({"name": "x", "rights": ["fly"]}), 400),
        (json!({"name": "x", "ttl_s": 0}), 400),
        (json!({"name": "x", "extra": 1}), 400),
    ] {
        assert_eq!(mint(&server, Some(CONTROL), &bad).await.0, code, "{bad}");
    }

    let alice = minted(&server, request).await;
    assert_eq!(alice.info.rights, vec![Right::View, Right::Drive]);
    assert_eq!(alice.info.expires_at - alice.info.issued_at, 600);
    assert_eq!(listed(&server).await, vec![alice.info.clone()]);

    // The welcome tells the client what it may do.
    let (access, mut ws) = hello(&server, &alice.token).await;
    assert_eq!(access.name.as_deref(), Some("alice"));
    assert!(access.view && !access.control);
    assert_eq!(access.rights, vec![Right::View, Right::Drive]);
    assert_eq!(access.expires_at, Some(alice.info.expires_at));

    // Drive: its own avatar, yes (over the websocket, where poses stream); no control
    // command, no other avatar, no recording.
    for (id, op, ok) in [
        (1, json!({"op": "drive", "avatar": "avatar"}), true),
        (2, json!({"op": "pause", "avatar": "avatar"}), false),
        (
            3,
            json!({"op": "record", "avatar": "avatar", "clip": "take"}),
            false,
        ),
        (4, json!({"op": "release_drive", "avatar": "avatar"}), true),
    ] {
        let msg = json!({"type": "command", "id": id, "command": op});
        ws.send(Message::Text(msg.to_string().into()))
            .await
            .unwrap();
        match next_text(&mut ws).await {
            Some(ServerMsg::Ack { id: got, .. }) if ok => assert_eq!(got, id),
            Some(ServerMsg::Error(e)) if !ok => {
                assert_eq!((e.code, e.id), (ErrorCode::Forbidden, Some(id)), "{e:?}");
            }
            other => panic!("command {id}: {other:?}"),
        }
    }
    ws.close(None).await.unwrap();
    let (status, body) =
        command(&server, &alice.token, r#"{"op":"pause","avatar":"avatar"}"#).await;
    assert_eq!((status, body["code"].as_str()), (403, Some("forbidden")));
    assert!(
        body["message"].as_str().unwrap().contains("control"),
        "{body}"
    );

    // View: reads work with views closed.
    assert_eq!(
        http_as(&server, Some(&alice.token), "GET", "/api/scenes", None)
            .await
            .0,
        200
    );
    // No upload right.
    let (status, _) = http_request(
        server.addr,
        Some(&alice.token),
        "POST",
        "/api/assets/x",
        "application/octet-stream",
        b"x",
    )
    .await;
    assert_eq!(status, 403);
    // A minted token never mints, lists or revokes.
    assert_eq!(
        mint(&server, Some(&alice.token), &json!({"name": "eve"}))
            .await
            .0,
        403
    );
    assert_eq!(
        http_as(&server, Some(&alice.token), "GET", "/api/tokens", None)
            .await
            .0,
        403
    );

    // Without the view right, a closed server shows nothing.
    let blind = minted(&server, json!({"name": "bob", "rights": ["control"]})).await;
    assert_eq!(
        http_as(&server, Some(&blind.token), "GET", "/api/scenes", None)
            .await
            .0,
        403
    );
    // ... but control brings drive, and every avatar (no limits).
    assert_eq!(
        command(&server, &blind.token, r#"{"op":"pause","avatar":"avatar"}"#)
            .await
            .0,
        200
    );

    // Forged: another right added to the claims, the signature kept.
    let (_, tag) = alice.token.rsplit_once('.').unwrap();
    let mut claims = alice.info.clone();
    claims.rights.push(Right::Control);
    let forged = format!(
        "pc1.{}.{tag}",
        base64_url(&serde_json::to_vec(&claims).unwrap())
    );
    let (status, body) = command(&server, &forged, r#"{"op":"pause","avatar":"avatar"}"#).await;
    assert_eq!((status, body["code"].as_str()), (401, Some("unauthorized")));
    server.stop().await;
}

#[tokio::test]
async fn revoking_refuses_the_token_and_closes_its_connections() {
    let server = server_with(60.0, access()).await;
    let keep = minted(&server, json!({"name": "carol", "rights": ["view"]})).await;
    let gone = minted(
        &server,
        json!({"name": "dan", "rights": ["view", "control"]}),
    )
    .await;
    let (_, mut kept_ws) = hello(&server, &keep.token).await;
    let (_, mut ws) = hello(&server, &gone.token).await;
    ws.send(Message::Text(
        r#"{"type":"subscribe","scene":"default"}"#.into(),
    ))
    .await
    .unwrap();

    // Only an admin revokes; a malformed id is a typed error.
    let path = format!("/api/tokens/{}", gone.info.id);
    assert_eq!(
        http_as(&server, Some(&keep.token), "DELETE", &path, None)
            .await
            .0,
        403
    );
    assert_eq!(
        http_as(&server, Some(CONTROL), "DELETE", "/api/tokens/nope", None)
            .await
            .0,
        400
    );
    assert_eq!(
        http_as(&server, Some(CONTROL), "DELETE", &path, None)
            .await
            .0,
        204
    );

    let (errors, reason) = until_closed(&mut ws).await;
    assert!(errors.contains(&ErrorCode::Unauthorized), "{errors:?}");
    assert_eq!(reason, "token no longer valid");
    let (status, body) = command(&server, &gone.token, r#"{"op":"pause","avatar":"avatar"}"#).await;
    assert_eq!(status, 401);
    assert!(
        body["message"].as_str().unwrap().contains("revoked"),
        "{body}"
    );
    assert_eq!(listed(&server).await, vec![keep.info.clone()]);

    // The other token's connection is untouched.
    kept_ws
        .send(Message::Text(
            r#"{"type":"ping","id":5,"client_time_us":1}"#.into(),
        ))
        .await
        .unwrap();
    assert!(matches!(
        next_text(&mut kept_ws).await,
        Some(ServerMsg::Pong { id: 5, .. })
    ));
    server.stop().await;
}

#[tokio::test]
async fn an_expired_token_is_refused_and_its_connection_closed() {
    let server = server_with(60.0, access()).await;
    // Long enough that the hello below is answered before it expires, even on a machine busy
    // with another build (the test then waits for the expiry, however long it takes to come).
    let brief = minted(
        &server,
        json!({"name": "erin", "rights": ["view"], "ttl_s": 20}),
    )
    .await;
    let (access, mut ws) = hello(&server, &brief.token).await;
    assert_eq!(
        access.name.as_deref(),
        Some("erin"),
        "accepted before it expired"
    );
    let (errors, reason) = until_closed(&mut ws).await;
    assert!(errors.contains(&ErrorCode::Unauthorized), "{errors:?}");
    assert_eq!(reason, "token no longer valid");
    let (status, body) = http_as(&server, Some(&brief.token), "GET", "/api/scenes", None).await;
    assert_eq!(status, 401);
    assert!(body.contains("expired"), "{body}");
    assert!(
        listed(&server).await.is_empty(),
        "expired tokens are not listed"
    );
    server.stop().await;
}

#[tokio::test]
async fn minted_tokens_and_revocations_survive_a_restart_and_no_other_key_accepts_them() {
    let dir = tempfile::tempdir().unwrap();
    let start = |dir: std::path::PathBuf| async move {
        posecast_testkit::TestServer::builder()
            .tick_rate(30.0)
            .access(access())
            .control_token(CONTROL)
            .data_dir(dir)
            .start()
            .await
            .unwrap()
            .into_server()
    };
    let server = start(dir.path().to_owned()).await;
    let keep = minted(
        &server,
        json!({"name": "fay", "rights": ["view", "control"]}),
    )
    .await;
    let gone = minted(
        &server,
        json!({"name": "gus", "rights": ["view", "control"]}),
    )
    .await;
    assert_eq!(
        http_as(
            &server,
            Some(CONTROL),
            "DELETE",
            &format!("/api/tokens/{}", gone.info.id),
            None
        )
        .await
        .0,
        204
    );
    server.stop().await;

    let server = start(dir.path().to_owned()).await;
    let pause = r#"{"op":"pause","avatar":"avatar"}"#;
    assert_eq!(command(&server, &keep.token, pause).await.0, 200);
    assert_eq!(command(&server, &gone.token, pause).await.0, 401);
    assert_eq!(listed(&server).await, vec![keep.info.clone()]);
    server.stop().await;

    // Another data folder, another key: the token means nothing there.
    let other = tempfile::tempdir().unwrap();
    let server = start(other.path().to_owned()).await;
    let (status, body) = command(&server, &keep.token, pause).await;
    assert_eq!((status, body["code"].as_str()), (401, Some("unauthorized")));
    server.stop().await;
}

/// The `raw_as` helper with the control token still works beside minted ones (no regression
/// of configured tokens).
#[tokio::test]
async fn configured_tokens_keep_every_right() {
    let server = server_with(60.0, access()).await;
    let mut ws = raw_as(&server, Encoding::Json, Some(CONTROL)).await;
    ws.close(None).await.unwrap();
    let (access, _ws) = hello(&server, LOBBY).await;
    // A configured control token limited to a scene: everything but uploads.
    assert_eq!(
        access.rights,
        vec![Right::View, Right::Control, Right::Drive, Right::Record]
    );
    let (access, _ws) = hello(&server, CONTROL).await;
    assert_eq!(access.rights, Right::ALL.to_vec());
    assert_eq!(access.expires_at, None);
    server.stop().await;
}

fn base64_url(bytes: &[u8]) -> String {
    const ALPHABET: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789-_";
    let mut out = String::new();
    for chunk in bytes.chunks(3) {
        let n = chunk
            .iter()
            .enumerate()
            .fold(0u32, |n, (i, &b)| n | u32::from(b) << (16 - 8 * i));
        for i in 0..=chunk.len() {
            out.push(char::from(ALPHABET[(n >> (18 - 6 * i) & 63) as usize]));
        }
    }
    out
}

#[test]
fn base64_url_matches_rfc_4648() {
    // RFC 4648 §10 test vectors (without padding).
    for (plain, coded) in [
        ("f", "Zg"),
        ("fo", "Zm8"),
        ("foo", "Zm9v"),
        ("foob", "Zm9vYg"),
        ("fooba", "Zm9vYmE"),
        ("foobar", "Zm9vYmFy"),
    ] {
        assert_eq!(base64_url(plain.as_bytes()), coded);
    }
}

/// In a cluster whose servers share `--cluster-secret`, a token minted on one server is
/// accepted by the others, and revoking it on one closes its connections on every server and
/// refuses it on a server that joins later.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_cluster_accepts_a_minted_token_everywhere_and_revokes_it_everywhere() {
    let Some(nats) = common::nats::Nats::start() else {
        return;
    };
    let url = nats.url();
    let node = |name: &str| {
        common::child::Posecast::start(
            &[
                "--nats",
                &url,
                "--node",
                name,
                "--no-persist",
                "--control-token",
                CONTROL,
            ],
            &[(
                "POSECAST_CLUSTER_SECRET",
                "a-cluster-secret-for-the-tokens-test",
            )],
        )
    };
    let (a, b) = (node("a"), node("b"));
    let body = json!({"name": "hana", "rights": ["view", "drive"], "ttl_s": 600}).to_string();
    let (status, answer) = http_request(
        a.addr,
        Some(CONTROL),
        "POST",
        "/api/tokens",
        "application/json",
        body.as_bytes(),
    )
    .await;
    assert_eq!(status, 201, "{answer}");
    let hana: MintedToken = serde_json::from_str(&answer).unwrap();

    // Accepted on the other server, which never saw it minted.
    let (access, mut on_b) = hello_at(b.addr, &hana.token).await;
    assert_eq!(access.name.as_deref(), Some("hana"));

    let path = format!("/api/tokens/{}", hana.info.id);
    assert_eq!(
        http_request(
            a.addr,
            Some(CONTROL),
            "DELETE",
            &path,
            "application/json",
            b""
        )
        .await
        .0,
        204
    );
    let (errors, reason) = until_closed(&mut on_b).await;
    assert!(errors.contains(&ErrorCode::Unauthorized), "{errors:?}");
    assert_eq!(reason, "token no longer valid");
    let (status, body) = http_request(
        b.addr,
        Some(&hana.token),
        "GET",
        "/api/scenes",
        "application/json",
        b"",
    )
    .await;
    assert_eq!(status, 401, "{body}");

    // A server that joins afterwards learns the revocation from the cluster's bucket.
    let c = node("c");
    let (status, body) = http_request(
        c.addr,
        Some(&hana.token),
        "GET",
        "/api/scenes",
        "application/json",
        b"",
    )
    .await;
    assert_eq!(status, 401, "{body}");
    assert!(body.contains("revoked"), "{body}");
}
