//! What the end-to-end tests share beyond `posecast-testkit` (which starts the in-process
//! servers and connects the clients): this repository's fixed control token and access rules,
//! `Server`/`Client`-returning shorthands for the tests written before the kit, raw websockets,
//! HTTP requests, uploads and the shared test files.

#![allow(dead_code, clippy::unwrap_used, clippy::expect_used)]

pub mod child;
pub mod cluster;
pub mod feed;
pub mod http;
pub mod link;
pub mod nats;
pub mod vmc;
pub mod watch;

use futures_util::{SinkExt, StreamExt};
use posecast_client::net::Client;
use posecast_proto::msg::{ClientMsg, Encoding, PROTOCOL_VERSION, ServerMsg};
use posecast_server::auth::{AccessConfig, Role, Secret, TokenRule};
use posecast_server::startup::Server;
use posecast_testkit::{ClientBuilder, TestServer, TestServerBuilder};
use std::time::Duration;
use tokio_tungstenite::tungstenite::Message;

pub type Ws =
    tokio_tungstenite::WebSocketStream<tokio_tungstenite::MaybeTlsStream<tokio::net::TcpStream>>;

/// Sends `hello` (this protocol version, `encoding`, no token, client name `client`) and
/// `subscribe` to every avatar and joint of `scene` at the full rate.
pub async fn hello_and_subscribe<S>(
    ws: &mut S,
    encoding: Encoding,
    scene: &str,
    client: Option<&str>,
) where
    S: futures_util::Sink<Message> + Unpin,
    S::Error: std::fmt::Debug,
{
    for msg in [
        ClientMsg::Hello {
            version: PROTOCOL_VERSION,
            encoding,
            token: None,
            client: client.map(str::to_owned),
        },
        ClientMsg::Subscribe {
            scene: posecast_proto::msg::SceneId(scene.into()),
            avatars: None,
            rate: None,
            joints: None,
            morph_weights: None,
            precision: None,
        },
    ] {
        let text = serde_json::to_string(&msg).unwrap();
        ws.send(Message::Text(text.into())).await.unwrap();
    }
}

/// The value of metric `name` (a line `name value`) in `addr`'s `/metrics`, read with the
/// control token.
pub async fn metric(addr: std::net::SocketAddr, name: &str) -> f64 {
    let (status, text) =
        http_request(addr, Some(CONTROL), "GET", "/metrics", "text/plain", b"").await;
    assert_eq!(status, 200);
    text.lines()
        .find_map(|l| l.strip_prefix(name)?.strip_prefix(' ')?.trim().parse().ok())
        .unwrap_or_else(|| panic!("no {name} in {text}"))
}

/// The unlimited control token of [`server`]'s servers.
pub const CONTROL: &str = "test-control-token";

/// The access rules of [`server`]: open views, one unlimited control token [`CONTROL`].
pub fn test_access() -> AccessConfig {
    let mut access = AccessConfig::default();
    access
        .add(TokenRule::new("test", Secret::new(CONTROL), Role::Control))
        .unwrap();
    access
}

/// A kit server with the built-in avatar at `tick_rate` Hz, [`test_access`]'s rules, and
/// [`CONTROL`] as the token its clients and drivers present.
pub async fn kit_server(tick_rate: f32) -> TestServer {
    kit_builder(tick_rate).start().await.unwrap()
}

/// [`kit_server`]'s builder, to change more before starting.
pub fn kit_builder(tick_rate: f32) -> TestServerBuilder {
    TestServer::builder()
        .tick_rate(tick_rate)
        .access(test_access())
        .control_token(CONTROL)
}

/// A server with the built-in avatar at `tick_rate` Hz on an ephemeral port.
pub async fn server(tick_rate: f32) -> Server {
    server_with(tick_rate, test_access()).await
}

/// [`server`] with other access rules.
pub async fn server_with(tick_rate: f32, access: AccessConfig) -> Server {
    TestServer::builder()
        .tick_rate(tick_rate)
        .access(access)
        .control_token(CONTROL)
        .start()
        .await
        .unwrap()
        .into_server()
}

/// A library client subscribed to `default`, holding the control token.
pub async fn client(server: &Server, encoding: Encoding) -> Client {
    ClientBuilder::new(server.ws_url())
        .encoding(encoding)
        .token(Some(CONTROL))
        .connect()
        .await
        .unwrap()
        .into_inner()
}

