//! A minimal HTTP/1.1 client over `tokio::net::TcpStream`, enough to fetch an avatar's mesh from
//! the server that streams it and to upload a file to it (plain `http`, `Content-Length` or
//! chunked bodies, one request per connection). A full HTTP client would pull in TLS and a
//! connection pool for a handful of requests.

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
    /// The URL does not parse, has an unknown scheme or no host, or a path does not join it.
    #[error("bad URL {url:?}: {message}")]
    Url {
        /// The URL (or path) as given.
        url: String,
        /// What is wrong with it.
        message: String,
    },
    /// The URL is not plain `http` (this client has no TLS).
    #[error("{url}: only plain http is supported, not {scheme}")]
    Scheme {
        /// The URL requested.
        url: String,
        /// Its scheme (e.g. `https`).
        scheme: String,
    },
    /// Connecting, writing the request or reading the response failed.
    #[error("{url}: {source}")]
    Io {
        /// The URL requested.
        url: String,
        /// What the socket reported.
        #[source]
        source: std::io::Error,
    },
    /// [`get`] got a status other than 200.
    #[error("{url}: HTTP status {status}")]
    Status {
        /// The URL requested.
        url: String,
        /// The response's status code.
        status: u16,
    },
    /// A request header's name or value contains CR or LF, which would smuggle in another
    /// header.
    #[error("{url}: header {name} holds a line break")]
    Header {
        /// The URL requested.
        url: String,
        /// The header's name.
        name: String,
    },
    /// The response is not valid HTTP/1.1 (status line, headers or chunked body).
    #[error("{url}: malformed response: {message}")]
    Response {
        /// The URL requested.
        url: String,
        /// What is wrong with it.
        message: String,
    },
    /// The response passed [`MAX_RESPONSE_BYTES`] (and 64 KiB more for its headers).
    #[error("{url}: response larger than {limit} bytes")]
    TooLarge {
        /// The URL requested.
        url: String,
        /// The limit, bytes ([`MAX_RESPONSE_BYTES`]).
        limit: usize,
    },
    /// The request did not complete within [`TIMEOUT`].
    #[error("{url}: no response within {seconds} s")]
    Timeout {
        /// The URL requested.
        url: String,
        /// The timeout, seconds.
        seconds: u64,
    },
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

/// An HTTP response: its status and (de-chunked) body.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Response {
    /// The HTTP status code.
    pub status: u16,
    /// The body, whatever the status (the server's errors are `{"code","message"}`).
    pub body: Vec<u8>,
}

/// GETs `url` and returns the body of a 200 response.
pub async fn get(url: &Url) -> Result<Vec<u8>, FetchError> {
    let response = request("GET", url, &[("Accept", "model/gltf-binary, */*")], &[]).await?;
    if response.status != 200 {
        return Err(FetchError::Status {
            url: url.to_string(),
            status: response.status,
        });
    }
    Ok(response.body)
}

/// Sends one request (`method`, extra `headers`, `body` with its `Content-Length`) and returns
/// the response whatever its status, so callers can read a server's typed error body.
pub async fn request(
    method: &str,
    url: &Url,
    headers: &[(&str, &str)],
    body: &[u8],
) -> Result<Response, FetchError> {
    let name = url.to_string();
    match tokio::time::timeout(TIMEOUT, request_inner(method, url, headers, body, &name)).await {
        Ok(result) => result,
        Err(_) => Err(FetchError::Timeout {
            url: name,
            seconds: TIMEOUT.as_secs(),
        }),
    }
}

