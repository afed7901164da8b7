//! A minimal HTTP/1.1 GET over `tokio::net::TcpStream`, enough to fetch an avatar's mesh from
//! the server that streams it (plain `http`, `Content-Length` or chunked bodies). A full HTTP
//! client would pull in TLS and a connection pool for one request per avatar.

use std::time::Duration;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use url::Url;

/// Largest response accepted: the built-in avatar's mesh is ~200 kB; a 100k-vertex mesh with
/// four influences is ~7 MB.
pub const MAX_RESPONSE_BYTES: usize = 64 << 20;

/// How long one request may take in total.
pub const TIMEOUT: Duration = Duration::from_secs(10);

/// Why a fetch failed.
#[derive(Debug, thiserror::Error)]
pub enum FetchError {
    #[error("bad URL {url:?}: {message}")]
    Url { url: String, message: String },
    #[error("{url}: only plain http is supported, not {scheme}")]
    Scheme { url: String, scheme: String },
    #[error("{url}: {source}")]
    Io {
        url: String,
        #[source]
        source: std::io::Error,
    },
    #[error("{url}: HTTP status {status}")]
    Status { url: String, status: u16 },
    #[error("{url}: malformed response: {message}")]
    Response { url: String, message: String },
    #[error("{url}: response larger than {limit} bytes")]
    TooLarge { url: String, limit: usize },
    #[error("{url}: no response within {seconds} s")]
    Timeout { url: String, seconds: u64 },
}

/// The HTTP URL of `path` (absolute or relative, e.g. `/api/assets/avatar/mesh.glb`) on the
/// server whose websocket is `ws_url`: `ws` becomes `http`, `wss` becomes `https`.
pub fn resolve(ws_url: &str, path: &str) -> Result<Url, FetchError> {
    let bad = |message: String| FetchError::Url {
        url: ws_url.to_owned(),
        message,
    };
    let mut base = Url::parse(ws_url).map_err(|e| bad(e.to_string()))?;
    let scheme = match base.scheme() {
        "ws" | "http" => "http",
        "wss" | "https" => "https",
        other => return Err(bad(format!("unknown scheme {other}"))),
    };
    base.set_scheme(scheme)
        .map_err(|()| bad(format!("cannot use scheme {scheme}")))?;
    base.join(path).map_err(|e| FetchError::Url {
        url: path.to_owned(),
        message: e.to_string(),
    })
}

/// GETs `url` and returns the body of a 200 response.
pub async fn get(url: &Url) -> Result<Vec<u8>, FetchError> {
    let name = url.to_string();
    match tokio::time::timeout(TIMEOUT, get_inner(url, &name)).await {
        Ok(result) => result,
        Err(_) => Err(FetchError::Timeout {
            url: name,
            seconds: TIMEOUT.as_secs(),
        }),
    }
}

async fn get_inner(url: &Url, name: &str) -> Result<Vec<u8>, FetchError> {
    if url.scheme() != "http" {
        return Err(FetchError::Scheme {
            url: name.to_owned(),
            scheme: url.scheme().to_owned(),
        });
    }
    let host = url.host_str().ok_or_else(|| FetchError::Url {
        url: name.to_owned(),
        message: "no host".into(),
    })?;
    let port = url.port_or_known_default().unwrap_or(80);
    let io = |source| FetchError::Io {
        url: name.to_owned(),
        source,
    };
    let mut stream = tokio::net::TcpStream::connect((host, port))
        .await
        .map_err(io)?;
    let mut target = url.path().to_owned();
    if let Some(q) = url.query() {
        target.push('?');
        target.push_str(q);
    }
    let request = format!(
        "GET {target} HTTP/1.1\r\nHost: {host}:{port}\r\nUser-Agent: posecast-client\r\n\
         Accept: model/gltf-binary, */*\r\nConnection: close\r\n\r\n"
    );
    stream.write_all(request.as_bytes()).await.map_err(io)?;
    let mut raw = Vec::new();
    // One byte past the limit tells "exactly at the limit" from "over it".
    let cap = (MAX_RESPONSE_BYTES + 64 * 1024 + 1) as u64;
    (&mut stream)
        .take(cap)
        .read_to_end(&mut raw)
        .await
        .map_err(io)?;
    if raw.len() as u64 >= cap {
        return Err(FetchError::TooLarge {
            url: name.to_owned(),
            limit: MAX_RESPONSE_BYTES,
        });
    }
    parse_response(&raw).map_err(|e| match e {
        Parsed::Status(status) => FetchError::Status {
            url: name.to_owned(),
            status,
        },
        Parsed::Malformed(message) => FetchError::Response {
            url: name.to_owned(),
            message,
        },
    })
}

