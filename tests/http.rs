//! HTTP details end to end: every error is typed JSON (axum's own 405 and 413 included), the
//! `Bearer` scheme in any case, and the dashboard's Content-Security-Policy.

#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use common::{CONTROL, header_value, http_with_headers, server};
use posecast_proto::msg::MAX_CLIENT_MESSAGE_BYTES;
use serde_json::Value;

/// The typed error body `{code, message}` of a response, or a failure naming what came.
fn typed(what: &str, body: &str) -> (String, String) {
    let v: Value =
        serde_json::from_str(body).unwrap_or_else(|_| panic!("{what}: untyped body {body:?}"));
    let code = v["code"]
        .as_str()
        .unwrap_or_else(|| panic!("{what}: {body}"));
    let message = v["message"]
        .as_str()
        .unwrap_or_else(|| panic!("{what}: {body}"));
    assert!(!message.is_empty(), "{what}: empty message");
    (code.to_owned(), message.to_owned())
}

#[tokio::test]
async fn method_not_allowed_body_too_large_and_unknown_paths_are_typed_json() {
    let server = server(60.0).await;
    let auth = format!("Bearer {CONTROL}");
    let headers = [
        ("Authorization", auth.as_str()),
        ("Content-Type", "application/json"),
    ];

    // A wrong method on a known path: 405, the Allow header kept.
    for (method, path) in [("GET", "/api/commands"), ("DELETE", "/api/scenes")] {
        let (status, head, body) =
            http_with_headers(server.addr, method, path, &headers, b"").await;
        let what = format!("{method} {path}");
        assert_eq!(status, 405, "{what}: {head}");
        assert!(
            header_value(&head, "content-type").is_some_and(|v| v.starts_with("application/json")),
            "{what}: {head}"
        );
        assert!(header_value(&head, "allow").is_some(), "{what}: {head}");
        assert_eq!(typed(&what, &body).0, "method_not_allowed");
    }

    // A command body over the 64 KiB limit: 413.
    let big = format!(
        r#"{{"op":"pause","avatar":"{}"}}"#,
        "a".repeat(MAX_CLIENT_MESSAGE_BYTES)
    );
    let (status, head, body) = http_with_headers(
        server.addr,
        "POST",
        "/api/commands",
        &headers,
        big.as_bytes(),
    )
    .await;
    assert_eq!(status, 413, "{head}");
    assert_eq!(typed("oversized command", &body).0, "too_large");

    // No such path: 404.
    let (status, _, body) =
        http_with_headers(server.addr, "GET", "/api/nothing", &headers, b"").await;
    assert_eq!(status, 404);
    let (code, message) = typed("unknown path", &body);
    assert_eq!(code, "not_found");
    assert!(message.contains("/api/nothing"), "{message}");

    // The handlers' own errors are unchanged.
    let (status, _, body) =
        http_with_headers(server.addr, "POST", "/api/commands", &headers, b"{not json").await;
    assert_eq!(status, 400);
    assert_eq!(typed("bad json", &body).0, "bad_message");
    server.stop().await;
}

#[tokio::test]
async fn the_bearer_scheme_is_case_insensitive() {
    let server = server(60.0).await;
    let pause = br#"{"op":"pause","avatar":"avatar"}"#;
    for scheme in ["Bearer", "bearer", "BEARER", "bEaReR"] {
        let auth = format!("{scheme} {CONTROL}");
        let (status, _, body) = http_with_headers(
            server.addr,
            "POST",
            "/api/commands",
            &[("Authorization", &auth)],
            pause,
        )
        .await;
        assert_eq!(status, 200, "{scheme}: {body}");
        let wrong = format!("{scheme} not-the-token");
        let (status, _, body) = http_with_headers(
            server.addr,
            "POST",
            "/api/commands",
            &[("Authorization", &wrong)],
            pause,
        )
        .await;
        assert_eq!(status, 401, "{scheme}: {body}");
    }
    let (status, _, _) = http_with_headers(
        server.addr,
        "POST",
        "/api/commands",
        &[("Authorization", &format!("Basic {CONTROL}"))],
        pause,
    )
    .await;
    assert_eq!(status, 401, "another scheme is refused");
    server.stop().await;
}

