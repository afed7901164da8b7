//! Typed bodies for the errors hyper answers by itself: a request head it cannot parse is
//! answered `400`, a URI too long for it `414`, a head too large `431`, each with an empty body
//! and the connection closed — before any of our code sees a request, so the router's
//! [`super::typed_errors`] cannot give them the `{"code", "message"}` body every other error
//! has. hyper has no hook for these answers, so the connection's I/O is wrapped: a response
//! head that starts a write, has one of those statuses and `content-length: 0` (hyper's, as our
//! handlers never answer those statuses without a body) is written with the typed body instead.
//! Everything else passes through untouched.

use axum::http::StatusCode;
use posecast_proto::msg::{ErrorCode, ProtocolError};
use std::io::IoSlice;
use std::pin::Pin;
use std::task::{Context, Poll};
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};

/// A connection whose parse-error answers get the typed body.
#[derive(Debug)]
pub struct TypedHeadErrors<S> {
    inner: S,
    /// The replacement being written, how far, and how many of the caller's bytes it stands for.
    pending: Option<(Vec<u8>, usize, usize)>,
}

impl<S> TypedHeadErrors<S> {
    /// Wraps `inner`.
    pub fn new(inner: S) -> Self {
        Self {
            inner,
            pending: None,
        }
    }

    /// The connection (after an upgrade: no answer of hyper's is being replaced then).
    pub fn into_inner(self) -> S {
        self.inner
    }
}

/// The typed error for one of hyper's own answers.
fn error_for(status: StatusCode) -> Option<ProtocolError> {
    let (code, message) = match status {
        StatusCode::BAD_REQUEST => (
            ErrorCode::BadMessage,
            "malformed HTTP request: the request line or a header does not parse",
        ),
        StatusCode::URI_TOO_LONG => (ErrorCode::TooLarge, "the request URI is too long"),
        StatusCode::REQUEST_HEADER_FIELDS_TOO_LARGE => (
            ErrorCode::TooLarge,
            "the request head (line and headers) is too large",
        ),
        _ => return None,
    };
    Some(ProtocolError::new(code, message))
}

/// When `bytes` start with a complete response head of hyper's parse errors (one of the
/// statuses of [`error_for`], `content-length: 0`), the same head with a typed JSON body, and
/// the length of the head it replaces.
#[must_use]
pub fn rewrite(bytes: &[u8]) -> Option<(Vec<u8>, usize)> {
    // Cheap first: every write of the connection (websocket frames too, once upgraded) comes
    // through here.
    let code = bytes.get(9..13)?;
    if !bytes.starts_with(b"HTTP/1.") || !matches!(code, b"400 " | b"414 " | b"431 ") {
        return None;
    }
    let end = bytes.windows(4).position(|w| w == b"\r\n\r\n")? + 4;
    let head = std::str::from_utf8(bytes.get(..end)?).ok()?;
    let mut lines = head.split("\r\n");
    let status_line = lines.next()?;
    let mut words = status_line.split(' ');
    if !words.next()?.starts_with("HTTP/1.") {
        return None;
    }
    let status = StatusCode::from_bytes(words.next()?.as_bytes()).ok()?;
    let error = error_for(status)?;
    let headers: Vec<&str> = lines.filter(|l| !l.is_empty()).collect();
    let empty = headers.iter().any(|h| {
        h.split_once(':').is_some_and(|(name, value)| {
            name.trim().eq_ignore_ascii_case("content-length") && value.trim() == "0"
        })
    });
    if !empty {
        return None;
    }
    let body = serde_json::to_vec(&error).ok()?;
    let mut out = format!("{status_line}\r\n");
    for h in headers {
        let name = h.split_once(':').map_or(h, |(n, _)| n).trim();
        if !name.eq_ignore_ascii_case("content-length")
            && !name.eq_ignore_ascii_case("content-type")
        {
            out.push_str(h);
            out.push_str("\r\n");
        }
    }
    out.push_str(&format!(
        "content-type: application/json\r\ncontent-length: {}\r\n\r\n",
        body.len()
    ));
    let mut out = out.into_bytes();
    out.extend_from_slice(&body);
    Some((out, end))
}

