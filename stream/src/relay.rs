//! A published frame as bytes for another server, and back: what lets a scene ticked on one
//! server be fanned out by others as the same bytes ([`super::feed::Feed::relay_frame`]).
//!
//! A frame travels as its header and, per avatar, the chunk exactly as the owner encoded it
//! plus the pose it encodes (f32 bit patterns), so the receiving server reassembles the same
//! binary messages for any avatar filter and writes the same JSON text from the same floats.
//! Descriptions travel separately (they change rarely); pieces name their avatar by id.
//!
//! Layout (little-endian): `PCR1`, kind (u8: 0 key, 1 delta), scene number (u32), seq (u64),
//! server time µs (u64), base seq (u64), piece count (u32); per piece: id length (u16) and
//! UTF-8 id, chunk length (u32) and chunk, avatar number (u32), description hash (u64),
//! rotations (u32 count, 4 f32 each), translations (u32 count, 3 f32 each), scales (u32 count,
//! 3 f32 each), placement (3 + 4 f32), morph weights (u32 count, f32 each). `PCR1` (before
//! morph weights) is refused: servers of one cluster run one version.

use super::publish::Published;
use bytes::Bytes;
use glam::{Quat, Vec3};
use posecast_proto::frame::{AvatarPose, FrameHeader, FrameKind};
use posecast_proto::msg::AvatarId;
use posecast_proto::placement::Placement;

const MAGIC: &[u8; 4] = b"PCR2";

/// A relayed frame that cannot be read.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum RelayError {
    /// Not a relayed frame of this version.
    #[error("not a relayed frame (bad magic)")]
    Magic,
    /// Cut short.
    #[error("relayed frame cut short at byte {at}")]
    Truncated {
        /// Where the bytes ran out.
        at: usize,
    },
    /// A field holds an impossible value.
    #[error("relayed frame: {0}")]
    Invalid(&'static str),
}

/// One avatar's part of a relayed frame.
#[derive(Debug, Clone, PartialEq)]
pub struct RelayPiece {
    /// The avatar.
    pub avatar: AvatarId,
    /// Its chunk as the owner encoded it.
    pub chunk: Bytes,
    /// The pose the chunk encodes.
    pub pose: AvatarPose,
}

/// A relayed frame, read.
#[derive(Debug, Clone, PartialEq)]
pub struct RelayFrame {
    /// The frame's header as the owner wrote it.
    pub header: FrameHeader,
    /// One piece per avatar, in scene order.
    pub pieces: Vec<RelayPiece>,
}

fn f32s(out: &mut Vec<u8>, values: &[f32]) {
    for v in values {
        out.extend_from_slice(&v.to_bits().to_le_bytes());
    }
}

/// The frame as bytes for another server.
#[must_use]
pub(super) fn encode(frame: &Published) -> Bytes {
    let h = &frame.header;
    let mut out = Vec::with_capacity(
        37 + frame
            .pieces
            .iter()
            .map(|p| 64 + p.chunk.len() + 16 * p.pose.rotations.len())
            .sum::<usize>(),
    );
    out.extend_from_slice(MAGIC);
    out.push(match h.kind {
        FrameKind::Key => 0,
        FrameKind::Delta => 1,
    });
    out.extend_from_slice(&h.scene_num.to_le_bytes());
    out.extend_from_slice(&h.seq.to_le_bytes());
    out.extend_from_slice(&h.server_time_us.to_le_bytes());
    out.extend_from_slice(&h.base_seq.to_le_bytes());
    out.extend_from_slice(&(frame.pieces.len() as u32).to_le_bytes());
    for p in &frame.pieces {
        let id = p.id().0.as_bytes();
        out.extend_from_slice(&(id.len().min(usize::from(u16::MAX)) as u16).to_le_bytes());
        out.extend_from_slice(&id[..id.len().min(usize::from(u16::MAX))]);
        out.extend_from_slice(&(p.chunk.len() as u32).to_le_bytes());
        out.extend_from_slice(&p.chunk);
        let pose = &p.pose;
        out.extend_from_slice(&pose.avatar_num.to_le_bytes());
        out.extend_from_slice(&pose.hash.to_le_bytes());
        out.extend_from_slice(&(pose.rotations.len() as u32).to_le_bytes());
        for q in &pose.rotations {
            f32s(&mut out, &q.to_array());
        }
        out.extend_from_slice(&(pose.translations.len() as u32).to_le_bytes());
        for t in &pose.translations {
            f32s(&mut out, &t.to_array());
        }
        out.extend_from_slice(&(pose.scales.len() as u32).to_le_bytes());
        for s in &pose.scales {
            f32s(&mut out, &s.to_array());
        }
        f32s(&mut out, &pose.placement.position.to_array());
        f32s(&mut out, &pose.placement.rotation.to_array());
        out.extend_from_slice(&(pose.weights.len() as u32).to_le_bytes());
        f32s(&mut out, &pose.weights);
    }
    Bytes::from(out)
}

