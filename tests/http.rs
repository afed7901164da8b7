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