impl<S: AsyncWrite + Unpin> TypedHeadErrors<S> {
    /// Writes the pending replacement; `Ready(n)` once it is all out (`n`: the caller's bytes
    /// it stood for).
    fn drive(&mut self, cx: &mut Context<'_>) -> Poll<std::io::Result<usize>> {
        while let Some((bytes, done, stands_for)) = &mut self.pending {
            let Some(rest) = bytes.get(*done..).filter(|r| !r.is_empty()) else {
                let n = *stands_for;
                self.pending = None;
                return Poll::Ready(Ok(n));
            };
            match Pin::new(&mut self.inner).poll_write(cx, rest) {
                Poll::Ready(Ok(0)) => {
                    return Poll::Ready(Err(std::io::ErrorKind::WriteZero.into()));
                }
                Poll::Ready(Ok(n)) => *done += n,
                Poll::Ready(Err(e)) => return Poll::Ready(Err(e)),
                Poll::Pending => return Poll::Pending,
            }
        }
        Poll::Ready(Ok(0))
    }

    /// Starts a replacement when `first` (the start of a write) is one of hyper's error heads.
    fn intercept(&mut self, first: &[u8]) -> bool {
        if self.pending.is_some() {
            return true;
        }
        match rewrite(first) {
            Some((bytes, stands_for)) => {
                self.pending = Some((bytes, 0, stands_for));
                true
            }
            None => false,
        }
    }
}

impl<S: AsyncRead + Unpin> AsyncRead for TypedHeadErrors<S> {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.inner).poll_read(cx, buf)
    }
}

impl<S: AsyncWrite + Unpin> AsyncWrite for TypedHeadErrors<S> {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<std::io::Result<usize>> {
        if self.intercept(buf) {
            return self.drive(cx);
        }
        Pin::new(&mut self.inner).poll_write(cx, buf)
    }

    fn poll_write_vectored(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[IoSlice<'_>],
    ) -> Poll<std::io::Result<usize>> {
        let first = bufs
            .iter()
            .find(|b| !b.is_empty())
            .map_or(&[][..], |b| &**b);
        if self.intercept(first) {
            return self.drive(cx);
        }
        Pin::new(&mut self.inner).poll_write_vectored(cx, bufs)
    }

    fn is_write_vectored(&self) -> bool {
        self.inner.is_write_vectored()
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        if self.pending.is_some() {
            match self.drive(cx) {
                Poll::Ready(Ok(_)) => {}
                Poll::Ready(Err(e)) => return Poll::Ready(Err(e)),
                Poll::Pending => return Poll::Pending,
            }
        }
        Pin::new(&mut self.inner).poll_flush(cx)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.inner).poll_shutdown(cx)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hypers_empty_error_heads_get_the_typed_body_and_nothing_else_changes() {
        let head = b"HTTP/1.1 431 Request Header Fields Too Large\r\ncontent-length: 0\r\ndate: Tue, 01 Dec 2026 21:00:00 GMT\r\n\r\n";
        let (out, replaced) = rewrite(head).unwrap();
        assert_eq!(replaced, head.len());
        let text = String::from_utf8(out).unwrap();
        let (top, body) = text.split_once("\r\n\r\n").unwrap();
        assert!(top.starts_with("HTTP/1.1 431 "), "{top}");
        assert!(top.contains("date: Tue"), "{top}");
        assert!(
            top.contains(&format!("content-length: {}", body.len())),
            "{top}"
        );
        let e: ProtocolError = serde_json::from_str(body).unwrap();
        assert_eq!(e.code, ErrorCode::TooLarge);
        // A response with a body, another status, or a body of its own: untouched.
        for other in [
            &b"HTTP/1.1 400 Bad Request\r\ncontent-length: 12\r\n\r\n{\"code\":\"x\"}"[..],
            b"HTTP/1.1 200 OK\r\ncontent-length: 0\r\n\r\n",
            b"HTTP/1.1 404 Not Found\r\ncontent-length: 0\r\n\r\n",
            b"HTTP/1.1 400 Bad Request\r\ncontent-length: 0\r\n",
            b"{\"code\":\"x\"}",
        ] {
            assert_eq!(rewrite(other), None, "{}", String::from_utf8_lossy(other));
        }
    }
}
