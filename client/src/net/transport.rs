//! The two transports a [`super::Client`] speaks the protocol over, behind one [`Link`]: a
//! websocket, or WebTransport (HTTP/3 over QUIC, `GET /api/quic`; the framing is
//! [`posecast_proto::quic`]'s) where frames come as datagrams.
//!
//! With [`TransportChoice::Auto`] (the default) a connection asks the server's `/api/quic`
//! whether it offers WebTransport; when it does, the client tries it first and falls back to
//! the websocket when the QUIC handshake fails or does not complete in time (UDP blocked on
//! the way, a firewall, a proxy that passes TCP only). [`super::Client::transport`] says which
//! one the connection uses.
//!
//! Over WebTransport the [`Link`] does what a websocket library does by itself — it answers
//! the server's pings — and what datagrams need: it acknowledges every keyframe the client
//! decodes, and in protocol version 8 every wire v2 frame ([`Link::acknowledge`]), so the
//! server codes deltas against frames the client holds and a lost datagram costs its own tick
//! only.

use futures_util::{Sink, SinkExt, Stream, StreamExt};
use posecast_proto::quic as wire;
use std::pin::Pin;
use std::time::Duration;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio_tungstenite::tungstenite::Message;
use tokio_tungstenite::tungstenite::protocol::CloseFrame;
use tokio_tungstenite::tungstenite::protocol::frame::coding::CloseCode;

/// What a client acknowledges of a frame it decoded ([`Link::acknowledge`]).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Ack {
    /// A wire v2 frame (protocol version 8: every frame is acknowledged), else a v1 keyframe.
    pub whole_frame: bool,
    /// Its scene number.
    pub scene_num: u32,
    /// Its tick.
    pub seq: u64,
    /// The avatars it carried.
    pub avatars: Vec<u32>,
}

/// The transport a connection uses.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Transport {
    /// A websocket (TCP): every frame in order, a lost segment holds back the frames behind it.
    WebSocket,
    /// WebTransport over QUIC (UDP): messages on a stream, frames as datagrams.
    WebTransport,
}

impl std::fmt::Display for Transport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Self::WebSocket => "websocket",
            Self::WebTransport => "webtransport",
        })
    }
}

/// Which transport a client tries.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum TransportChoice {
    /// WebTransport when the server offers it (`GET /api/quic`) and its handshake completes
    /// within [`super::ClientOptions::quic_timeout`]; the websocket otherwise.
    #[default]
    Auto,
    /// The websocket only.
    WebSocket,
    /// WebTransport only: a server that does not offer it, or a handshake that fails, fails
    /// the connection.
    WebTransport,
}

/// What `GET /api/quic` says of a server's WebTransport endpoint.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct QuicOffer {
    /// The `https://host:port/` URL to connect to: the websocket URL's host, the endpoint's
    /// UDP port.
    pub url: String,
    /// SHA-256 of a self-signed certificate, to trust by its hash; `None`: a certificate the
    /// system's roots verify.
    pub cert_sha256: Option<[u8; 32]>,
}

/// The largest message the server's stream may carry to the client (a websocket library's
/// default bound).
const MAX_SERVER_MESSAGE_BYTES: usize = 64 << 20;

type BoxSink = Pin<Box<dyn Sink<Message, Error = String> + Send>>;
type BoxStream = Pin<Box<dyn Stream<Item = Result<Message, String>> + Send>>;

/// One connection's messages, whichever the transport: a sink and a stream of websocket
/// messages (over WebTransport, datagrams come as binary messages among the stream's).
pub struct Link {
    /// Messages to the server.
    pub sink: BoxSink,
    /// Messages from the server.
    pub stream: BoxStream,
    /// The transport under them.
    pub transport: Transport,
    /// The QUIC connection (and its endpoint) of a WebTransport link.
    quic: Option<(
        wtransport::Connection,
        wtransport::Endpoint<wtransport::endpoint::endpoint_side::Client>,
    )>,
}

impl std::fmt::Debug for Link {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Link")
            .field("transport", &self.transport)
            .finish_non_exhaustive()
    }
}

impl Link {
    /// A websocket link to `url`.
    ///
    /// # Errors
    /// The websocket handshake failed.
    pub async fn websocket(url: &str) -> Result<Self, String> {
        let (ws, _) = tokio_tungstenite::connect_async(url)
            .await
            .map_err(|e| e.to_string())?;
        let (sink, stream) = ws.split();
        Ok(Self {
            sink: Box::pin(sink.sink_map_err(|e| e.to_string())),
            stream: Box::pin(stream.map(|m| m.map_err(|e| e.to_string()))),
            transport: Transport::WebSocket,
            quic: None,
        })
    }