/// A raw websocket that has said hello with the control token (and read the welcome).
pub async fn raw(server: &Server, encoding: Encoding) -> Ws {
    raw_as(server, encoding, Some(CONTROL)).await
}

/// A raw websocket that has said hello with `token` (and read the welcome).
pub async fn raw_as(server: &Server, encoding: Encoding, token: Option<&str>) -> Ws {
    raw_at(server.addr, encoding, token).await
}

/// [`raw_as`] to any address (e.g. a child process's).
pub async fn raw_at(addr: std::net::SocketAddr, encoding: Encoding, token: Option<&str>) -> Ws {
    let (mut ws, _) = tokio_tungstenite::connect_async(format!("ws://{addr}/ws"))
        .await
        .unwrap();
    let hello = ClientMsg::Hello {
        version: PROTOCOL_VERSION,
        encoding,
        token: token.map(str::to_owned),
        client: None,
    };
    ws.send(Message::Text(serde_json::to_string(&hello).unwrap().into()))
        .await
        .unwrap();
    match next_text(&mut ws).await {
        Some(ServerMsg::Welcome { .. }) => ws,
        other => panic!("expected welcome, got {other:?}"),
    }
}

/// The next text message as a `ServerMsg` (skipping binary frames), or `None` on close or
/// after 5 s.
pub async fn next_text(ws: &mut Ws) -> Option<ServerMsg> {
    let deadline = tokio::time::Instant::now() + Duration::from_secs(5);
    loop {
        let msg = tokio::time::timeout_at(deadline, ws.next())
            .await
            .ok()??
            .ok()?;
        match msg {
            Message::Text(t) => return Some(serde_json::from_str(t.as_str()).unwrap()),
            Message::Close(_) => return None,
            _ => {}
        }
    }
}