/// The sources of the `connect-src` directive of a policy.
fn connect_src(policy: &str) -> Vec<String> {
    policy
        .split(';')
        .map(str::trim)
        .find_map(|d| d.strip_prefix("connect-src "))
        .unwrap_or_else(|| panic!("no connect-src in {policy}"))
        .split_whitespace()
        .map(str::to_owned)
        .collect()
}

/// `/sdk/`: the JavaScript client and its declarations, with their types, readable from any
/// origin (module scripts are fetched with CORS), and revalidated by tag (304, no body).
#[tokio::test]
async fn the_javascript_client_is_served_to_any_origin_and_revalidated() {
    let server = server(60.0).await;
    for (path, content_type, starts) in [
        (
            "/sdk/posecast.js",
            "text/javascript; charset=utf-8",
            "// @ts-check",
        ),
        (
            "/sdk/frames.js",
            "text/javascript; charset=utf-8",
            "// @ts-check",
        ),
        (
            "/sdk/posecast.d.ts",
            "application/typescript; charset=utf-8",
            "// Type declarations",
        ),
        (
            "/sdk/protocol.d.ts",
            "application/typescript; charset=utf-8",
            "// The JSON messages",
        ),
    ] {
        let origin = [("Origin", "http://elsewhere.example")];
        let (status, head, body) = http_with_headers(server.addr, "GET", path, &origin, b"").await;
        assert_eq!(status, 200, "{path}");
        assert_eq!(
            header_value(&head, "content-type").as_deref(),
            Some(content_type)
        );
        assert_eq!(
            header_value(&head, "access-control-allow-origin").as_deref(),
            Some("*")
        );
        assert_eq!(
            header_value(&head, "cache-control").as_deref(),
            Some("no-cache")
        );
        assert!(body.starts_with(starts), "{path}");
        let tag = header_value(&head, "etag").unwrap();
        let (status, head, body) =
            http_with_headers(server.addr, "GET", path, &[("If-None-Match", &tag)], b"").await;
        assert_eq!(status, 304, "{path}");
        assert!(body.is_empty(), "{path}");
        assert_eq!(header_value(&head, "etag"), Some(tag));
    }
    let (status, _, body) =
        http_with_headers(server.addr, "GET", "/sdk/nothing.js", &[], b"").await;
    assert_eq!(status, 404);
    let body: Value = serde_json::from_str(&body).unwrap();
    assert_eq!(body["code"], "not_found", "{body}");
    server.stop().await;
}

#[tokio::test]
async fn the_dashboard_lets_websockets_reach_its_own_host_only() {
    let server = server(60.0).await;
    let host = server.addr.to_string();
    for path in ["/", "/dashboard/app.js", "/sdk/posecast.js"] {
        let (status, head, _) = http_with_headers(server.addr, "GET", path, &[], b"").await;
        assert_eq!(status, 200, "{path}");
        let policy = header_value(&head, "content-security-policy").unwrap();
        assert_eq!(
            connect_src(&policy),
            [
                "'self'".to_owned(),
                format!("ws://{host}"),
                format!("wss://{host}")
            ],
            "{path}: {policy}"
        );
    }
    // A Host that is not a plain host[:port] cannot widen or extend the policy.
    let (_, head, _) = http_with_headers(
        server.addr,
        "GET",
        "/",
        &[("Host", "evil.example; connect-src *")],
        b"",
    )
    .await;
    let policy = header_value(&head, "content-security-policy").unwrap();
    assert_eq!(connect_src(&policy), ["'self'"], "{policy}");
    assert_eq!(policy.matches("connect-src").count(), 1, "{policy}");
    server.stop().await;
}