    /// A WebTransport link to the endpoint `offer` names, its stream opened.
    ///
    /// # Errors
    /// The QUIC or WebTransport handshake failed, or the stream could not be opened.
    pub async fn webtransport(offer: &QuicOffer) -> Result<Self, String> {
        let builder = wtransport::ClientConfig::builder().with_bind_default();
        let builder = match offer.cert_sha256 {
            Some(hash) => {
                builder.with_server_certificate_hashes([wtransport::tls::Sha256Digest::new(hash)])
            }
            None => builder.with_native_certs(),
        };
        let config = builder
            .keep_alive_interval(Some(Duration::from_secs(3)))
            .build();
        let endpoint = wtransport::Endpoint::client(config).map_err(|e| e.to_string())?;
        let conn = endpoint
            .connect(&offer.url)
            .await
            .map_err(|e| e.to_string())?;
        let (send, recv) = conn
            .open_bi()
            .await
            .map_err(|e| e.to_string())?
            .await
            .map_err(|e| e.to_string())?;
        let stream = futures_util::stream::select(received(recv), datagrams(conn.clone()));
        Ok(Self {
            sink: Box::pin(sent(send)),
            stream: Box::pin(stream),
            transport: Transport::WebTransport,
            quic: Some((conn, endpoint)),
        })
    }

    /// Whether the client answers the server's pings itself (a websocket library does).
    #[must_use]
    pub fn answers_pings(&self) -> bool {
        self.quic.is_some()
    }

    /// Acknowledges what the client decoded: over WebTransport the server codes deltas only
    /// against frames acknowledged for every avatar — v1 keyframes, or (protocol version 8)
    /// any v2 frame; a frame too large for a datagram comes cut by avatar, and any part may
    /// be lost. A websocket delivers every frame, and needs none. Returns whether an
    /// acknowledgement went.
    pub fn acknowledge(&self, ack: &Ack) -> bool {
        let datagram = if ack.whole_frame {
            wire::frame_ack_of(ack.scene_num, ack.seq, &ack.avatars)
        } else {
            wire::key_ack_of(ack.scene_num, ack.seq, &ack.avatars)
        };
        match &self.quic {
            // A lost acknowledgement is made up for by the next frame's.
            Some((conn, _)) => conn.send_datagram(datagram).is_ok(),
            None => false,
        }
    }
}

impl Drop for Link {
    fn drop(&mut self) {
        if let Some((conn, _)) = &self.quic {
            conn.close(0u32.into(), b"");
        }
    }
}

/// The messages of the server's stream, until it ends or breaks the framing.
fn received(recv: wtransport::RecvStream) -> impl Stream<Item = Result<Message, String>> + Send {
    futures_util::stream::unfold(Some(recv), |recv| async move {
        let mut recv = recv?;
        let mut header = [0u8; wire::STREAM_HEADER];
        if let Err(e) = recv.read_exact(&mut header).await {
            return Some((Err(format!("the stream ended: {e}")), None));
        }
        let (kind, len) = wire::read_header(header);
        if len > MAX_SERVER_MESSAGE_BYTES {
            return Some((Err(format!("a message of {len} bytes")), None));
        }
        let mut payload = vec![0u8; len];
        if let Err(e) = recv.read_exact(&mut payload).await {
            return Some((Err(format!("the stream ended: {e}")), None));
        }
        let message = match kind {
            wire::TEXT => match String::from_utf8(payload) {
                Ok(text) => Message::Text(text.into()),
                Err(_) => return Some((Err("a text message is not UTF-8".into()), None)),
            },
            wire::BINARY => Message::Binary(payload.into()),
            wire::PING => Message::Ping(payload.into()),
            wire::PONG => Message::Pong(payload.into()),
            wire::CLOSE => Message::Close(close_frame(&payload)),
            other => return Some((Err(format!("a message of unknown kind {other}")), None)),
        };
        Some((Ok(message), Some(recv)))
    })
}

/// A close message's code and reason (`u16` little-endian, then UTF-8), as a websocket's.
fn close_frame(payload: &[u8]) -> Option<CloseFrame> {
    let (code, reason) = payload.split_at_checked(2)?;
    Some(CloseFrame {
        code: CloseCode::from(u16::from_le_bytes([code[0], code[1]])),
        reason: String::from_utf8_lossy(reason).into_owned().into(),
    })
}

/// The server's datagrams (frames), as binary messages, until the connection ends.
fn datagrams(conn: wtransport::Connection) -> impl Stream<Item = Result<Message, String>> + Send {
    futures_util::stream::unfold(Some(conn), |conn| async move {
        let conn = conn?;
        match conn.receive_datagram().await {
            Ok(d) => Some((Ok(Message::Binary(d.payload().to_vec().into())), Some(conn))),
            Err(e) => Some((Err(format!("the connection ended: {e}")), None)),
        }
    })
}

