//! The protocol over WebTransport (HTTP/3 over QUIC; `--quic-listen`, `GET /api/quic`):
//! the client opens one bidirectional stream, which carries the websocket protocol's messages
//! in order — `hello`, commands, acks, descriptions, errors, live poses — each framed as
//! [`STREAM_HEADER`] bytes (a kind, then the payload's length, `u32` little-endian) and its
//! payload. Frames come as datagrams, one wire v1 frame each (a frame larger than a datagram
//! comes on the stream, kind [`BINARY`]): a delta refers to a keyframe the client
//! acknowledged, with a [`KEY_ACK`] datagram, so a lost datagram costs its own tick only; the
//! server sends the newest keyframe again before each delta until it is acknowledged.

/// Bytes before a message's payload on the stream: its kind and its length.
pub const STREAM_HEADER: usize = 5;
/// A text message (JSON).
pub const TEXT: u8 = 1;
/// A binary message (a frame from the server, a live pose from the client).
pub const BINARY: u8 = 2;
/// A ping (the peer answers with a [`PONG`] of the same payload: the server's pings measure
/// the round trip its adaptive frame rate reads, as on the websocket).
pub const PING: u8 = 3;
/// A pong.
pub const PONG: u8 = 4;
/// A close: a `u16` code (little-endian) and a reason, as a websocket close frame.
pub const CLOSE: u8 = 5;
/// The first byte of a client's keyframe acknowledgement datagram, followed by the keyframe's
/// scene number (`u32`) and tick (`u64`, both little-endian), from its header.
pub const KEY_ACK: u8 = b'K';

/// `payload` framed as a message of `kind` on the stream.
#[must_use]
pub fn frame_message(kind: u8, payload: &[u8]) -> Vec<u8> {
    let mut out = Vec::with_capacity(STREAM_HEADER + payload.len());
    out.push(kind);
    out.extend_from_slice(&(payload.len() as u32).to_le_bytes());
    out.extend_from_slice(payload);
    out
}

/// A message header's kind and payload length.
#[must_use]
pub fn read_header(header: [u8; STREAM_HEADER]) -> (u8, usize) {
    let [kind, a, b, c, d] = header;
    (kind, u32::from_le_bytes([a, b, c, d]) as usize)
}

/// The datagram acknowledging the keyframe of tick `seq` of scene number `scene_num`.
#[must_use]
pub fn key_ack(scene_num: u32, seq: u64) -> [u8; 13] {
    let mut out = [0u8; 13];
    out[0] = KEY_ACK;
    out[1..5].copy_from_slice(&scene_num.to_le_bytes());
    out[5..].copy_from_slice(&seq.to_le_bytes());
    out
}

/// The scene number and tick a keyframe acknowledgement datagram names, if `datagram` is one.
#[must_use]
pub fn read_key_ack(datagram: &[u8]) -> Option<(u32, u64)> {
    match datagram {
        [KEY_ACK, a, b, c, d, rest @ ..] => {
            let seq = u64::from_le_bytes(rest.try_into().ok()?);
            Some((u32::from_le_bytes([*a, *b, *c, *d]), seq))
        }
        _ => None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn messages_and_acks_round_trip_and_junk_is_no_ack() {
        let m = frame_message(TEXT, b"{}");
        let (kind, len) = read_header(m[..STREAM_HEADER].try_into().unwrap());
        assert_eq!((kind, len, &m[STREAM_HEADER..]), (TEXT, 2, &b"{}"[..]));
        assert_eq!(read_key_ack(&key_ack(3, 1 << 40)), Some((3, 1 << 40)));
        assert_eq!(read_key_ack(&key_ack(3, 7)[..12]), None);
        assert_eq!(read_key_ack(b"X123456789012"), None);
        assert_eq!(read_key_ack(&[]), None);
    }
}
