//! The tests' HTTP client: hyper's (`hyper_util`'s client over HTTP/1.1), one connection per
//! request. Raw bytes are written by hand only where a test is about malformed requests
//! (`tests/http.rs`, `raw`).

use axum::body::Body;
use axum::http::{HeaderMap, Method, Request};
use hyper_util::client::legacy::Client;
use hyper_util::rt::TokioExecutor;
use std::net::SocketAddr;

/// A response: status, headers and the whole body.
#[derive(Debug)]
pub struct Response {
    /// The status code.
    pub status: u16,
    /// The headers.
    pub headers: HeaderMap,
    /// The body, de-chunked.
    pub body: Vec<u8>,
}

impl Response {
    /// The status line and headers as text (`HTTP/1.1 200`, then `name: value` lines), for
    /// tests that look for a header by name ([`super::header_value`]).
    #[must_use]
    pub fn head(&self) -> String {
        let mut head = format!("HTTP/1.1 {}", self.status);
        for (name, value) in &self.headers {
            head.push_str(&format!(
                "\r\n{name}: {}",
                String::from_utf8_lossy(value.as_bytes())
            ));
        }
        head
    }

    /// The body as text (lossy UTF-8).
    #[must_use]
    pub fn text(&self) -> String {
        String::from_utf8_lossy(&self.body).into_owned()
    }
}

/// `method path` to `addr` with these headers and body (`Host` is `addr` unless given).
///
/// # Errors
/// The connection refused, reset or closed before a whole response came (a killed server).
pub async fn request(
    addr: SocketAddr,
    method: &str,
    path: &str,
    headers: &[(&str, &str)],
    body: Vec<u8>,
) -> Result<Response, String> {
    let client = Client::builder(TokioExecutor::new())
        .pool_max_idle_per_host(0)
        .build_http::<Body>();
    let mut builder = Request::builder()
        .method(Method::from_bytes(method.as_bytes()).map_err(|e| e.to_string())?)
        .uri(format!("http://{addr}{path}"));
    for (name, value) in headers {
        builder = builder.header(*name, *value);
    }
    let request = builder.body(Body::from(body)).map_err(|e| e.to_string())?;
    let response = client
        .request(request)
        .await
        .map_err(|e| format!("{method} {path} to {addr}: {e:?}"))?;
    let status = response.status().as_u16();
    let headers = response.headers().clone();
    let body = axum::body::to_bytes(Body::new(response.into_body()), usize::MAX)
        .await
        .map_err(|e| format!("{method} {path} to {addr}: body: {e}"))?
        .to_vec();
    Ok(Response {
        status,
        headers,
        body,
    })
}