/// Sends messages on the client's stream, framed.
fn sent(send: wtransport::SendStream) -> impl Sink<Message, Error = String> + Send {
    futures_util::sink::unfold(send, |mut send, message: Message| async move {
        let (kind, payload): (u8, Vec<u8>) = match message {
            Message::Text(text) => (wire::TEXT, text.as_bytes().to_vec()),
            Message::Binary(bytes) => (wire::BINARY, bytes.to_vec()),
            Message::Ping(p) => (wire::PING, p.to_vec()),
            Message::Pong(p) => (wire::PONG, p.to_vec()),
            Message::Close(frame) => {
                let mut payload = Vec::new();
                if let Some(f) = frame {
                    payload.extend_from_slice(&u16::from(f.code).to_le_bytes());
                    payload.extend_from_slice(f.reason.as_bytes());
                }
                (wire::CLOSE, payload)
            }
            Message::Frame(_) => return Ok(send),
        };
        send.write_all(&wire::frame_message(kind, &payload))
            .await
            .map_err(|e| e.to_string())?;
        Ok(send)
    })
}

/// Asks the server behind websocket URL `ws_url` (`ws://host:port/…`) whether it offers
/// WebTransport (`GET /api/quic` on the same host and port, over HTTP/1.1), waiting at most
/// `timeout`. `Ok(None)`: it does not (or predates the endpoint: 404).
///
/// # Errors
/// The URL is not a `ws://` one, or the server could not be asked or answered nonsense.
pub async fn discover(ws_url: &str, timeout: Duration) -> Result<Option<QuicOffer>, String> {
    let (host, authority) = host_of(ws_url)?;
    let ask = async {
        let mut tcp = tokio::net::TcpStream::connect(&authority)
            .await
            .map_err(|e| format!("cannot reach {authority}: {e}"))?;
        let request = format!(
            "GET /api/quic HTTP/1.1\r\nHost: {authority}\r\nAccept: application/json\r\n\
             Connection: close\r\n\r\n"
        );
        tcp.write_all(request.as_bytes())
            .await
            .map_err(|e| e.to_string())?;
        let mut answer = Vec::new();
        (&mut tcp)
            .take(1 << 16)
            .read_to_end(&mut answer)
            .await
            .map_err(|e| e.to_string())?;
        Ok::<_, String>(answer)
    };
    let answer = tokio::time::timeout(timeout, ask)
        .await
        .map_err(|_| format!("no answer from {authority}/api/quic in {timeout:?}"))??;
    let split = answer
        .windows(4)
        .position(|w| w == b"\r\n\r\n")
        .ok_or("an HTTP answer without a body")?;
    let head = String::from_utf8_lossy(&answer[..split]);
    let status = head.split_whitespace().nth(1).unwrap_or("");
    if status == "404" {
        return Ok(None);
    }
    if status != "200" {
        return Err(format!("/api/quic answered {status}"));
    }
    let body = &answer[split + 4..];
    let chunked = head.lines().any(|l| {
        l.to_ascii_lowercase()
            .starts_with("transfer-encoding: chunked")
    });
    let body = if chunked {
        dechunk(body)?
    } else {
        body.to_vec()
    };
    offer_of(&host, &body)
}

/// The offer `/api/quic`'s JSON answer makes, for a client that reached the server at `host`.
fn offer_of(host: &str, body: &[u8]) -> Result<Option<QuicOffer>, String> {
    let info: serde_json::Value =
        serde_json::from_slice(body).map_err(|e| format!("/api/quic: {e}"))?;
    if info["available"] != true {
        return Ok(None);
    }
    let port = info["port"]
        .as_u64()
        .and_then(|p| u16::try_from(p).ok())
        .ok_or("/api/quic: no port")?;
    let cert_sha256 = if info["self_signed"] == true {
        let hex = info["cert_sha256"]
            .as_str()
            .ok_or("/api/quic: no certificate hash")?;
        Some(hex_32(hex).ok_or("/api/quic: the certificate hash is not 64 hex digits")?)
    } else {
        None
    };
    Ok(Some(QuicOffer {
        url: format!("https://{host}:{port}/"),
        cert_sha256,
    }))
}

fn hex_32(hex: &str) -> Option<[u8; 32]> {
    if hex.len() != 64 || !hex.is_ascii() {
        return None;
    }
    let mut out = [0u8; 32];
    for (i, byte) in out.iter_mut().enumerate() {
        *byte = u8::from_str_radix(&hex[2 * i..2 * i + 2], 16).ok()?;
    }
    Some(out)
}