/// Waits until `f` holds, polling every 10 ms, for at most `secs`.
pub async fn wait_for(secs: f32, mut f: impl FnMut() -> bool) -> bool {
    let deadline = tokio::time::Instant::now() + Duration::from_secs_f32(secs);
    while tokio::time::Instant::now() < deadline {
        if f() {
            return true;
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    f()
}

/// An HTTP request with the control token; returns status and body.
pub async fn http(server: &Server, method: &str, path: &str, body: Option<&str>) -> (u16, String) {
    http_as(server, Some(CONTROL), method, path, body).await
}

/// [`http`] with `token` as bearer token (or none).
pub async fn http_as(
    server: &Server,
    token: Option<&str>,
    method: &str,
    path: &str,
    body: Option<&str>,
) -> (u16, String) {
    http_request(
        server.addr,
        token,
        method,
        path,
        "application/json",
        body.unwrap_or("").as_bytes(),
    )
    .await
}

/// An HTTP request with any body and the control token to `addr`; returns status and body.
pub async fn http_to(
    addr: std::net::SocketAddr,
    method: &str,
    path: &str,
    content_type: &str,
    body: &[u8],
) -> (u16, String) {
    http_request(addr, Some(CONTROL), method, path, content_type, body).await
}

/// [`http_to`] with `token` as bearer token (or none).
pub async fn http_request(
    addr: std::net::SocketAddr,
    token: Option<&str>,
    method: &str,
    path: &str,
    content_type: &str,
    body: &[u8],
) -> (u16, String) {
    let auth = token.map(|t| format!("Bearer {t}"));
    let mut headers = vec![("Content-Type", content_type)];
    if let Some(auth) = &auth {
        headers.push(("Authorization", auth));
    }
    let response = http::request(addr, method, path, &headers, body.to_vec())
        .await
        .unwrap_or_else(|e| panic!("{e}"));
    (response.status, response.text())
}

/// A `multipart/form-data` body with one file part per `(file name, bytes)`; returns the
/// content type (with its boundary) and the body.
pub fn multipart(files: &[(&str, &[u8])]) -> (String, Vec<u8>) {
    multipart_with_fields(files, &[])
}

/// A multipart body of file parts and then text fields (upload options such as `name_map`).
pub fn multipart_with_fields(
    files: &[(&str, &[u8])],
    fields: &[(&str, &str)],
) -> (String, Vec<u8>) {
    let boundary = "posecast-test-boundary-7d1f0c";
    let mut body = Vec::new();
    for (name, bytes) in files {
        body.extend_from_slice(
            format!(
                "--{boundary}\r\nContent-Disposition: form-data; name=\"file\"; filename=\"{name}\"\r\nContent-Type: application/octet-stream\r\n\r\n"
            )
            .as_bytes(),
        );
        body.extend_from_slice(bytes);
        body.extend_from_slice(b"\r\n");
    }
    for (name, text) in fields {
        body.extend_from_slice(
            format!(
                "--{boundary}\r\nContent-Disposition: form-data; name=\"{name}\"\r\n\r\n{text}\r\n"
            )
            .as_bytes(),
        );
    }
    body.extend_from_slice(format!("--{boundary}--\r\n").as_bytes());
    (format!("multipart/form-data; boundary={boundary}"), body)
}

/// Uploads files with a multipart POST to `path` on `addr`.
pub async fn upload_files(
    addr: std::net::SocketAddr,
    path: &str,
    files: &[(&str, &[u8])],
) -> (u16, String) {
    let (content_type, body) = multipart(files);
    http_to(addr, "POST", path, &content_type, &body).await
}

/// A shared test file's bytes, or `None` (with a note; a failure under `CI=true`) when
/// `../shared/testdata` is absent.
pub fn testdata_bytes(relative: &str) -> Option<Vec<u8>> {
    let path = posecast_proto::testing::require_testdata(relative)?;
    Some(std::fs::read(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display())))
}

/// Adds built-in avatars `extra-{i}` for `i` in `numbers` to scene `default`, playing `walk`,
/// `wave` and `idle` in turn (by `i`).
#[allow(dead_code)]
pub async fn add_extras(server: &Server, numbers: std::ops::Range<usize>) {
    for i in numbers {
        server
            .state
            .world
            .add_avatar(
                &posecast_proto::msg::SceneId("default".into()),
                posecast_server::builtin::BUILTIN_ASSET,
                Some(posecast_proto::msg::AvatarId(format!("extra-{i}"))),
            )
            .unwrap();
        let clip = ["walk", "wave", "idle"][i % 3];
        command_to(
            server.addr,
            &format!(r#"{{"op":"play","avatar":"extra-{i}","clip":"{clip}"}}"#),
        )
        .await;
    }
}

/// A REST command to `addr`; returns status and the parsed body.
pub async fn command_to(addr: std::net::SocketAddr, json: &str) -> (u16, serde_json::Value) {
    let (status, body) = http_to(
        addr,
        "POST",
        "/api/commands",
        "application/json",
        json.as_bytes(),
    )
    .await;
    let value = serde_json::from_str(&body).unwrap_or(serde_json::Value::Null);
    (status, value)
}

/// Every file under `dir`, relative, sorted (to check a folder did not change).
pub fn list_tree(dir: &std::path::Path) -> Vec<String> {
    fn walk(root: &std::path::Path, dir: &std::path::Path, out: &mut Vec<String>) {
        if let Ok(entries) = std::fs::read_dir(dir) {
            for e in entries.filter_map(Result::ok) {
                let p = e.path();
                out.push(p.strip_prefix(root).unwrap().display().to_string());
                if p.is_dir() {
                    walk(root, &p, out);
                }
            }
        }
    }
    let mut out = Vec::new();
    walk(dir, dir, &mut out);
    out.sort();
    out
}

/// An HTTP/1.1 request to `addr` with these headers (`Host` is `addr` unless given);
/// returns status, the response head (status line and headers) and body.
pub async fn http_with_headers(
    addr: std::net::SocketAddr,
    method: &str,
    path: &str,
    headers: &[(&str, &str)],
    body: &[u8],
) -> (u16, String, String) {
    let response = http::request(addr, method, path, headers, body.to_vec())
        .await
        .unwrap_or_else(|e| panic!("{e}"));
    (response.status, response.head(), response.text())
}

/// The value of header `name` in a response head from [`http_with_headers`].
pub fn header_value(head: &str, name: &str) -> Option<String> {
    head.lines().find_map(|l| {
        let (k, v) = l.split_once(':')?;
        k.trim()
            .eq_ignore_ascii_case(name)
            .then(|| v.trim().to_owned())
    })
}

/// `GET path` from `addr` with the control token; returns status and the body's bytes (for
/// binary answers such as `.glb`).
pub async fn get_bytes(addr: std::net::SocketAddr, path: &str) -> (u16, Vec<u8>) {
    let auth = format!("Bearer {CONTROL}");
    let response = http::request(addr, "GET", path, &[("Authorization", &auth)], Vec::new())
        .await
        .unwrap_or_else(|e| panic!("{e}"));
    (response.status, response.body)
}

/// A websocket server as one of before protocol version 2 behaves: it welcomes a hello of
/// version 1 (and then says nothing) and refuses any other with `unsupported_version`, closing
/// as a server does. Returns its address and the versions of the hellos it got, in order.
#[allow(dead_code)]
pub async fn version_1_server() -> (
    std::net::SocketAddr,
    std::sync::Arc<std::sync::Mutex<Vec<u32>>>,
) {
    use posecast_proto::msg::{Access, ErrorCode, ProtocolError};
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let hellos = std::sync::Arc::new(std::sync::Mutex::new(Vec::new()));
    let seen = hellos.clone();
    tokio::spawn(async move {
        while let Ok((stream, _)) = listener.accept().await {
            let seen = seen.clone();
            tokio::spawn(async move {
                let Ok(mut ws) = tokio_tungstenite::accept_async(stream).await else {
                    return;
                };
                while let Some(Ok(Message::Text(text))) = ws.next().await {
                    let Ok(ClientMsg::Hello { version, .. }) = serde_json::from_str(&text) else {
                        continue;
                    };
                    seen.lock().unwrap().push(version);
                    let answer = if version == 1 {
                        ServerMsg::Welcome {
                            version: 1,
                            encoding: Encoding::Binary,
                            server: "posecast 0.0.1 (protocol version 1 only)".into(),
                            tick_rate: 60.0,
                            server_time_us: 0,
                            access: Access {
                                view: true,
                                ..Access::default()
                            },
                        }
                    } else {
                        ServerMsg::Error(ProtocolError::new(
                            ErrorCode::UnsupportedVersion,
                            format!("version {version} is not supported; this server speaks 1"),
                        ))
                    };
                    let text = serde_json::to_string(&answer).unwrap();
                    if ws.send(Message::text(text)).await.is_err() {
                        return;
                    }
                    if version != 1 {
                        // Close as a server does: send the close, read until the client's.
                        ws.close(None).await.ok();
                        while let Some(Ok(_)) = ws.next().await {}
                        return;
                    }
                }
            });
        }
    });
    (addr, hellos)
}

/// The built-in avatar's `.glb` as a VRM 1.0 file: its JSON chunk gains a `VRMC_vrm` humanoid
/// naming every joint but `sacroiliac` (VRM has no such bone).
pub fn builtin_as_vrm() -> Vec<u8> {
    builtin_with_bone_map("VRMC_vrm", false)
}

/// The built-in avatar's `.glb` with a VRM 1.0 humanoid bone map in the root extension
/// `extension`, the clavicles and toes included when `full`.
pub fn builtin_with_bone_map(extension: &str, full: bool) -> Vec<u8> {
    edit_glb_json(posecast_server::builtin::AVATAR_GLB, |doc| {
        add_bone_map(doc, extension, full);
    })
}

/// `glb` (a binary glTF with a JSON chunk and a BIN chunk) with its JSON edited by `edit`,
/// the BIN chunk unchanged.
pub fn edit_glb_json(glb: &[u8], edit: impl FnOnce(&mut serde_json::Value)) -> Vec<u8> {
    let json_len = u32::from_le_bytes(glb[12..16].try_into().unwrap()) as usize;
    let mut doc: serde_json::Value = serde_json::from_slice(&glb[20..20 + json_len]).unwrap();
    edit(&mut doc);
    let mut json = serde_json::to_vec(&doc).unwrap();
    while !json.len().is_multiple_of(4) {
        json.push(b' ');
    }
    let bin = &glb[20 + json_len..];
    let mut out = b"glTF".to_vec();
    out.extend_from_slice(&2u32.to_le_bytes());
    out.extend_from_slice(&((12 + 8 + json.len() + bin.len()) as u32).to_le_bytes());
    out.extend_from_slice(&(json.len() as u32).to_le_bytes());
    out.extend_from_slice(b"JSON");
    out.extend_from_slice(&json);
    out.extend_from_slice(bin);
    out
}

fn add_bone_map(doc: &mut serde_json::Value, extension: &str, full: bool) {
    let bones: serde_json::Map<String, serde_json::Value> = doc["nodes"]
        .as_array()
        .unwrap()
        .iter()
        .enumerate()
        .filter_map(|(i, node)| {
            let bone = match node["name"].as_str()? {
                "humanoid_root" => "hips",
                "vl5" => "spine",
                "vt10" => "chest",
                "vt1" => "upperChest",
                "vc4" => "neck",
                "skullbase" => "head",
                "l_shoulder" => "leftUpperArm",
                "l_elbow" => "leftLowerArm",
                "l_wrist" => "leftHand",
                "r_shoulder" => "rightUpperArm",
                "r_elbow" => "rightLowerArm",
                "r_wrist" => "rightHand",
                "l_hip" => "leftUpperLeg",
                "l_knee" => "leftLowerLeg",
                "l_ankle" => "leftFoot",
                "r_hip" => "rightUpperLeg",
                "r_knee" => "rightLowerLeg",
                "r_ankle" => "rightFoot",
                "l_sternoclavicular" if full => "leftShoulder",
                "r_sternoclavicular" if full => "rightShoulder",
                "l_midtarsal" if full => "leftToes",
                "r_midtarsal" if full => "rightToes",
                _ => return None,
            };
            Some((bone.to_owned(), serde_json::json!({ "node": i })))
        })
        .collect();
    doc["extensionsUsed"] = serde_json::json!([extension]);
    let mut root = serde_json::json!({"specVersion": "1.0", "humanoid": {"humanBones": bones}});
    if extension == "VRMC_vrm" {
        // What a VRM 1.0 file's meta must hold (three-vrm's loader reads it).
        root["meta"] = serde_json::json!({"name": "posecast built-in avatar", "authors": ["posecast"],
            "licenseUrl": "https://vrm.dev/licenses/1.0/"});
    }
    doc["extensions"] = serde_json::json!({ extension: root });
}

/// Avatar `avatar`'s latest morph weights by channel name as `client` decodes them, once every
/// channel is at its weight in `want` (0 for those not named) within the wire's bound; fails
/// the test (naming `label`) when they never are.
#[allow(dead_code)]
pub async fn weights_become(
    client: &Client,
    avatar: &str,
    label: &str,
    want: &[(&str, f32)],
) -> Vec<(String, f32)> {
    let read = || {
        client
            .avatars()
            .into_iter()
            .find(|a| a.description.id.0 == avatar)
            .and_then(|a| {
                let weights = a.latest?.weights;
                Some(
                    a.description
                        .morph_targets
                        .iter()
                        .cloned()
                        .zip(weights)
                        .collect::<Vec<_>>(),
                )
            })
            .unwrap_or_default()
    };
    let matches = |got: &[(String, f32)]| {
        !got.is_empty()
            && got.iter().all(|(name, w)| {
                let expected = want
                    .iter()
                    .find(|(n, _)| n == name)
                    .map_or(0.0, |(_, w)| *w);
                (w - expected).abs() <= posecast_proto::morph::MAX_WEIGHT_ERROR
            })
    };
    assert!(
        wait_for(120.0, || matches(&read())).await,
        "{label}: weights of {avatar} never became {want:?}: {:?}",
        read()
    );
    read()
}

/// Reads `ws` until a text message of type `kind` (others skipped), as JSON; fails after
/// 120 s (an event, not a timing).
#[allow(dead_code)]
pub async fn next_of_type(ws: &mut Ws, kind: &str) -> serde_json::Value {
    let deadline = tokio::time::Instant::now() + Duration::from_secs(120);
    loop {
        match tokio::time::timeout_at(deadline, ws.next()).await {
            Ok(Some(Ok(tokio_tungstenite::tungstenite::Message::Text(t)))) => {
                let v: serde_json::Value = serde_json::from_str(&t).unwrap();
                if v["type"] == kind {
                    return v;
                }
            }
            Ok(Some(Ok(_))) => {}
            other => panic!("no {kind}: {other:?}"),
        }
    }
}