struct Reader<'a> {
    bytes: &'a [u8],
    at: usize,
}

impl<'a> Reader<'a> {
    fn take(&mut self, n: usize) -> Result<&'a [u8], RelayError> {
        let end = self
            .at
            .checked_add(n)
            .filter(|&e| e <= self.bytes.len())
            .ok_or(RelayError::Truncated { at: self.at })?;
        let s = &self.bytes[self.at..end];
        self.at = end;
        Ok(s)
    }

    fn array<const N: usize>(&mut self) -> Result<[u8; N], RelayError> {
        let mut a = [0u8; N];
        a.copy_from_slice(self.take(N)?);
        Ok(a)
    }

    fn u16(&mut self) -> Result<u16, RelayError> {
        Ok(u16::from_le_bytes(self.array()?))
    }

    fn u32(&mut self) -> Result<u32, RelayError> {
        Ok(u32::from_le_bytes(self.array()?))
    }

    fn u64(&mut self) -> Result<u64, RelayError> {
        Ok(u64::from_le_bytes(self.array()?))
    }

    fn f32(&mut self) -> Result<f32, RelayError> {
        Ok(f32::from_bits(self.u32()?))
    }

    fn vec3(&mut self) -> Result<Vec3, RelayError> {
        Ok(Vec3::new(self.f32()?, self.f32()?, self.f32()?))
    }

    fn quat(&mut self) -> Result<Quat, RelayError> {
        Ok(Quat::from_xyzw(
            self.f32()?,
            self.f32()?,
            self.f32()?,
            self.f32()?,
        ))
    }

    /// A count of items of `size` bytes each, checked against the bytes left (so a forged
    /// count cannot make the reader allocate more than the message holds).
    fn count(&mut self, size: usize) -> Result<usize, RelayError> {
        let n = self.u32()? as usize;
        if n.saturating_mul(size) > self.bytes.len() - self.at {
            return Err(RelayError::Truncated { at: self.at });
        }
        Ok(n)
    }
}

/// The tick number of a relayed frame, read from its header alone.
#[must_use]
pub fn peek_seq(bytes: &[u8]) -> Option<u64> {
    let seq = bytes.get(9..17)?;
    (bytes.get(..4)? == MAGIC).then(|| u64::from_le_bytes(seq.try_into().unwrap_or([0; 8])))
}