async fn request_inner(
    method: &str,
    url: &Url,
    headers: &[(&str, &str)],
    body: &[u8],
    name: &str,
) -> Result<Response, FetchError> {
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
    let mut target = url.path().to_owned();
    if let Some(q) = url.query() {
        target.push('?');
        target.push_str(q);
    }
    let mut head = format!(
        "{method} {target} HTTP/1.1\r\nHost: {host}:{port}\r\nUser-Agent: posecast-client\r\n\
         Connection: close\r\n"
    );
    for (key, value) in headers {
        // A line break would end the header early and smuggle in another.
        if [key, value].iter().any(|s| s.contains(['\r', '\n'])) {
            return Err(FetchError::Header {
                url: name.to_owned(),
                name: (*key).to_owned(),
            });
        }
        head.push_str(&format!("{key}: {value}\r\n"));
    }
    if !body.is_empty() || !matches!(method, "GET" | "HEAD") {
        head.push_str(&format!("Content-Length: {}\r\n", body.len()));
    }
    head.push_str("\r\n");
    let io = |source| FetchError::Io {
        url: name.to_owned(),
        source,
    };
    let mut stream = tokio::net::TcpStream::connect((host, port))
        .await
        .map_err(io)?;
    // A server may answer before reading the whole body (413) and close: the answer read below
    // is worth more than the write's broken pipe, which is only reported without one.
    let written = match stream.write_all(head.as_bytes()).await {
        Ok(()) => stream.write_all(body).await,
        Err(e) => Err(e),
    };
    let mut raw = Vec::new();
    // One byte past the limit tells "exactly at the limit" from "over it".
    let cap = (MAX_RESPONSE_BYTES + 64 * 1024 + 1) as u64;
    let read = (&mut stream).take(cap).read_to_end(&mut raw).await;
    if raw.len() as u64 >= cap {
        return Err(FetchError::TooLarge {
            url: name.to_owned(),
            limit: MAX_RESPONSE_BYTES,
        });
    }
    match parse_response(&raw) {
        Ok((status, body)) => Ok(Response { status, body }),
        Err(message) => {
            written.map_err(io)?;
            read.map_err(io)?;
            Err(FetchError::Response {
                url: name.to_owned(),
                message,
            })
        }
    }
}

/// The status and body of a complete `Connection: close` response.
fn parse_response(raw: &[u8]) -> Result<(u16, Vec<u8>), String> {
    let malformed = |m: &str| m.to_owned();
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
    let body = if chunked {
        dechunk(body).ok_or_else(|| malformed("bad chunked body"))?
    } else {
        match length {
            Some(n) => body
                .get(..n)
                .map(<[u8]>::to_vec)
                .ok_or_else(|| malformed("body shorter than Content-Length"))?,
            None => body.to_vec(),
        }
    };
    Ok((status, body))
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
        assert_eq!(parse_response(ok).unwrap(), (200, b"hello".to_vec()));
        let chunked =
            b"HTTP/1.1 200 OK\r\nTransfer-Encoding: chunked\r\n\r\n3\r\nhel\r\n2\r\nlo\r\n0\r\n\r\n";
        assert_eq!(parse_response(chunked).unwrap(), (200, b"hello".to_vec()));
        let conflict = b"HTTP/1.1 409 Conflict\r\ncontent-length: 4\r\n\r\n{..}";
        assert_eq!(parse_response(conflict).unwrap(), (409, b"{..}".to_vec()));
        let short = b"HTTP/1.1 200 OK\r\ncontent-length: 9\r\n\r\nhello";
        assert!(parse_response(short).is_err());
        let bad_chunk = b"HTTP/1.1 200 OK\r\nTransfer-Encoding: chunked\r\n\r\nzz\r\n";
        assert!(parse_response(bad_chunk).is_err());
        assert!(parse_response(b"garbage").is_err());
    }

    #[tokio::test]
    async fn a_header_with_a_line_break_is_refused_before_connecting() {
        // Port 9 (discard) is never contacted: the check comes first.
        let url = Url::parse("http://127.0.0.1:9/api/assets/x").unwrap();
        let smuggled = [("Authorization", "Bearer t\r\nX-Evil: 1")];
        let err = request("POST", &url, &smuggled, b"body").await.unwrap_err();
        assert!(matches!(err, FetchError::Header { .. }), "{err}");
    }
}
