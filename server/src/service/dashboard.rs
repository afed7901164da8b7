//! The web dashboard and the JavaScript client it is built on, static files embedded in the
//! binary: the page at `GET /` and `GET /dashboard/{file}`, the client (`server/sdk/`) at
//! `GET /sdk/{file}` — `posecast.js`, the ES module a third-party page imports, its modules and
//! its TypeScript declarations `posecast.d.ts` with the wire's generated `protocol.d.ts`. The page uses only the public protocol (the
//! websocket at `/ws` through the client, and the REST API).
//!
//! Every response carries a strict Content-Security-Policy ([`content_security_policy`]):
//! scripts, styles and images from this origin only, no inline code, network access to this
//! origin's HTTP and websocket only. The client's files are also readable from any origin
//! (`Access-Control-Allow-Origin: *`: module scripts are fetched with CORS), so a page served
//! elsewhere can import them. Every file has an `ETag` (its contents' FNV-1a 64) and
//! `Cache-Control: no-cache`: browsers keep it and revalidate (a 304 when unchanged), so a new
//! server binary never leaves a stale script in use.

use crate::app::AppState;
use axum::extract::{Path, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use std::sync::Arc;

/// The policy of a dashboard file served to a request whose `Host` header is `host`.
///
/// `connect-src` is this origin only. CSP Level 3 lets `'self'` match `ws:`/`wss:` URLs of the
/// page's own host and port (w3c/webappsec-csp#7), but Level 2 did not, and browsers that follow it would refuse the
/// dashboard's websocket; so the policy also names `ws://HOST` and `wss://HOST` (wss for a page
/// behind a TLS proxy) — that host only, never the bare `ws:`/`wss:` schemes, which would let an
/// injected script talk to any server. `HOST` is the request's `Host` if it is a plain
/// `name[:port]` (the CSP host-source grammar); anything else (an IPv6 literal, which that
/// grammar lacks, or text that could smuggle in other directives) gets `'self'` alone.
///
/// With a WebTransport endpoint (`quic_port`, `--quic-listen`) the policy also names
/// `https://NAME:PORT`, the request host's name at the endpoint's UDP port: the page's client
/// connects there first.
#[must_use]
pub fn content_security_policy(host: Option<&str>, quic_port: Option<u16>) -> String {
    let connect = match host.filter(|h| is_host_source(h)) {
        Some(h) => {
            let mut sources = format!("'self' ws://{h} wss://{h}");
            if let Some(port) = quic_port {
                let name = h.split_once(':').map_or(h, |(name, _)| name);
                sources.push_str(&format!(" https://{name}:{port}"));
            }
            sources
        }
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
/// `protocol.js`, JSDoc types only, nor the type check's `tsconfig.json` and `check/`); its
/// connection, frame decoding and forward kinematics come from the client in [`SDK`].
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
    ("tokens.js", JS, include_str!("../../web/tokens.js")),
    ("store.js", JS, include_str!("../../web/store.js")),
    ("sync.js", JS, include_str!("../../web/sync.js")),
    ("ui.js", JS, include_str!("../../web/ui.js")),
    ("rest.js", JS, include_str!("../../web/rest.js")),
    ("viewer.js", JS, include_str!("../../web/viewer.js")),
    ("draw.js", JS, include_str!("../../web/draw.js")),
    ("draw-gl.js", JS, include_str!("../../web/draw-gl.js")),
    ("glb.js", JS, include_str!("../../web/glb.js")),
    ("drive.js", JS, include_str!("../../web/drive.js")),
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
    ("panel-face.js", JS, include_str!("../../web/panel-face.js")),
    (
        "panel-upload.js",
        JS,
        include_str!("../../web/panel-upload.js"),
    ),
    (
        "panel-takes.js",
        JS,
        include_str!("../../web/panel-takes.js"),
    ),
];

/// `(name, content type, contents)` of the JavaScript client's files in `server/sdk/`: the
/// module `posecast.js` (a page imports only it), the modules it imports, and its declarations
/// (`posecast.d.ts`, which imports the wire's generated types from `protocol.d.ts`).
const SDK: &[(&str, &str, &str)] = &[
    ("posecast.js", JS, include_str!("../../sdk/posecast.js")),
    ("client.js", JS, include_str!("../../sdk/client.js")),
    ("errors.js", JS, include_str!("../../sdk/errors.js")),
    ("tokens.js", JS, include_str!("../../sdk/tokens.js")),
    ("frames.js", JS, include_str!("../../sdk/frames.js")),
    ("frames2.js", JS, include_str!("../../sdk/frames2.js")),
    ("jitter.js", JS, include_str!("../../sdk/jitter.js")),
    ("clock.js", JS, include_str!("../../sdk/clock.js")),
    ("fk.js", JS, include_str!("../../sdk/fk.js")),
    ("math.js", JS, include_str!("../../sdk/math.js")),
    ("subset.js", JS, include_str!("../../sdk/subset.js")),
    (
        "webtransport.js",
        JS,
        include_str!("../../sdk/webtransport.js"),
    ),
    ("three.js", JS, include_str!("../../sdk/three.js")),
    (
        "three.d.ts",
        "application/typescript; charset=utf-8",
        include_str!("../../sdk/three.d.ts"),
    ),
    (
        "package.json",
        "application/json; charset=utf-8",
        include_str!("../../sdk/package.json"),
    ),
    (
        "posecast.d.ts",
        "application/typescript; charset=utf-8",
        include_str!("../../sdk/posecast.d.ts"),
    ),
    (
        "protocol.d.ts",
        "application/typescript; charset=utf-8",
        include_str!("../../sdk/protocol.d.ts"),
    ),
];

const JS: &str = "text/javascript; charset=utf-8";

/// The entity tag of a file: FNV-1a 64 of its contents, quoted.
fn etag(body: &str) -> String {
    let hash = body.bytes().fold(0xcbf2_9ce4_8422_2325_u64, |h, b| {
        (h ^ u64::from(b)).wrapping_mul(0x0000_0100_0000_01b3)
    });
    format!("\"{hash:016x}\"")
}

/// Whether an `If-None-Match` header names `tag` (or is `*`).
fn matches_tag(request: &HeaderMap, tag: &str) -> bool {
    request
        .get_all(header::IF_NONE_MATCH)
        .iter()
        .filter_map(|v| v.to_str().ok())
        .flat_map(|v| v.split(','))
        .map(|t| t.trim().trim_start_matches("W/"))
        .any(|t| t == tag || t == "*")
}

fn serve(
    files: &[(&str, &'static str, &'static str)],
    name: &str,
    request: &HeaderMap,
    quic_port: Option<u16>,
) -> Response {
    let Some(&(_, content_type, body)) = files.iter().find(|(n, _, _)| *n == name) else {
        return (StatusCode::NOT_FOUND, format!("no file {name}")).into_response();
    };
    let host = request.get(header::HOST).and_then(|h| h.to_str().ok());
    let tag = etag(body);
    let mut response = if matches_tag(request, &tag) {
        StatusCode::NOT_MODIFIED.into_response()
    } else {
        body.into_response()
    };
    let headers = response.headers_mut();
    if let Ok(tag) = HeaderValue::from_str(&tag) {
        headers.insert(header::ETAG, tag);
    }
    headers.insert(header::CONTENT_TYPE, HeaderValue::from_static(content_type));
    let policy = content_security_policy(host, quic_port);
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

/// The WebTransport endpoint's UDP port, if the server has one.
fn quic_port(state: &AppState) -> Option<u16> {
    state.quic.get().map(|q| q.port)
}

/// `GET /`: the dashboard page.
pub async fn index(State(state): State<Arc<AppState>>, headers: HeaderMap) -> Response {
    serve(FILES, "index.html", &headers, quic_port(&state))
}

/// `GET /dashboard/{file}`: the page's scripts and styles.
pub async fn file(
    State(state): State<Arc<AppState>>,
    Path(name): Path<String>,
    headers: HeaderMap,
) -> Response {
    serve(FILES, &name, &headers, quic_port(&state))
}

/// `GET /sdk/{file}`: the JavaScript client, readable from any origin.
pub async fn sdk(
    State(state): State<Arc<AppState>>,
    Path(name): Path<String>,
    headers: HeaderMap,
) -> Response {
    let mut response = serve(SDK, &name, &headers, quic_port(&state));
    response.headers_mut().insert(
        header::ACCESS_CONTROL_ALLOW_ORIGIN,
        HeaderValue::from_static("*"),
    );
    response
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
        for files in [FILES, SDK] {
            for (name, content_type, _) in files {
                let r = serve(files, name, &host("example.org:8080"), None);
                assert_eq!(r.status(), StatusCode::OK);
                assert_eq!(r.headers()[header::CONTENT_TYPE], *content_type);
                assert!(r.headers().contains_key(header::CONTENT_SECURITY_POLICY));
                assert_eq!(r.headers()[header::CACHE_CONTROL], "no-cache");
            }
        }
        assert_eq!(
            serve(FILES, "../Cargo.toml", &HeaderMap::new(), None).status(),
            StatusCode::NOT_FOUND
        );
        assert_eq!(
            serve(SDK, "index.html", &HeaderMap::new(), None).status(),
            StatusCode::NOT_FOUND
        );
    }

    /// Every module and declaration file of the two folders is embedded: a file added to the
    /// folder but not to the list would leave every page importing it broken.
    #[test]
    fn every_file_of_the_folders_is_embedded() {
        let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
        for (folder, files) in [("web", FILES), ("sdk", SDK)] {
            let on_disk: Vec<String> = std::fs::read_dir(root.join(folder))
                .unwrap()
                .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
                .filter(|n| {
                    [".js", ".ts", ".html", ".css"]
                        .iter()
                        .any(|ext| n.ends_with(ext))
                })
                // JSDoc types only, for the type check: never imported at run time.
                .filter(|n| !(folder == "web" && n == "protocol.js"))
                .collect();
            for name in &on_disk {
                assert!(
                    files.iter().any(|(f, _, _)| f == name),
                    "{folder}/{name} is not embedded in {}",
                    file!()
                );
            }
        }
    }

    /// A request naming the file's tag gets 304 without the body; another tag, the file.
    #[test]
    fn files_are_revalidated_by_their_tag() {
        let r = serve(SDK, "posecast.js", &HeaderMap::new(), None);
        let tag = r.headers()[header::ETAG].to_str().unwrap().to_owned();
        assert_eq!(tag.len(), 18, "{tag}");
        // A different file has a different tag.
        let other = serve(SDK, "frames.js", &HeaderMap::new(), None);
        assert_ne!(other.headers()[header::ETAG], tag.as_str());
        for (sent, status) in [
            (tag.clone(), StatusCode::NOT_MODIFIED),
            (format!("W/{tag}"), StatusCode::NOT_MODIFIED),
            (
                format!("\"0000000000000000\", {tag}"),
                StatusCode::NOT_MODIFIED,
            ),
            ("\"0000000000000000\"".to_owned(), StatusCode::OK),
        ] {
            let mut headers = HeaderMap::new();
            headers.insert(header::IF_NONE_MATCH, HeaderValue::from_str(&sent).unwrap());
            assert_eq!(
                serve(SDK, "posecast.js", &headers, None).status(),
                status,
                "{sent}"
            );
        }
    }

    /// The `.js` files of `dir` (but `except`), and those of `files`: the same names.
    fn served_as_on_disk(dir: &str, files: &[(&str, &str, &str)], except: &[&str]) {
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join(dir);
        let mut on_disk: Vec<String> = std::fs::read_dir(&dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .filter(|n| n.ends_with(".js") && !except.contains(&n.as_str()))
            .collect();
        on_disk.sort();
        let mut served: Vec<String> = files
            .iter()
            .map(|(n, _, _)| (*n).to_owned())
            .filter(|n| n.ends_with(".js"))
            .collect();
        served.sort();
        assert_eq!(on_disk, served);
    }

    /// Every module the page imports is served: each `.js` beside `index.html` (but the
    /// type-only `protocol.js`) is in [`FILES`], and each file in [`FILES`] is there; the
    /// same for the client's modules and [`SDK`].
    #[test]
    fn every_module_of_the_page_and_the_client_is_served() {
        served_as_on_disk("web", FILES, &["protocol.js"]);
        served_as_on_disk("sdk", SDK, &[]);
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
                connect_src(&content_security_policy(Some(h), None)),
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
            let policy = content_security_policy(Some(h), Some(4433));
            assert_eq!(connect_src(&policy), ["'self'"], "{h:?}");
            assert_eq!(policy.matches("script-src").count(), 1, "{h:?}");
        }
        assert_eq!(
            connect_src(&content_security_policy(None, None)),
            ["'self'"]
        );
        // With a WebTransport endpoint: the host's name at its UDP port, https only.
        assert_eq!(
            connect_src(&content_security_policy(Some("127.0.0.1:8080"), Some(4433))),
            [
                "'self'",
                "ws://127.0.0.1:8080",
                "wss://127.0.0.1:8080",
                "https://127.0.0.1:4433"
            ]
        );
        assert_eq!(
            connect_src(&content_security_policy(Some("example.org"), Some(443))),
            [
                "'self'",
                "ws://example.org",
                "wss://example.org",
                "https://example.org:443"
            ]
        );
    }
}
