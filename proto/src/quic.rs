//! The protocol over WebTransport (HTTP/3 over QUIC; `--quic-listen`, `GET /api/quic`):
//! the client opens one bidirectional stream, which carries the websocket protocol's messages
//! in order — `hello`, commands, acks, descriptions, errors, live poses — each framed as
//! [`STREAM_HEADER`] bytes (a kind, then the payload's length, `u32` little-endian) and its
//! payload. Frames come as datagrams, one wire v1 frame each: a frame larger than a datagram
//! is cut by avatar into frames that each fit ([`crate::frame::split_by_avatar`]: same header,
//! fewer chunks, each decodable alone), and one avatar's chunk too large for a datagram comes
//! on the stream, kind [`BINARY`]. A delta refers to a keyframe the client acknowledged, with
//! a [`KEY_ACK`] datagram naming the avatars it decoded, so a lost datagram costs its own tick
//! only; the server sends the newest keyframe again before each delta until every avatar of it
//! is acknowledged.

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
/// scene number (`u32`) and tick (`u64`), from its header, and the numbers (`u32` each) of the
/// avatars whose chunks it decoded — none: every avatar of that keyframe. All little-endian.
pub const KEY_ACK: u8 = b'K';

/// The first byte of a client's frame acknowledgement datagram (protocol version 8): the
/// frame's scene number (`u32`), tick (`u64`) and the numbers (`u32` each) of the avatars it
/// decoded — none: every avatar of the frame. All little-endian, as a [`KEY_ACK`].
pub const FRAME_ACK: u8 = b'A';

/// Most avatars one acknowledgement names (it stays within the smallest datagram QUIC allows,
/// 1,200 bytes): a v1 keyframe part with more avatars is acknowledged whole; a wire v2 frame
/// is cut into parts of at most this many ([`crate::frame2::MAX_PART_AVATARS`]).
pub const MAX_ACKED_AVATARS: usize = crate::frame2::MAX_PART_AVATARS;

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

/// The datagram acknowledging the chunks of `avatars` in the keyframe of tick `seq` of scene
/// number `scene_num` (a part of a keyframe cut by avatar); more than [`MAX_ACKED_AVATARS`]
/// acknowledge the whole keyframe.
#[must_use]
pub fn key_ack_of(scene_num: u32, seq: u64, avatars: &[u32]) -> Vec<u8> {
    let mut out = key_ack(scene_num, seq).to_vec();
    if avatars.len() <= MAX_ACKED_AVATARS {
        for a in avatars {
            out.extend_from_slice(&a.to_le_bytes());
        }
    }
    out
}

/// The datagram acknowledging the chunks of `avatars` in the frame of tick `seq` of scene
/// number `scene_num` (protocol version 8); more than [`MAX_ACKED_AVATARS`] acknowledge the
/// whole frame.
#[must_use]
pub fn frame_ack_of(scene_num: u32, seq: u64, avatars: &[u32]) -> Vec<u8> {
    let mut out = key_ack_of(scene_num, seq, avatars);
    out[0] = FRAME_ACK;
    out
}

/// A keyframe acknowledgement: its scene number, tick, and the avatars it names (empty: every
/// avatar of the keyframe).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct KeyAck {
    /// The keyframe's scene number.
    pub scene_num: u32,
    /// Its tick.
    pub seq: u64,
    /// The avatars whose chunks the client decoded; empty: all.
    pub avatars: Vec<u32>,
}

/// The keyframe acknowledgement `datagram` is, if it is one.
#[must_use]
pub fn read_key_ack(datagram: &[u8]) -> Option<KeyAck> {
    match datagram.first() {
        Some(&KEY_ACK) => read_ack(datagram),
        _ => None,
    }
}

/// The frame acknowledgement (protocol version 8) `datagram` is, if it is one.
#[must_use]
pub fn read_frame_ack(datagram: &[u8]) -> Option<KeyAck> {
    match datagram.first() {
        Some(&FRAME_ACK) => read_ack(datagram),
        _ => None,
    }
}

fn read_ack(datagram: &[u8]) -> Option<KeyAck> {
    let [_, a, b, c, d, rest @ ..] = datagram else {
        return None;
    };
    let (seq, avatars) = rest.split_at_checked(8)?;
    if avatars.len() % 4 != 0 || avatars.len() / 4 > MAX_ACKED_AVATARS {
        return None;
    }
    Some(KeyAck {
        scene_num: u32::from_le_bytes([*a, *b, *c, *d]),
        seq: u64::from_le_bytes(seq.try_into().ok()?),
        avatars: avatars
            .chunks_exact(4)
            .map(|n| u32::from_le_bytes([n[0], n[1], n[2], n[3]]))
            .collect(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn messages_and_acks_round_trip_and_junk_is_no_ack() {
        let m = frame_message(TEXT, b"{}");
        let (kind, len) = read_header(m[..STREAM_HEADER].try_into().unwrap());
        assert_eq!((kind, len, &m[STREAM_HEADER..]), (TEXT, 2, &b"{}"[..]));
        let whole = |scene_num, seq| {
            Some(KeyAck {
                scene_num,
                seq,
                avatars: Vec::new(),
            })
        };
        assert_eq!(read_key_ack(&key_ack(3, 1 << 40)), whole(3, 1 << 40));
        assert_eq!(read_key_ack(&key_ack(3, 7)[..12]), None);
        let named = key_ack_of(3, 7, &[1, 70_000]);
        assert_eq!(named.len(), 13 + 8);
        assert_eq!(
            read_key_ack(&named),
            Some(KeyAck {
                scene_num: 3,
                seq: 7,
                avatars: vec![1, 70_000]
            })
        );
        assert_eq!(read_key_ack(&named[..15]), None);
        let many: Vec<u32> = (0..=MAX_ACKED_AVATARS as u32).collect();
        assert_eq!(read_key_ack(&key_ack_of(3, 7, &many)), whole(3, 7));
        assert_eq!(read_key_ack(b"X123456789012"), None);
        // A frame acknowledgement is laid out alike, and is not a keyframe's.
        let frame = frame_ack_of(3, 7, &[1, 70_000]);
        assert_eq!((frame[0], &frame[1..]), (FRAME_ACK, &named[1..]));
        assert_eq!(read_key_ack(&frame), None);
        assert_eq!(read_frame_ack(&named), None);
        assert_eq!(
            read_frame_ack(&frame).map(|a| (a.seq, a.avatars)),
            Some((7, vec![1, 70_000]))
        );
        assert_eq!(read_key_ack(&[]), None);
    }
}