/// Sends `request` as raw bytes and reads the answer until the server closes: (status, head,
/// body).
async fn raw(addr: std::net::SocketAddr, request: &[u8]) -> (u16, String, String) {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let mut stream = tokio::net::TcpStream::connect(addr).await.unwrap();
    // The server may answer and close before it has read all of an oversized head.
    stream.write_all(request).await.ok();
    let mut response = Vec::new();
    let read = tokio::time::timeout(
        std::time::Duration::from_secs(30),
        stream.read_to_end(&mut response),
    )
    .await;
    assert!(read.is_ok(), "no answer within 30 s");
    let text = String::from_utf8_lossy(&response).to_string();
    let (head, body) = text.split_once("\r\n\r\n").unwrap_or((&text, ""));
    let status = head
        .split(' ')
        .nth(1)
        .and_then(|s| s.parse().ok())
        .unwrap_or(0);
    (status, head.to_owned(), body.to_owned())
}

/// Issue 37: what hyper answers by itself, before any handler (a head it cannot parse, a URI
/// too long or too many headers for it), has the typed body too; and a HEAD that is not allowed says so in
/// the typed error's headers (a HEAD answer carries no content, RFC 9110 §9.3.2).
#[tokio::test]
async fn malformed_requests_and_a_refused_head_are_typed() {
    let server = server(60.0).await;
    let host = server.addr;
    let long_uri = format!(
        "GET /api/scenes?{} HTTP/1.1\r\nHost: {host}\r\n\r\n",
        "a".repeat(70_000)
    );
    // More headers than hyper parses (100).
    let many_headers = format!(
        "GET /api/scenes HTTP/1.1\r\nHost: {host}\r\n{}\r\n",
        (0..150)
            .map(|i| format!("X-H{i}: {i}\r\n"))
            .collect::<String>()
    );
    for (what, request, status, code) in [
        (
            "a malformed request line",
            format!("GET /a b c d\r\nHost: {host}\r\n\r\n"),
            400,
            "bad_message",
        ),
        (
            "a header without a colon",
            format!("GET /healthz HTTP/1.1\r\nHost: {host}\r\nno colon here\r\n\r\n"),
            400,
            "bad_message",
        ),
        ("a 70 KB URI", long_uri, 414, "too_large"),
        ("150 headers", many_headers, 431, "too_large"),
    ] {
        let (got, head, body) = raw(server.addr, request.as_bytes()).await;
        assert_eq!(got, status, "{what}: {head}");
        assert!(
            header_value(&head, "content-type").is_some_and(|v| v.starts_with("application/json")),
            "{what}: {head}"
        );
        assert_eq!(
            header_value(&head, "content-length"),
            Some(body.len().to_string()),
            "{what}: {head}"
        );
        assert_eq!(typed(what, &body).0, code, "{what}");
    }
    // HEAD on a POST-only route: 405 with the typed error's type and length, and no content.
    let (got, head, body) = raw(
        server.addr,
        format!("HEAD /api/commands HTTP/1.1\r\nHost: {host}\r\nConnection: close\r\n\r\n")
            .as_bytes(),
    )
    .await;
    assert_eq!(got, 405, "{head}");
    assert!(
        header_value(&head, "content-type").is_some_and(|v| v.starts_with("application/json")),
        "{head}"
    );
    assert!(header_value(&head, "allow").is_some(), "{head}");
    let length: usize = header_value(&head, "content-length")
        .and_then(|v| v.parse().ok())
        .unwrap_or(0);
    assert!(length > 0, "HEAD: no typed body announced: {head}");
    assert!(body.is_empty(), "HEAD: content sent: {body:?}");
    // A well-formed request on the same server is still served as before.
    let (got, _, _) = raw(
        server.addr,
        format!("GET /healthz HTTP/1.1\r\nHost: {host}\r\nConnection: close\r\n\r\n").as_bytes(),
    )
    .await;
    assert_eq!(got, 200);
    server.stop().await;
}
