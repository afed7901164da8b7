//! Shared set-up for the end-to-end tests: an in-process server on port 0 and clients.

#![allow(dead_code, clippy::unwrap_used, clippy::expect_used)]

use futures_util::{SinkExt, StreamExt};
use posecast_client::net::{Client, ClientOptions};
use posecast_proto::msg::{ClientMsg, Encoding, PROTOCOL_VERSION, ServerMsg};
use posecast_server::auth::{AccessConfig, Role, Secret, TokenRule};
use posecast_server::startup::Server;
use posecast_server::state::Config;
use std::time::Duration;
use tokio_tungstenite::tungstenite::Message;

pub type Ws =
    tokio_tungstenite::WebSocketStream<tokio_tungstenite::MaybeTlsStream<tokio::net::TcpStream>>;

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

/// A server with the built-in avatar at `tick_rate` Hz on an ephemeral port.
pub async fn server(tick_rate: f32) -> Server {
    server_with(tick_rate, test_access()).await
}

/// [`server`] with other access rules.
pub async fn server_with(tick_rate: f32, access: AccessConfig) -> Server {
    let config = Config {
        listen: "127.0.0.1:0".parse().unwrap(),
        tick_rate,
        access,
        ..Config::default()
    };
    Server::start(config).await.unwrap()
}

/// A library client subscribed to `default`, holding the control token.
pub async fn client(server: &Server, encoding: Encoding) -> Client {
    let mut options = ClientOptions::new(server.ws_url(), "default");
    options.encoding = encoding;
    options.reconnect = false;
    options.token = Some(CONTROL.into());
    Client::connect(options).await.unwrap()
}

/// A raw websocket that has said hello with the control token (and read the welcome).
pub async fn raw(server: &Server, encoding: Encoding) -> Ws {
    raw_as(server, encoding, Some(CONTROL)).await
}

/// A raw websocket that has said hello with `token` (and read the welcome).
pub async fn raw_as(server: &Server, encoding: Encoding, token: Option<&str>) -> Ws {
    let (mut ws, _) = tokio_tungstenite::connect_async(server.ws_url())
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

/// A minimal HTTP/1.1 request with the control token (Connection: close); returns status
/// and body.
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
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let mut stream = tokio::net::TcpStream::connect(server.addr).await.unwrap();
    let body = body.unwrap_or("");
    let auth = token.map_or(String::new(), |t| format!("Authorization: Bearer {t}\r\n"));
    let request = format!(
        "{method} {path} HTTP/1.1\r\nHost: {}\r\nConnection: close\r\n{auth}Content-Type: application/json\r\nContent-Length: {}\r\n\r\n{body}",
        server.addr,
        body.len()
    );
    stream.write_all(request.as_bytes()).await.unwrap();
    let mut response = Vec::new();
    stream.read_to_end(&mut response).await.unwrap();
    let text = String::from_utf8_lossy(&response).to_string();
    let status = text
        .split(' ')
        .nth(1)
        .and_then(|s| s.parse().ok())
        .unwrap_or(0);
    let body = text
        .split_once("\r\n\r\n")
        .map(|(_, b)| b.to_string())
        .unwrap_or_default();
    // Chunked bodies: keep it simple by stripping chunk-size lines for small JSON answers.
    let body = if text
        .to_ascii_lowercase()
        .contains("transfer-encoding: chunked")
    {
        body.lines()
            .filter(|l| !l.chars().all(|c| c.is_ascii_hexdigit()) || l.is_empty())
            .collect::<Vec<_>>()
            .join("\n")
    } else {
        body
    };
    (status, body)
}