/// Reads a relayed frame.
///
/// # Errors
/// The bytes are not a whole relayed frame of this version.
pub fn decode(bytes: &[u8]) -> Result<RelayFrame, RelayError> {
    let mut r = Reader { bytes, at: 0 };
    if r.take(4).map_err(|_| RelayError::Magic)? != MAGIC {
        return Err(RelayError::Magic);
    }
    let kind = match r.array::<1>()?[0] {
        0 => FrameKind::Key,
        1 => FrameKind::Delta,
        _ => return Err(RelayError::Invalid("frame kind")),
    };
    let header = FrameHeader {
        kind,
        scene_num: r.u32()?,
        seq: r.u64()?,
        server_time_us: r.u64()?,
        base_seq: r.u64()?,
    };
    let count = r.count(2)?;
    let mut pieces = Vec::with_capacity(count);
    for _ in 0..count {
        let id_len = usize::from(r.u16()?);
        let id = std::str::from_utf8(r.take(id_len)?)
            .map_err(|_| RelayError::Invalid("avatar id is not UTF-8"))?;
        let chunk_len = r.u32()? as usize;
        let chunk = Bytes::copy_from_slice(r.take(chunk_len)?);
        let avatar_num = r.u32()?;
        let hash = r.u64()?;
        let n = r.count(16)?;
        let rotations = (0..n).map(|_| r.quat()).collect::<Result<_, _>>()?;
        let n = r.count(12)?;
        let translations = (0..n).map(|_| r.vec3()).collect::<Result<_, _>>()?;
        let n = r.count(12)?;
        let scales = (0..n).map(|_| r.vec3()).collect::<Result<_, _>>()?;
        let position = r.vec3()?;
        let rotation = r.quat()?;
        let n = r.count(4)?;
        let weights = (0..n).map(|_| r.f32()).collect::<Result<_, _>>()?;
        pieces.push(RelayPiece {
            avatar: AvatarId(id.to_owned()),
            chunk,
            pose: AvatarPose {
                avatar_num,
                hash,
                rotations,
                translations,
                scales,
                placement: Placement { position, rotation },
                weights,
            },
        });
    }
    if r.at != bytes.len() {
        return Err(RelayError::Invalid("bytes after the last piece"));
    }
    Ok(RelayFrame { header, pieces })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::publish::{Piece, Snapshot};
    use posecast_proto::frame::ChunkEncoder;
    use posecast_sim::avatar::Avatar;
    use std::sync::Arc;

    fn frame() -> Published {
        let rig = Arc::new(posecast_rigs::builtin::rig().unwrap());
        let pieces = ["a", "bb"]
            .iter()
            .enumerate()
            .map(|(i, id)| {
                let mut a = Avatar::new(AvatarId((*id).into()), i as u32 + 7, rig.clone());
                if let Some(walk) = rig.clip("walk").cloned() {
                    a.play(
                        posecast_sim::avatar::playback::Layer::new(walk, None, 0.0, 1.0, true),
                        0.0,
                    );
                }
                a.tick(0.37 * (i as f64 + 1.0));
                Piece::encode(
                    Snapshot::of(&a),
                    &mut ChunkEncoder::new(),
                    FrameKind::Key,
                    false,
                    false,
                )
            })
            .collect();
        Published {
            header: FrameHeader {
                kind: FrameKind::Key,
                scene_num: 0xdead_beef,
                seq: 1 << 40,
                server_time_us: 1_764_000_000_123_456,
                base_seq: 1 << 40,
            },
            pieces,
        }
    }

    /// What the owner encodes reads back as its header, chunks and poses, bit for bit.
    #[test]
    fn a_frame_reads_back_as_written() {
        let f = frame();
        let back = decode(&encode(&f)).unwrap();
        assert_eq!(back.header, f.header);
        assert_eq!(back.pieces.len(), 2);
        for (b, p) in back.pieces.iter().zip(&f.pieces) {
            assert_eq!(&b.avatar, p.id());
            assert_eq!(b.chunk, p.chunk);
            assert_eq!(b.pose, p.pose);
            assert!(!b.pose.rotations.is_empty());
        }
        assert_eq!(peek_seq(&encode(&f)), Some(1 << 40));
    }

    /// Every cut, a byte too many and a wrong magic are refused, never read short.
    #[test]
    fn damaged_bytes_are_refused() {
        let bytes = encode(&frame());
        for cut in 0..bytes.len() {
            assert!(decode(&bytes[..cut]).is_err(), "cut at {cut}");
        }
        let mut long = bytes.to_vec();
        long.push(0);
        assert_eq!(
            decode(&long),
            Err(RelayError::Invalid("bytes after the last piece"))
        );
        let mut magic = bytes.to_vec();
        magic[0] = b'X';
        assert_eq!(decode(&magic), Err(RelayError::Magic));
        assert_eq!(peek_seq(&magic), None);
    }
}