#[derive(Debug, PartialEq)]
enum Parsed {
    Status(u16),
    Malformed(String),
}

/// The body of a complete `Connection: close` response with status 200.
fn parse_response(raw: &[u8]) -> Result<Vec<u8>, Parsed> {
    let malformed = |m: &str| Parsed::Malformed(m.to_owned());
    let end = raw
        .windows(4)
        .position(|w| w == b"\r\n\r\n")
        .ok_or_else(|| malformed("no end of headers"))?;
    let head = std::str::from_utf8(&raw[..end]).map_err(|_| malformed("headers not UTF-8"))?;
    let body = &raw[end + 4..];
    let mut lines = head.split("\r\n");
    let status_line = lines.next().unwrap_or_default();
    let status: u16 = status_line
        .split(' ')
        .nth(1)
        .and_then(|s| s.parse().ok())
        .ok_or_else(|| malformed("no status code"))?;
    if status != 200 {
        return Err(Parsed::Status(status));
    }
    let mut length = None;
    let mut chunked = false;
    for line in lines {
        let Some((key, value)) = line.split_once(':') else {
            continue;
        };
        let value = value.trim();
        if key.eq_ignore_ascii_case("content-length") {
            length = Some(
                value
                    .parse::<usize>()
                    .map_err(|_| malformed("bad Content-Length"))?,
            );
        } else if key.eq_ignore_ascii_case("transfer-encoding") {
            chunked = value.to_ascii_lowercase().contains("chunked");
        }
    }
    if chunked {
        return dechunk(body).ok_or_else(|| malformed("bad chunked body"));
    }
    match length {
        Some(n) => body
            .get(..n)
            .map(<[u8]>::to_vec)
            .ok_or_else(|| malformed("body shorter than Content-Length")),
        None => Ok(body.to_vec()),
    }
}

fn dechunk(mut body: &[u8]) -> Option<Vec<u8>> {
    let mut out = Vec::new();
    loop {
        let line_end = body.windows(2).position(|w| w == b"\r\n")?;
        let size_text = std::str::from_utf8(&body[..line_end]).ok()?;
        let size_text = size_text.split(';').next()?.trim();
        let size = usize::from_str_radix(size_text, 16).ok()?;
        body = &body[line_end + 2..];
        if size == 0 {
            return Some(out);
        }
        out.extend_from_slice(body.get(..size)?);
        body = body.get(size + 2..)?;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mesh_urls_resolve_against_the_websocket() {
        let url = resolve("ws://127.0.0.1:8080/ws", "/api/assets/avatar/mesh.glb").unwrap();
        assert_eq!(
            url.as_str(),
            "http://127.0.0.1:8080/api/assets/avatar/mesh.glb"
        );
        let url = resolve("wss://example.org/ws", "http://other:1/m.glb").unwrap();
        assert_eq!(url.as_str(), "http://other:1/m.glb");
        assert!(resolve("not a url", "/x").is_err());
    }

    #[test]
    fn responses_parse() {
        let ok = b"HTTP/1.1 200 OK\r\ncontent-length: 5\r\n\r\nhello";
        assert_eq!(parse_response(ok).unwrap(), b"hello");
        let chunked =
            b"HTTP/1.1 200 OK\r\nTransfer-Encoding: chunked\r\n\r\n3\r\nhel\r\n2\r\nlo\r\n0\r\n\r\n";
        assert_eq!(parse_response(chunked).unwrap(), b"hello");
        let missing = b"HTTP/1.1 404 Not Found\r\ncontent-length: 0\r\n\r\n";
        assert_eq!(parse_response(missing), Err(Parsed::Status(404)));
        let short = b"HTTP/1.1 200 OK\r\ncontent-length: 9\r\n\r\nhello";
        assert!(matches!(parse_response(short), Err(Parsed::Malformed(_))));
        let bad_chunk = b"HTTP/1.1 200 OK\r\nTransfer-Encoding: chunked\r\n\r\nzz\r\n";
        assert!(matches!(
            parse_response(bad_chunk),
            Err(Parsed::Malformed(_))
        ));
        assert!(parse_response(b"garbage").is_err());
    }
}
