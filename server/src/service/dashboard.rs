//! The web dashboard: static files embedded in the binary, served at `GET /` and
//! `GET /dashboard/{file}`. The page uses only the public protocol (the websocket at `/ws` with
//! JSON frames, and the REST API), so it is also an example of a third-party client.
//!
//! Every response carries a strict Content-Security-Policy ([`content_security_policy`]):
//! scripts, styles and images from this origin only, no inline code, network access to this
//! origin's HTTP and websocket only.

use axum::extract::Path;
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};

/// The policy of a dashboard file served to a request whose `Host` header is `host`.
///
/// `connect-src` is this origin only. CSP Level 3 lets `'self'` match `ws:`/`wss:` URLs of the
/// page's own host and port (w3c/webappsec-csp#7), but Level 2 did not, and browsers that follow it would refuse the
/// dashboard's websocket; so the policy also names `ws://HOST` and `wss://HOST` (wss for a page
/// behind a TLS proxy) — that host only, never the bare `ws:`/`wss:` schemes, which would let an
/// injected script talk to any server. `HOST` is the request's `Host` if it is a plain
/// `name[:port]` (the CSP host-source grammar); anything else (an IPv6 literal, which that
/// grammar lacks, or text that could smuggle in other directives) gets `'self'` alone.
#[must_use]
pub fn content_security_policy(host: Option<&str>) -> String {
    let connect = match host.filter(|h| is_host_source(h)) {
        Some(h) => format!("'self' ws://{h} wss://{h}"),
        None => "'self'".to_owned(),
    };
    format!(
        "default-src 'self'; script-src 'self'; style-src 'self'; img-src 'self' data: blob:; \
         connect-src {connect}; object-src 'none'; base-uri 'none'; form-action 'self'; \
         frame-ancestors 'none'"
    )
}

/// Whether `host` is `label(.label)*[:port]` with labels of letters, digits and `-`.
fn is_host_source(host: &str) -> bool {
    let (name, port) = match host.split_once(':') {
        Some((name, port)) => (name, Some(port)),
        None => (host, None),
    };
    let name_ok = !name.is_empty()
        && name.split('.').all(|label| {
            !label.is_empty() && label.chars().all(|c| c.is_ascii_alphanumeric() || c == '-')
        });
    let port_ok =
        port.is_none_or(|p| !p.is_empty() && p.len() <= 5 && p.chars().all(|c| c.is_ascii_digit()));
    host.len() <= 255 && name_ok && port_ok
}

/// `(name, content type, contents)` of every file the page loads from `server/web/` (not
/// `protocol.js`, JSDoc types only, nor the type check's `tsconfig.json` and `check/`).
const FILES: &[(&str, &str, &str)] = &[
    (
        "index.html",
        "text/html; charset=utf-8",
        include_str!("../../web/index.html"),
    ),
    (
        "style.css",
        "text/css; charset=utf-8",
        include_str!("../../web/style.css"),
    ),
    ("app.js", JS, include_str!("../../web/app.js")),
    ("connection.js", JS, include_str!("../../web/connection.js")),
    ("tokens.js", JS, include_str!("../../web/tokens.js")),
    ("store.js", JS, include_str!("../../web/store.js")),
    ("sync.js", JS, include_str!("../../web/sync.js")),
    ("ui.js", JS, include_str!("../../web/ui.js")),
    ("rest.js", JS, include_str!("../../web/rest.js")),
    ("viewer.js", JS, include_str!("../../web/viewer.js")),
    ("draw.js", JS, include_str!("../../web/draw.js")),
    ("draw-gl.js", JS, include_str!("../../web/draw-gl.js")),
    ("fk.js", JS, include_str!("../../web/fk.js")),
    ("glb.js", JS, include_str!("../../web/glb.js")),
    ("math.js", JS, include_str!("../../web/math.js")),
    (
        "panel-status.js",
        JS,
        include_str!("../../web/panel-status.js"),
    ),
    (
        "panel-access.js",
        JS,
        include_str!("../../web/panel-access.js"),
    ),
    (
        "panel-scenes.js",
        JS,
        include_str!("../../web/panel-scenes.js"),
    ),
    (
        "panel-playback.js",
        JS,
        include_str!("../../web/panel-playback.js"),
    ),
    (
        "panel-timeline.js",
        JS,
        include_str!("../../web/panel-timeline.js"),
    ),
    (
        "panel-place.js",
        JS,
        include_str!("../../web/panel-place.js"),
    ),
    (
        "panel-joints.js",
        JS,
        include_str!("../../web/panel-joints.js"),
    ),
    (
        "panel-upload.js",
        JS,
        include_str!("../../web/panel-upload.js"),
    ),
];