/// A chunked HTTP body, joined.
fn dechunk(mut body: &[u8]) -> Result<Vec<u8>, String> {
    let mut out = Vec::new();
    loop {
        let line_end = body
            .windows(2)
            .position(|w| w == b"\r\n")
            .ok_or("a broken chunked body")?;
        let size = std::str::from_utf8(&body[..line_end])
            .ok()
            .and_then(|s| usize::from_str_radix(s.split(';').next()?.trim(), 16).ok())
            .ok_or("a broken chunk size")?;
        body = &body[line_end + 2..];
        if size == 0 {
            return Ok(out);
        }
        let chunk = body.get(..size).ok_or("a cut chunked body")?;
        out.extend_from_slice(chunk);
        body = body.get(size + 2..).ok_or("a cut chunked body")?;
    }
}

/// The host (brackets kept for IPv6) and the `host:port` authority of a `ws://` URL.
fn host_of(ws_url: &str) -> Result<(String, String), String> {
    let rest = ws_url
        .strip_prefix("ws://")
        .ok_or_else(|| format!("{ws_url}: only ws:// URLs are asked for WebTransport"))?;
    let authority = rest.split(['/', '?', '#']).next().unwrap_or("");
    let authority = authority.rsplit('@').next().unwrap_or(authority);
    if authority.is_empty() {
        return Err(format!("{ws_url}: no host"));
    }
    let (host, port) = if let Some(v6) = authority.strip_prefix('[') {
        let end = v6
            .find(']')
            .ok_or_else(|| format!("{ws_url}: a broken host"))?;
        let host = format!("[{}]", &v6[..end]);
        let port = v6[end + 1..].strip_prefix(':').unwrap_or("80");
        (host, port.to_owned())
    } else {
        match authority.rsplit_once(':') {
            Some((h, p)) => (h.to_owned(), p.to_owned()),
            None => (authority.to_owned(), "80".to_owned()),
        }
    };
    Ok((host.clone(), format!("{host}:{port}")))
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn hosts_of_websocket_urls() {
        let h = |u: &str| host_of(u).unwrap();
        assert_eq!(
            h("ws://127.0.0.1:8080/ws"),
            ("127.0.0.1".into(), "127.0.0.1:8080".into())
        );
        assert_eq!(
            h("ws://example.org/ws?x=1"),
            ("example.org".into(), "example.org:80".into())
        );
        assert_eq!(h("ws://[::1]:9/ws"), ("[::1]".into(), "[::1]:9".into()));
        assert_eq!(h("ws://[::1]/ws"), ("[::1]".into(), "[::1]:80".into()));
        assert!(host_of("wss://example.org/ws").is_err());
        assert!(host_of("ws:///ws").is_err());
    }

    #[test]
    fn offers_from_api_quic_answers() {
        let hash = "ab".repeat(32);
        let body = format!(
            r#"{{"available":true,"port":4433,"cert_sha256":"{hash}","self_signed":true}}"#
        );
        assert_eq!(
            offer_of("[::1]", body.as_bytes()).unwrap(),
            Some(QuicOffer {
                url: "https://[::1]:4433/".into(),
                cert_sha256: Some([0xab; 32]),
            })
        );
        // A real certificate: verified by the system's roots, not trusted by its hash.
        let real = br#"{"available":true,"port":443,"cert_sha256":"00","self_signed":false}"#;
        assert_eq!(offer_of("h", real).unwrap().unwrap().cert_sha256, None);
        assert_eq!(offer_of("h", br#"{"available":false}"#).unwrap(), None);
        let short = br#"{"available":true,"port":1,"cert_sha256":"abc","self_signed":true}"#;
        assert!(offer_of("h", short).is_err());
        assert!(offer_of("h", br#"{"available":true,"port":70000}"#).is_err());
        assert!(offer_of("h", b"<html>").is_err());
    }

    #[test]
    fn chunked_bodies_are_joined_and_cut_ones_refused() {
        assert_eq!(
            dechunk(b"3\r\nabc\r\n2;x=y\r\nde\r\n0\r\n\r\n").unwrap(),
            b"abcde"
        );
        assert!(dechunk(b"5\r\nab").is_err());
        assert!(dechunk(b"zz\r\n").is_err());
    }

    #[test]
    fn close_messages_carry_their_code_and_reason() {
        let mut payload = 4001u16.to_le_bytes().to_vec();
        payload.extend_from_slice(b"token revoked");
        let f = close_frame(&payload).unwrap();
        assert_eq!(
            (u16::from(f.code), f.reason.as_str()),
            (4001, "token revoked")
        );
        assert!(close_frame(&[1]).is_none());
    }
}