const JS: &str = "text/javascript; charset=utf-8";

fn serve(name: &str, request: &HeaderMap) -> Response {
    let Some(&(_, content_type, body)) = FILES.iter().find(|(n, _, _)| *n == name) else {
        return (StatusCode::NOT_FOUND, "no such dashboard file").into_response();
    };
    let host = request.get(header::HOST).and_then(|h| h.to_str().ok());
    let mut response = body.into_response();
    let headers = response.headers_mut();
    headers.insert(header::CONTENT_TYPE, HeaderValue::from_static(content_type));
    let policy = content_security_policy(host);
    headers.insert(
        header::CONTENT_SECURITY_POLICY,
        HeaderValue::from_str(&policy).unwrap_or(HeaderValue::from_static("default-src 'self'")),
    );
    headers.insert(
        header::X_CONTENT_TYPE_OPTIONS,
        HeaderValue::from_static("nosniff"),
    );
    headers.insert(
        header::REFERRER_POLICY,
        HeaderValue::from_static("no-referrer"),
    );
    // Files change with the binary; revalidating is cheap and avoids stale scripts.
    headers.insert(header::CACHE_CONTROL, HeaderValue::from_static("no-cache"));
    response
}

/// `GET /`: the dashboard page.
pub async fn index(headers: HeaderMap) -> Response {
    serve("index.html", &headers)
}

/// `GET /dashboard/{file}`: the page's scripts and styles.
pub async fn file(Path(name): Path<String>, headers: HeaderMap) -> Response {
    serve(&name, &headers)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn host(h: &str) -> HeaderMap {
        let mut headers = HeaderMap::new();
        headers.insert(header::HOST, HeaderValue::from_str(h).unwrap());
        headers
    }

    #[test]
    fn every_file_is_served_with_its_type_and_the_policy() {
        for (name, content_type, _) in FILES {
            let r = serve(name, &host("example.org:8080"));
            assert_eq!(r.status(), StatusCode::OK);
            assert_eq!(r.headers()[header::CONTENT_TYPE], *content_type);
            assert!(r.headers().contains_key(header::CONTENT_SECURITY_POLICY));
        }
        assert_eq!(
            serve("../Cargo.toml", &HeaderMap::new()).status(),
            StatusCode::NOT_FOUND
        );
    }

    /// Every module the page imports is served: each `.js` beside `index.html` (but the
    /// type-only `protocol.js`) is in [`FILES`], and each file in [`FILES`] is there.
    #[test]
    fn every_module_of_the_page_is_served() {
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("web");
        let mut on_disk: Vec<String> = std::fs::read_dir(&dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .filter(|n| n.ends_with(".js") && n != "protocol.js")
            .collect();
        on_disk.sort();
        let mut served: Vec<String> = FILES
            .iter()
            .map(|(n, _, _)| (*n).to_owned())
            .filter(|n| n.ends_with(".js"))
            .collect();
        served.sort();
        assert_eq!(on_disk, served);
    }

    /// The `connect-src` directive of a policy, split into its sources.
    fn connect_src(policy: &str) -> Vec<String> {
        policy
            .split(';')
            .map(str::trim)
            .find_map(|d| d.strip_prefix("connect-src "))
            .unwrap()
            .split_whitespace()
            .map(str::to_owned)
            .collect()
    }

    #[test]
    fn connect_src_names_only_the_requests_own_host() {
        for h in ["127.0.0.1:8080", "localhost", "pose-cast.example.org:443"] {
            assert_eq!(
                connect_src(&content_security_policy(Some(h))),
                [
                    "'self'".to_owned(),
                    format!("ws://{h}"),
                    format!("wss://{h}")
                ],
            );
        }
        // Nothing that is not a plain host: 'self' alone, and no directive smuggled in.
        for h in [
            "evil.example; script-src *",
            "a b",
            "[::1]:8080",
            "host:",
            "host:80:80",
            "a..b",
            "*",
            "",
        ] {
            let policy = content_security_policy(Some(h));
            assert_eq!(connect_src(&policy), ["'self'"], "{h:?}");
            assert_eq!(policy.matches("script-src").count(), 1, "{h:?}");
        }
        assert_eq!(connect_src(&content_security_policy(None)), ["'self'"]);
    }
}
