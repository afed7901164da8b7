//! Binary pose frames: keyframes and delta frames against the last keyframe.
//!
//! A frame is a 32-byte header followed by one chunk per avatar. All integers and floats are
//! little-endian.
//!
//! ```text
//! header   0  u8   magic 0x50 ('P')
//!          1  u8   kind: 1 = keyframe, 2 = delta; bit 7 (0x80, [`WEIGHTS_FLAG`]) set: every
//!                  chunk ends with morph weights (WebTransport sessions of protocol version
//!                  4 and later, which get wire v1)
//!          2  u16  avatar chunk count
//!          4  u32  scene number (from `subscribed`)
//!          8  u64  seq: the scene's tick number
//!         16  u64  server time at the tick, µs since the Unix epoch
//!         24  u64  base seq: the keyframe a delta refers to (== seq for a keyframe)
//! chunk       u32  avatar number (from its description)
//!             u64  description hash
//!             u16  joint count J, u16 translation count T,
//!             u16  scale count S in bits 0–14; bit 15 set: a placement follows the scales
//!             rotations:
//!               keyframe: J × 6 bytes, smallest-three (crate::quant)
//!               delta:    ⌈J/4⌉ bytes of 2-bit tags (joint j at bits 2(j mod 4) of byte j/4),
//!                         then per joint by tag: 0 = unchanged from the keyframe, no bytes;
//!                         1 = same dropped component, three i8 level differences (3 bytes);
//!                         2 = full 6-byte rotation; 3 is invalid.
//!             T × 3 f32 translations, S × 3 f32 scales (joints listed in the description)
//!             placement (when flagged): 3 f32 position, 4 f32 rotation [x, y, z, w]
//!             weights (kind bit 7): u16 count W, W × u16 levels (crate::morph, 0–1023), one
//!                  per channel of the description's `morph_targets`
//! ```
//!
//! The placement ([`crate::placement`]) is in a keyframe chunk when it is not the identity,
//! and in a delta chunk when it differs from its keyframe's; a chunk without one has its
//! keyframe's (a keyframe without one: the identity). So every decoded pose carries the
//! placement of its own tick.
//!
//! Why deltas against the *keyframe* rather than the previous frame: a slow subscriber only
//! ever receives the newest frame (older ones are dropped), so a delta must be decodable from
//! the keyframe alone. The server sends a keyframe at least once a second, whenever the set of
//! avatars or a rig changes, and the scene's last keyframe to every new subscriber before any
//! delta; the per-connection queue never drops a keyframe that a pending delta needs.
//! Translations and scales are few (roots, mostly) and sent as f32 in every frame.

use crate::placement::Placement;
use crate::quant;
use glam::{Quat, Vec3};
use std::collections::HashMap;

/// First byte of every binary frame.
pub const MAGIC: u8 = 0x50;
/// Header size in bytes.
pub const HEADER_BYTES: usize = 32;
/// Bit of a chunk's scale-count field that flags a placement after the scales.
pub const PLACEMENT_FLAG: u16 = 0x8000;
/// Most scaled joints a chunk can carry (the other bit of the field is [`PLACEMENT_FLAG`]).
pub const MAX_SCALES: usize = 0x7fff;
/// Bit of the header's kind byte saying every chunk ends with its morph weights.
pub const WEIGHTS_FLAG: u8 = 0x80;

/// Appends a chunk's morph weights (after the chunk, in a frame whose kind has
/// [`WEIGHTS_FLAG`]): their count and each weight's level.
pub fn write_weights(weights: &[f32], out: &mut Vec<u8>) {
    let n = weights.len().min(usize::from(u16::MAX));
    out.extend_from_slice(&(n as u16).to_le_bytes());
    for &w in &weights[..n] {
        out.extend_from_slice(&crate::morph::weight_level(w).to_le_bytes());
    }
}

/// Sets [`WEIGHTS_FLAG`] in the header at the start of `frame`.
pub fn flag_weights(frame: &mut [u8]) {
    if let Some(kind) = frame.get_mut(1) {
        *kind |= WEIGHTS_FLAG;
    }
}

/// Keyframe or delta.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FrameKind {
    /// Every rotation in full.
    Key,
    /// Rotations relative to the keyframe `base_seq`.
    Delta,
}

/// The header of a binary frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FrameHeader {
    /// Keyframe or delta.
    pub kind: FrameKind,
    /// The scene's number.
    pub scene_num: u32,
    /// Tick number.
    pub seq: u64,
    /// Server time at the tick, µs since the Unix epoch.
    pub server_time_us: u64,
    /// The keyframe a delta refers to; `seq` for a keyframe.
    pub base_seq: u64,
}

/// One avatar's pose, as the server produces it and a client decodes it.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct AvatarPose {
    /// The avatar's number.
    pub avatar_num: u32,
    /// Its description hash.
    pub hash: u64,
    /// Local rotation of every joint.
    pub rotations: Vec<Quat>,
    /// Local translations of the description's `translated_joints`, in order.
    pub translations: Vec<Vec3>,
    /// Local scales of the description's `scaled_joints`, in order.
    pub scales: Vec<Vec3>,
    /// The avatar's world placement at this tick (clients draw `placement · root`).
    pub placement: Placement,
    /// Morph weights, one per channel of the description's `morph_targets` (empty for a rig
    /// without any), each a multiple of 1/1023 in `[0, 1]` ([`crate::morph`]).
    pub weights: Vec<f32>,
}

/// A decoded frame.
#[derive(Debug, Clone, PartialEq)]
pub struct Frame {
    /// Its header.
    pub header: FrameHeader,
    /// One pose per avatar chunk.
    pub avatars: Vec<AvatarPose>,
}

/// Why a binary frame could not be decoded.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum FrameError {
    /// Shorter than its own counts say.
    #[error("frame truncated at byte {at} (needed {needed} more)")]
    Truncated {
        /// Offset where data ran out.
        at: usize,
        /// Bytes missing.
        needed: usize,
    },
    /// Not a posecast frame.
    #[error("bad magic byte {0:#04x}")]
    Magic(u8),
    /// Unknown frame kind.
    #[error("unknown frame kind {0}")]
    Kind(u8),
    /// Bytes left over after the last chunk.
    #[error("{0} trailing bytes after the last avatar chunk")]
    Trailing(usize),
    /// A delta tag of 3.
    #[error("avatar {avatar}: invalid delta tag for joint {joint}")]
    Tag {
        /// The avatar.
        avatar: u32,
        /// The joint.
        joint: usize,
    },
    /// A delta whose keyframe this decoder does not hold (it was never received, or a newer
    /// keyframe replaced it). Wait for the next keyframe.
    #[error("avatar {avatar}: delta against keyframe {base_seq}, which this decoder does not hold")]
    MissingKeyframe {
        /// The avatar.
        avatar: u32,
        /// The keyframe the delta needs.
        base_seq: u64,
    },
    /// A delta whose joint count differs from its keyframe's.
    #[error("avatar {avatar}: delta has {actual} joints, its keyframe {expected}")]
    JointCount {
        /// The avatar.
        avatar: u32,
        /// The keyframe's joint count.
        expected: usize,
        /// The delta's.
        actual: usize,
    },
}

/// Writes a frame header. `avatar_count` is the number of chunks that follow.
pub fn write_header(header: &FrameHeader, avatar_count: u16, out: &mut Vec<u8>) {
    out.push(MAGIC);
    out.push(match header.kind {
        FrameKind::Key => 1,
        FrameKind::Delta => 2,
    });
    out.extend_from_slice(&avatar_count.to_le_bytes());
    out.extend_from_slice(&header.scene_num.to_le_bytes());
    out.extend_from_slice(&header.seq.to_le_bytes());
    out.extend_from_slice(&header.server_time_us.to_le_bytes());
    out.extend_from_slice(&header.base_seq.to_le_bytes());
}

/// Encodes one avatar's chunks. Holds the quantised rotations of the last keyframe, so deltas
/// can refer to them; one encoder per avatar per scene.
#[derive(Debug, Default, Clone)]
pub struct ChunkEncoder {
    key: Vec<u64>,
    key_placement: Placement,
    scratch: Vec<u64>,
    /// Whether the last chunk encoded was a keyframe (its rotations are then in `key`).
    last_key: bool,
}

impl ChunkEncoder {
    /// A fresh encoder (its first chunk must be a keyframe).
    #[must_use]
    pub fn new() -> Self {
        Self::default()
    }

    /// The quantised rotations ([`quant::encode`]) of the chunk encoded last, so other
    /// encodings of the same pose (wire v2's levels) need not quantise it again.
    #[must_use]
    pub fn rotation_bits(&self) -> &[u64] {
        if self.last_key {
            &self.key
        } else {
            &self.scratch
        }
    }

    /// Whether a delta can be encoded: a keyframe with this joint count was encoded before.
    #[must_use]
    pub fn has_key(&self, joint_count: usize) -> bool {
        !self.key.is_empty() && self.key.len() == joint_count
    }

    /// Appends `pose`'s chunk to `out`. A keyframe chunk becomes the new reference for deltas.
    /// A delta needs a keyframe with the same joint count (check [`Self::has_key`]; the server
    /// forces a keyframe when any avatar lacks one): without one, every joint is written in
    /// full, and a decoder rejects the chunk for its joint count.
    pub fn encode(&mut self, pose: &AvatarPose, kind: FrameKind, out: &mut Vec<u8>) {
        let joints = pose.rotations.len();
        out.extend_from_slice(&pose.avatar_num.to_le_bytes());
        out.extend_from_slice(&pose.hash.to_le_bytes());
        let with_placement = match kind {
            FrameKind::Key => !pose.placement.is_identity(),
            FrameKind::Delta => pose.placement != self.key_placement,
        };
        if kind == FrameKind::Key {
            self.key_placement = pose.placement;
        }
        for n in [joints, pose.translations.len()] {
            out.extend_from_slice(&(n.min(usize::from(u16::MAX)) as u16).to_le_bytes());
        }
        let scales = pose.scales.len().min(MAX_SCALES);
        let flag = if with_placement { PLACEMENT_FLAG } else { 0 };
        out.extend_from_slice(&(scales as u16 | flag).to_le_bytes());
        self.scratch.clear();
        self.scratch
            .extend(pose.rotations.iter().map(|&q| quant::encode(q)));
        match kind {
            FrameKind::Key => {
                for bits in &self.scratch {
                    out.extend_from_slice(&bits.to_le_bytes()[..quant::BYTES]);
                }
                std::mem::swap(&mut self.key, &mut self.scratch);
                self.last_key = true;
            }
            FrameKind::Delta => {
                self.last_key = false;
                let tags_at = out.len();
                out.resize(tags_at + joints.div_ceil(4), 0);
                for (j, &bits) in self.scratch.iter().enumerate() {
                    let tag = match self.key.get(j) {
                        Some(&key) if key == bits => 0u8,
                        Some(&key) => match small_difference(key, bits) {
                            Some(d) => {
                                out.extend(d.map(|v| v as u8));
                                1
                            }
                            None => {
                                out.extend_from_slice(&bits.to_le_bytes()[..quant::BYTES]);
                                2
                            }
                        },
                        None => {
                            out.extend_from_slice(&bits.to_le_bytes()[..quant::BYTES]);
                            2
                        }
                    };
                    out[tags_at + j / 4] |= tag << (2 * (j % 4));
                }
            }
        }
        for v in pose.translations.iter().chain(&pose.scales[..scales]) {
            for c in v.to_array() {
                out.extend_from_slice(&c.to_le_bytes());
            }
        }
        if with_placement {
            let p = &pose.placement;
            for c in p
                .position
                .to_array()
                .into_iter()
                .chain(p.rotation.to_array())
            {
                out.extend_from_slice(&c.to_le_bytes());
            }
        }
    }
}

/// The length in bytes of the avatar chunk at the start of `chunk` (of a frame of kind `kind`),
/// and its avatar number.
///
/// # Errors
/// The chunk is cut short, or a delta tag is invalid.
pub fn chunk_len(chunk: &[u8], kind: FrameKind, weights: bool) -> Result<(usize, u32), FrameError> {
    let mut r = Reader {
        bytes: chunk,
        at: 0,
    };
    let head = r.take(12)?;
    let avatar = u32::from_le_bytes([head[0], head[1], head[2], head[3]]);
    let joints = usize::from(r.u16()?);
    let translations = usize::from(r.u16()?);
    let scales_field = r.u16()?;
    let scales = usize::from(scales_field & !PLACEMENT_FLAG);
    match kind {
        FrameKind::Key => {
            r.take(joints * quant::BYTES)?;
        }
        FrameKind::Delta => {
            let tags = r.take(joints.div_ceil(4))?;
            let mut bytes = 0;
            for joint in 0..joints {
                bytes += match (tags[joint / 4] >> (2 * (joint % 4))) & 3 {
                    0 => 0,
                    1 => 3,
                    2 => quant::BYTES,
                    _ => return Err(FrameError::Tag { avatar, joint }),
                };
            }
            r.take(bytes)?;
        }
    }
    r.take((translations + scales) * 12)?;
    if scales_field & PLACEMENT_FLAG != 0 {
        r.take(7 * 4)?;
    }
    if weights {
        let n = usize::from(r.u16()?);
        r.take(2 * n)?;
    }
    Ok((r.at, avatar))
}

/// A part of a frame cut by avatar: its bytes (a frame) and the avatar numbers it carries.
pub type FramePart = (Vec<u8>, Vec<u32>);

/// `frame` cut into frames of whole avatar chunks, each at most `max` bytes where it can be
/// (a chunk larger than `max` less the header goes alone), each with `frame`'s header and its
/// own chunk count, each decodable alone (a delta refers to its avatar's keyframe): how a
/// frame too large for one datagram goes as several. Returns each part with the avatar
/// numbers it carries. A frame that fits comes back whole.
///
/// # Errors
/// The frame is malformed.
pub fn split_by_avatar(frame: &[u8], max: usize) -> Result<Vec<FramePart>, FrameError> {
    let (_, chunks) = chunks(frame)?;
    let mut parts: Vec<FramePart> = Vec::new();
    let mut open: Option<FramePart> = None;
    for (range, avatar) in chunks {
        if let Some((bytes, _)) = &open
            && bytes.len() + range.len() > max
        {
            parts.extend(open.take());
        }
        let (bytes, avatars) =
            open.get_or_insert_with(|| (frame[..HEADER_BYTES].to_vec(), Vec::new()));
        bytes.extend_from_slice(&frame[range]);
        avatars.push(avatar);
    }
    parts.extend(open);
    for (bytes, avatars) in &mut parts {
        bytes[2..4].copy_from_slice(&(avatars.len() as u16).to_le_bytes());
    }
    if parts.is_empty() {
        parts.push((frame.to_vec(), Vec::new()));
    }
    Ok(parts)
}

/// Where an avatar chunk lies in its frame, and its avatar number.
type ChunkAt = (std::ops::Range<usize>, u32);

/// The header of `frame` and where each of its avatar chunks lies, with its avatar number:
/// the walk [`split_by_avatar`] and [`avatars_of`] share.
fn chunks(frame: &[u8]) -> Result<(FrameHeader, Vec<ChunkAt>), FrameError> {
    let mut r = Reader {
        bytes: frame,
        at: 0,
    };
    let (header, count, weights) = header(&mut r)?;
    let mut chunks = Vec::with_capacity(usize::from(count));
    let mut at = HEADER_BYTES;
    for _ in 0..count {
        let (len, avatar) = chunk_len(&frame[at..], header.kind, weights)?;
        chunks.push((at..at + len, avatar));
        at += len;
    }
    if at != frame.len() {
        return Err(FrameError::Trailing(frame.len() - at));
    }
    Ok((header, chunks))
}

/// The header of `frame` and the numbers of the avatars it carries, in order, without
/// decoding a rotation: what a client acknowledging a keyframe (or a part of one cut by
/// avatar) names.
///
/// # Errors
/// The frame is malformed.
pub fn avatars_of(frame: &[u8]) -> Result<(FrameHeader, Vec<u32>), FrameError> {
    let (header, chunks) = chunks(frame)?;
    Ok((
        header,
        chunks.into_iter().map(|(_, avatar)| avatar).collect(),
    ))
}

/// Appends to `out` the chunk `chunk` (one avatar's, as [`ChunkEncoder::encode`] wrote it, of
/// a frame of kind `kind`) cut down to the joints `selection` names ([`crate::subset`]): the
/// selected rotations (keyframe: their 6 bytes; delta: their tags and bytes), translations
/// and scales, and the placement as it was. A delta cut this way decodes against the keyframe
/// cut the same way, so one encoding serves every subset.
///
/// # Errors
/// The chunk is malformed, or its joint, translation or scale counts are not the ones the
/// selection was made for.
pub fn select_chunk(
    chunk: &[u8],
    kind: FrameKind,
    selection: &crate::subset::Selection,
    out: &mut Vec<u8>,
) -> Result<(), FrameError> {
    let start = out.len();
    let result = select_into(chunk, kind, selection, out);
    if result.is_err() {
        out.truncate(start);
    }
    result
}

fn select_into(
    chunk: &[u8],
    kind: FrameKind,
    selection: &crate::subset::Selection,
    out: &mut Vec<u8>,
) -> Result<(), FrameError> {
    let mut r = Reader {
        bytes: chunk,
        at: 0,
    };
    let head = r.take(12)?;
    let avatar = u32::from_le_bytes([head[0], head[1], head[2], head[3]]);
    let joints = usize::from(r.u16()?);
    let translations = usize::from(r.u16()?);
    let scales_field = r.u16()?;
    let scales = usize::from(scales_field & !PLACEMENT_FLAG);
    if joints != selection.joint_count {
        return Err(FrameError::JointCount {
            avatar,
            expected: selection.joint_count,
            actual: joints,
        });
    }
    let streamed_fits = |which: &[usize], n: usize| which.iter().all(|&i| i < n);
    if !streamed_fits(&selection.translations, translations)
        || !streamed_fits(&selection.scales, scales)
    {
        return Err(FrameError::Truncated {
            at: r.at,
            needed: 12,
        });
    }
    out.extend_from_slice(head);
    for n in [selection.joints.len(), selection.translations.len()] {
        out.extend_from_slice(&(n as u16).to_le_bytes());
    }
    let flag = scales_field & PLACEMENT_FLAG;
    out.extend_from_slice(&(selection.scales.len() as u16 | flag).to_le_bytes());
    match kind {
        FrameKind::Key => {
            let rotations = r.take(joints * quant::BYTES)?;
            for j in selection.joint_indices() {
                out.extend_from_slice(&rotations[j * quant::BYTES..(j + 1) * quant::BYTES]);
            }
        }
        FrameKind::Delta => {
            let tags = r.take(joints.div_ceil(4))?;
            let tag = |j: usize| (tags[j / 4] >> (2 * (j % 4))) & 3;
            // Where each joint's bytes start.
            let mut at = Vec::with_capacity(joints + 1);
            let mut offset = 0usize;
            for j in 0..joints {
                at.push(offset);
                offset += match tag(j) {
                    0 => 0,
                    1 => 3,
                    2 => quant::BYTES,
                    _ => return Err(FrameError::Tag { avatar, joint: j }),
                };
            }
            let data = r.take(offset)?;
            let tags_at = out.len();
            out.resize(tags_at + selection.joints.len().div_ceil(4), 0);
            for (k, j) in selection.joint_indices().enumerate() {
                let t = tag(j);
                out[tags_at + k / 4] |= t << (2 * (k % 4));
                let len = [0, 3, quant::BYTES][usize::from(t)];
                out.extend_from_slice(&data[at[j]..at[j] + len]);
            }
        }
    }
    let streamed = r.take((translations + scales) * 12)?;
    let (t_bytes, s_bytes) = streamed.split_at(translations * 12);
    for &i in &selection.translations {
        out.extend_from_slice(&t_bytes[i * 12..(i + 1) * 12]);
    }
    for &i in &selection.scales {
        out.extend_from_slice(&s_bytes[i * 12..(i + 1) * 12]);
    }
    if flag != 0 {
        out.extend_from_slice(r.take(28)?);
    }
    if r.at != chunk.len() {
        return Err(FrameError::Trailing(chunk.len() - r.at));
    }
    Ok(())
}

const LEVEL_MASK: u64 = (1 << 15) - 1;

fn levels(bits: u64) -> (u64, [i32; 3]) {
    let index = (bits >> 45) & 3;
    let l = |k: u32| ((bits >> (15 * (2 - k))) & LEVEL_MASK) as i32;
    (index, [l(0), l(1), l(2)])
}

fn small_difference(key: u64, bits: u64) -> Option<[i8; 3]> {
    let (ki, kl) = levels(key);
    let (bi, bl) = levels(bits);
    if ki != bi {
        return None;
    }
    let mut d = [0i8; 3];
    for k in 0..3 {
        d[k] = i8::try_from(bl[k] - kl[k]).ok()?;
    }
    Some(d)
}

fn apply_difference(key: u64, d: [i8; 3]) -> u64 {
    let (index, l) = levels(key);
    let mut bits = index;
    for k in 0..3 {
        let level = (l[k] + i32::from(d[k])).clamp(0, LEVEL_MASK as i32) as u64;
        bits = (bits << 15) | level;
    }
    bits
}

/// Decodes binary frames, keeping the last keyframe of every (scene, avatar) for deltas.
#[derive(Debug, Default)]
pub struct FrameDecoder {
    keys: HashMap<(u32, u32), (u64, Vec<u64>, Placement)>,
}

struct Reader<'a> {
    bytes: &'a [u8],
    at: usize,
}

impl<'a> Reader<'a> {
    fn take(&mut self, n: usize) -> Result<&'a [u8], FrameError> {
        let end = self
            .at
            .checked_add(n)
            .filter(|&e| e <= self.bytes.len())
            .ok_or(FrameError::Truncated {
                at: self.at,
                needed: n.saturating_sub(self.bytes.len() - self.at),
            })?;
        let s = &self.bytes[self.at..end];
        self.at = end;
        Ok(s)
    }
    fn array<const N: usize>(&mut self) -> Result<[u8; N], FrameError> {
        let mut a = [0u8; N];
        a.copy_from_slice(self.take(N)?);
        Ok(a)
    }
    fn u8(&mut self) -> Result<u8, FrameError> {
        Ok(self.array::<1>()?[0])
    }
    fn u16(&mut self) -> Result<u16, FrameError> {
        Ok(u16::from_le_bytes(self.array()?))
    }
    fn u32(&mut self) -> Result<u32, FrameError> {
        Ok(u32::from_le_bytes(self.array()?))
    }
    fn u64(&mut self) -> Result<u64, FrameError> {
        Ok(u64::from_le_bytes(self.array()?))
    }
    fn quat_bits(&mut self) -> Result<u64, FrameError> {
        let mut b = [0u8; 8];
        b[..quant::BYTES].copy_from_slice(self.take(quant::BYTES)?);
        Ok(u64::from_le_bytes(b))
    }
    fn f32(&mut self) -> Result<f32, FrameError> {
        Ok(f32::from_le_bytes(self.array()?))
    }
    fn vec3(&mut self) -> Result<Vec3, FrameError> {
        let b: [u8; 12] = self.array()?;
        let f = |i: usize| f32::from_le_bytes([b[i], b[i + 1], b[i + 2], b[i + 3]]);
        Ok(Vec3::new(f(0), f(4), f(8)))
    }
}

/// Reads just the header of a binary frame.
///
/// # Errors
/// Truncated, bad magic or unknown kind.
pub fn read_header(bytes: &[u8]) -> Result<(FrameHeader, u16), FrameError> {
    let mut r = Reader { bytes, at: 0 };
    header(&mut r).map(|(h, count, _)| (h, count))
}

/// The header, its chunk count, and whether its chunks carry morph weights.
fn header(r: &mut Reader<'_>) -> Result<(FrameHeader, u16, bool), FrameError> {
    let magic = r.u8()?;
    if magic != MAGIC {
        return Err(FrameError::Magic(magic));
    }
    let raw = r.u8()?;
    let kind = match raw & !WEIGHTS_FLAG {
        1 => FrameKind::Key,
        2 => FrameKind::Delta,
        _ => return Err(FrameError::Kind(raw)),
    };
    let count = r.u16()?;
    let scene_num = r.u32()?;
    let seq = r.u64()?;
    let server_time_us = r.u64()?;
    let base_seq = r.u64()?;
    Ok((
        FrameHeader {
            kind,
            scene_num,
            seq,
            server_time_us,
            base_seq,
        },
        count,
        raw & WEIGHTS_FLAG != 0,
    ))
}

impl FrameDecoder {
    /// A decoder holding no keyframes.
    #[must_use]
    pub fn new() -> Self {
        Self::default()
    }

    /// Decodes one binary frame. A keyframe's rotations become the reference for later deltas
    /// of the same scene and avatar. On error nothing is changed.
    ///
    /// # Errors
    /// Malformed bytes, or a delta whose keyframe this decoder does not hold.
    pub fn decode(&mut self, bytes: &[u8]) -> Result<Frame, FrameError> {
        let mut r = Reader { bytes, at: 0 };
        let (header, count, with_weights) = header(&mut r)?;
        let mut avatars = Vec::with_capacity(usize::from(count).min(bytes.len() / 16));
        let mut new_keys = Vec::new();
        for _ in 0..count {
            let avatar_num = r.u32()?;
            let hash = r.u64()?;
            let joints = usize::from(r.u16()?);
            let translations = usize::from(r.u16()?);
            let scales_field = r.u16()?;
            let scales = usize::from(scales_field & !PLACEMENT_FLAG);
            let mut bits = Vec::with_capacity(joints.min(bytes.len()));
            // A chunk without a placement has its keyframe's (a keyframe's default: identity).
            let mut placement = Placement::IDENTITY;
            match header.kind {
                FrameKind::Key => {
                    for _ in 0..joints {
                        bits.push(r.quat_bits()?);
                    }
                }
                FrameKind::Delta => {
                    let key = match self.keys.get(&(header.scene_num, avatar_num)) {
                        Some((seq, key, key_placement)) if *seq == header.base_seq => {
                            placement = *key_placement;
                            key
                        }
                        _ => {
                            return Err(FrameError::MissingKeyframe {
                                avatar: avatar_num,
                                base_seq: header.base_seq,
                            });
                        }
                    };
                    if key.len() != joints {
                        return Err(FrameError::JointCount {
                            avatar: avatar_num,
                            expected: key.len(),
                            actual: joints,
                        });
                    }
                    let tags = r.take(joints.div_ceil(4))?;
                    for (j, &key_bits) in key.iter().enumerate() {
                        let tag = (tags[j / 4] >> (2 * (j % 4))) & 3;
                        bits.push(match tag {
                            0 => key_bits,
                            1 => {
                                let d: [u8; 3] = r.array()?;
                                apply_difference(key_bits, d.map(|v| v as i8))
                            }
                            2 => r.quat_bits()?,
                            _ => {
                                return Err(FrameError::Tag {
                                    avatar: avatar_num,
                                    joint: j,
                                });
                            }
                        });
                    }
                }
            }
            let mut pose = AvatarPose {
                avatar_num,
                hash,
                rotations: bits.iter().map(|&b| quant::decode(b)).collect(),
                translations: Vec::with_capacity(translations.min(bytes.len() / 12)),
                scales: Vec::with_capacity(scales.min(bytes.len() / 12)),
                placement,
                weights: Vec::new(),
            };
            for _ in 0..translations {
                pose.translations.push(r.vec3()?);
            }
            for _ in 0..scales {
                pose.scales.push(r.vec3()?);
            }
            if scales_field & PLACEMENT_FLAG != 0 {
                let position = r.vec3()?;
                let q = [r.f32()?, r.f32()?, r.f32()?, r.f32()?];
                pose.placement = Placement {
                    position,
                    rotation: Quat::from_array(q),
                };
            }
            if with_weights {
                let n = usize::from(r.u16()?);
                let levels = r.take(2 * n)?;
                pose.weights = levels
                    .chunks_exact(2)
                    .map(|l| crate::morph::weight_value(u16::from_le_bytes([l[0], l[1]])))
                    .collect();
            }
            if header.kind == FrameKind::Key {
                new_keys.push(((header.scene_num, avatar_num), bits, pose.placement));
            }
            avatars.push(pose);
        }
        if r.at != bytes.len() {
            return Err(FrameError::Trailing(bytes.len() - r.at));
        }
        for (k, bits, placement) in new_keys {
            self.keys.insert(k, (header.seq, bits, placement));
        }
        Ok(Frame { header, avatars })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::arb_quat;
    use crate::testing::f32s;
    use proptest::prelude::*;

    fn frame(
        kind: FrameKind,
        seq: u64,
        base: u64,
        enc: &mut ChunkEncoder,
        pose: &AvatarPose,
    ) -> Vec<u8> {
        let mut out = Vec::new();
        let h = FrameHeader {
            kind,
            scene_num: 3,
            seq,
            server_time_us: 99,
            base_seq: base,
        };
        write_header(&h, 1, &mut out);
        enc.encode(pose, kind, &mut out);
        out
    }

    fn pose(rotations: Vec<Quat>) -> AvatarPose {
        AvatarPose {
            avatar_num: 7,
            hash: 0xabcd,
            rotations,
            translations: vec![Vec3::new(1.0, 2.0, 3.0)],
            scales: vec![],
            placement: Placement::IDENTITY,
            weights: Vec::new(),
        }
    }

    /// A frame of many avatars (different joint counts, placements, deltas with every tag)
    /// cut by avatar: every part within the bound, each decodable alone, together the whole
    /// frame's poses; a part lost costs only its own avatars; a chunk over the bound goes alone.
    #[test]
    fn frames_split_by_avatar_decode_alone_and_together_as_the_whole() {
        let avatars: Vec<AvatarPose> = (0..12u32)
            .map(|i| {
                let joints = 5 + 7 * i as usize;
                AvatarPose {
                    avatar_num: 100 + i,
                    hash: u64::from(i) * 31,
                    rotations: (0..joints)
                        .map(|j| Quat::from_rotation_x(0.01 * (i as f32 + j as f32)))
                        .collect(),
                    translations: vec![Vec3::new(i as f32, 0.0, 0.0)],
                    scales: vec![],
                    placement: if i % 2 == 0 {
                        Placement::IDENTITY
                    } else {
                        Placement {
                            position: Vec3::new(1.0, 0.0, i as f32),
                            rotation: Quat::IDENTITY,
                        }
                    },
                    weights: Vec::new(),
                }
            })
            .collect();
        let mut encoders: Vec<ChunkEncoder> = avatars.iter().map(|_| ChunkEncoder::new()).collect();
        let whole = |kind, seq, base, poses: &[AvatarPose], encoders: &mut [ChunkEncoder]| {
            let mut out = Vec::new();
            let h = FrameHeader {
                kind,
                scene_num: 3,
                seq,
                server_time_us: 99,
                base_seq: base,
            };
            write_header(&h, poses.len() as u16, &mut out);
            for (p, e) in poses.iter().zip(encoders) {
                e.encode(p, kind, &mut out);
            }
            out
        };
        let key = whole(FrameKind::Key, 1, 1, &avatars, &mut encoders);
        // Moved: small changes, large ones, and unchanged joints.
        let moved: Vec<AvatarPose> = avatars
            .iter()
            .map(|a| AvatarPose {
                rotations: a
                    .rotations
                    .iter()
                    .enumerate()
                    .map(|(j, q)| match j % 3 {
                        0 => *q,
                        1 => Quat::from_rotation_y(0.001) * *q,
                        _ => Quat::from_rotation_z(1.0) * *q,
                    })
                    .collect(),
                ..a.clone()
            })
            .collect();
        let delta = whole(FrameKind::Delta, 2, 1, &moved, &mut encoders);
        let max = 400;
        let mut reference = FrameDecoder::new();
        let mut split_decoder = FrameDecoder::new();
        for frame in [&key, &delta] {
            let want = reference.decode(frame).unwrap();
            let parts = split_by_avatar(frame, max).unwrap();
            assert!(parts.len() > 2, "{} parts", parts.len());
            let mut got = Vec::new();
            for (bytes, nums) in &parts {
                // A chunk over the bound alone in its part.
                assert!(
                    bytes.len() <= max || nums.len() == 1,
                    "{} bytes",
                    bytes.len()
                );
                let part = split_decoder.decode(bytes).unwrap();
                assert_eq!(part.header, want.header);
                let decoded: Vec<u32> = part.avatars.iter().map(|a| a.avatar_num).collect();
                assert_eq!(&decoded, nums);
                // What an acknowledgement names, read without decoding.
                assert_eq!(avatars_of(bytes).unwrap(), (want.header, decoded));
                got.extend(part.avatars);
            }
            assert_eq!(got, want.avatars);
            // The keyframe's largest chunks do not fit the bound.
            let alone = parts.iter().any(|(b, n)| b.len() > max && n.len() == 1);
            assert_eq!(alone, frame == &key);
        }
        // A lost part of the keyframe: the delta's other parts still decode.
        let mut lossy = FrameDecoder::new();
        let key_parts = split_by_avatar(&key, max).unwrap();
        for (bytes, _) in key_parts.iter().skip(1) {
            lossy.decode(bytes).unwrap();
        }
        let lost = &key_parts[0].1;
        for (bytes, nums) in split_by_avatar(&delta, max).unwrap() {
            let result = lossy.decode(&bytes);
            assert_eq!(
                result.is_ok(),
                !nums.iter().any(|n| lost.contains(n)),
                "{nums:?}"
            );
        }
        // A frame that fits comes back whole; malformed ones are refused.
        assert_eq!(
            split_by_avatar(&key, key.len()).unwrap(),
            vec![(key.clone(), (100..112).collect())]
        );
        assert!(split_by_avatar(&key[..key.len() - 1], max).is_err());
        let mut trailing = key.clone();
        trailing.push(0);
        assert!(split_by_avatar(&trailing, max).is_err());
        assert!(avatars_of(&trailing).is_err());
        assert!(avatars_of(&key[..key.len() - 1]).is_err());
    }

    /// Chunks flagged to carry morph weights decode to the weights' levels (within the
    /// wire's bound), whole and cut by avatar; a kind with the flag and an unknown kind is
    /// refused, and weights cut short are a truncated frame.
    #[test]
    fn morph_weights_ride_in_flagged_v1_chunks() {
        let mut out = Vec::new();
        let h = FrameHeader {
            kind: FrameKind::Key,
            scene_num: 1,
            seq: 5,
            server_time_us: 0,
            base_seq: 5,
        };
        write_header(&h, 3, &mut out);
        flag_weights(&mut out);
        let faces = [vec![0.25, 1.0, 0.0], vec![], vec![0.5; 40]];
        for (i, w) in faces.iter().enumerate() {
            let mut p = pose(vec![Quat::IDENTITY; 4]);
            p.avatar_num = i as u32;
            ChunkEncoder::new().encode(&p, FrameKind::Key, &mut out);
            write_weights(w, &mut out);
        }
        let decoded = FrameDecoder::new().decode(&out).unwrap();
        for (a, want) in decoded.avatars.iter().zip(&faces) {
            assert_eq!(a.weights.len(), want.len());
            for (g, w) in a.weights.iter().zip(want) {
                assert!((g - w).abs() <= crate::morph::MAX_WEIGHT_ERROR, "{g} {w}");
            }
        }
        let parts = split_by_avatar(&out, HEADER_BYTES + 100).unwrap();
        assert_eq!(parts.len(), 3);
        let mut dec = FrameDecoder::new();
        for ((bytes, nums), want) in parts.iter().zip(&decoded.avatars) {
            let part = dec.decode(bytes).unwrap();
            assert_eq!((&part.avatars[0], nums), (want, &vec![want.avatar_num]));
        }
        assert!(FrameDecoder::new().decode(&out[..out.len() - 1]).is_err());
        let mut unknown = out.clone();
        unknown[1] = WEIGHTS_FLAG | 3;
        assert_eq!(
            FrameDecoder::new().decode(&unknown),
            Err(FrameError::Kind(WEIGHTS_FLAG | 3))
        );
    }

    #[test]
    fn placement_rides_in_keyframes_and_in_deltas_that_change_it() {
        let placed = Placement {
            position: Vec3::new(1.0, 0.0, -2.0),
            rotation: Quat::from_rotation_y(0.5),
        };
        let moved = Placement {
            position: Vec3::new(1.5, 0.0, -2.0),
            ..placed
        };
        let mut enc = ChunkEncoder::new();
        let mut dec = FrameDecoder::new();
        let rest = pose(vec![Quat::IDENTITY; 3]);
        let plain = frame(FrameKind::Key, 1, 1, &mut enc, &rest);
        assert_eq!(
            dec.decode(&plain).unwrap().avatars[0].placement,
            Placement::IDENTITY
        );
        let at = |p: Placement| AvatarPose {
            placement: p,
            ..rest.clone()
        };
        let key = frame(FrameKind::Key, 2, 2, &mut enc, &at(placed));
        assert_eq!(key.len(), plain.len() + 28);
        assert_eq!(dec.decode(&key).unwrap().avatars[0].placement, placed);
        // Unchanged since the keyframe: not sent, yet decoded as the keyframe's.
        let same = frame(FrameKind::Delta, 3, 2, &mut enc, &at(placed));
        assert_eq!(dec.decode(&same).unwrap().avatars[0].placement, placed);
        let changed = frame(FrameKind::Delta, 4, 2, &mut enc, &at(moved));
        assert_eq!(changed.len(), same.len() + 28);
        assert_eq!(dec.decode(&changed).unwrap().avatars[0].placement, moved);
        // Back to the keyframe's placement: the next delta says so by omitting it.
        let back = frame(FrameKind::Delta, 5, 2, &mut enc, &at(placed));
        assert_eq!(dec.decode(&back).unwrap().avatars[0].placement, placed);
    }

    proptest! {
        #[test]
        fn key_then_delta_decode_within_the_quantisation_bound(
            key in prop::collection::vec(arb_quat(), 1..70),
            nudges in prop::collection::vec((arb_quat(), f32s(0.0..1.0), 0u8..3), 70),
        ) {
            // Each joint of the delta pose is unchanged, nudged slightly, or arbitrary.
            let delta: Vec<Quat> = key.iter().zip(&nudges).map(|(&k, &(r, t, kind))| match kind {
                0 => k,
                1 => k.slerp(r, t * 1e-3).normalize(),
                _ => r,
            }).collect();
            let mut enc = ChunkEncoder::new();
            let mut dec = FrameDecoder::new();
            let kb = frame(FrameKind::Key, 10, 10, &mut enc, &pose(key.clone()));
            let df = frame(FrameKind::Delta, 11, 10, &mut enc, &pose(delta.clone()));
            let k = dec.decode(&kb).unwrap();
            let d = dec.decode(&df).unwrap();
            prop_assert!(df.len() <= kb.len() + key.len().div_ceil(4));
            for (expected, frame) in [(&key, &k), (&delta, &d)] {
                let got = &frame.avatars[0];
                prop_assert_eq!(got.hash, 0xabcd);
                prop_assert_eq!(&got.translations, &vec![Vec3::new(1.0, 2.0, 3.0)]);
                for (a, b) in expected.iter().zip(&got.rotations) {
                    prop_assert!(quant::angle_between_degrees(*a, *b) <= quant::MAX_ERROR_DEGREES);
                }
            }
        }
    }

    proptest! {
        /// A chunk cut to a joint subset decodes to exactly the subset of the full chunk's
        /// decoded pose, keyframes and deltas alike (the delta against the cut keyframe).
        #[test]
        fn a_selected_chunk_decodes_to_the_selected_part_of_the_full_pose(
            key in prop::collection::vec(arb_quat(), 1..40),
            nudges in prop::collection::vec((arb_quat(), f32s(0.0..1.0), 0u8..3), 40),
            mask in prop::collection::vec(any::<bool>(), 40),
            translated in prop::collection::vec(any::<bool>(), 40),
            placed in any::<bool>(),
        ) {
            let n = key.len();
            let delta: Vec<Quat> = key.iter().zip(&nudges).map(|(&k, &(r, t, kind))| match kind {
                0 => k,
                1 => k.slerp(r, t * 1e-3).normalize(),
                _ => r,
            }).collect();
            let translated: Vec<usize> = (0..n).filter(|&j| translated[j]).collect();
            let with = |rotations: Vec<Quat>, x: f32| AvatarPose {
                translations: translated.iter().map(|&j| Vec3::new(j as f32, x, 0.5)).collect(),
                scales: vec![Vec3::splat(2.0)],
                placement: if placed {
                    Placement { position: Vec3::new(x, 0.0, 1.0), rotation: Quat::from_rotation_y(x) }
                } else {
                    Placement::IDENTITY
                },
                ..pose(rotations)
            };
            let joints: Vec<u16> = (0..n).filter(|&j| mask[j]).map(|j| j as u16).collect();
            let selection = crate::subset::Selection {
                joint_count: n,
                translations: translated.iter().enumerate()
                    .filter(|&(_, &j)| mask[j]).map(|(i, _)| i).collect(),
                scales: if mask[0] { vec![0] } else { vec![] },
                joints,
            };
            let mut enc = ChunkEncoder::new();
            let full_key = frame(FrameKind::Key, 10, 10, &mut enc, &with(key.clone(), 1.0));
            let full_delta = frame(FrameKind::Delta, 11, 10, &mut enc, &with(delta, 2.0));
            let mut full = FrameDecoder::new();
            let mut cut = FrameDecoder::new();
            for (bytes, kind) in [(&full_key, FrameKind::Key), (&full_delta, FrameKind::Delta)] {
                let whole = full.decode(bytes).unwrap();
                let mut selected = bytes[..HEADER_BYTES].to_vec();
                select_chunk(&bytes[HEADER_BYTES..], kind, &selection, &mut selected).unwrap();
                let part = cut.decode(&selected).unwrap();
                let (w, p) = (&whole.avatars[0], &part.avatars[0]);
                let picked: Vec<Quat> = selection.joint_indices().map(|j| w.rotations[j]).collect();
                prop_assert_eq!(&p.rotations, &picked);
                prop_assert_eq!(&p.translations, &crate::subset::Selection::pick(&w.translations, selection.translations.iter().copied()));
                prop_assert_eq!(&p.scales, &crate::subset::Selection::pick(&w.scales, selection.scales.iter().copied()));
                prop_assert_eq!(p.placement, w.placement);
                prop_assert_eq!((p.avatar_num, p.hash), (w.avatar_num, w.hash));
                prop_assert!(selected.len() <= bytes.len());
            }
        }
    }

    #[test]
    fn selecting_from_a_chunk_of_another_rig_or_a_broken_one_is_an_error() {
        let q = vec![Quat::from_rotation_x(0.4); 6];
        let mut enc = ChunkEncoder::new();
        let kb = frame(FrameKind::Key, 1, 1, &mut enc, &pose(q));
        let chunk = &kb[HEADER_BYTES..];
        let of = |joint_count: usize| crate::subset::Selection {
            joint_count,
            joints: vec![0, 2],
            translations: vec![0],
            scales: vec![],
        };
        let mut out = vec![7u8];
        assert_eq!(
            select_chunk(chunk, FrameKind::Key, &of(5), &mut out),
            Err(FrameError::JointCount {
                avatar: 7,
                expected: 5,
                actual: 6
            })
        );
        for len in 0..chunk.len() {
            assert!(select_chunk(&chunk[..len], FrameKind::Key, &of(6), &mut out).is_err());
            assert_eq!(out, vec![7u8], "nothing is left behind on error");
        }
        // A keyframe read as a delta: its first byte is not a valid tag set or runs short.
        let _ = select_chunk(chunk, FrameKind::Delta, &of(6), &mut out);
        select_chunk(chunk, FrameKind::Key, &of(6), &mut out).unwrap();
        assert_eq!(out.len(), 1 + 18 + 2 * 6 + 12);
    }

    #[test]
    fn unchanged_delta_is_tags_only_and_missing_key_is_reported() {
        let q = vec![Quat::from_rotation_y(0.3); 8];
        let mut enc = ChunkEncoder::new();
        let kb = frame(FrameKind::Key, 1, 1, &mut enc, &pose(q.clone()));
        let db = frame(FrameKind::Delta, 2, 1, &mut enc, &pose(q.clone()));
        // header + chunk head (4 + 8 + 6) + 2 tag bytes + one translation
        assert_eq!(db.len(), HEADER_BYTES + 18 + 2 + 12);
        assert_eq!(kb.len(), HEADER_BYTES + 18 + 8 * 6 + 12);
        let mut dec = FrameDecoder::new();
        assert_eq!(
            dec.decode(&db),
            Err(FrameError::MissingKeyframe {
                avatar: 7,
                base_seq: 1
            })
        );
        dec.decode(&kb).unwrap();
        dec.decode(&db).unwrap();
    }

    #[test]
    fn every_truncation_and_trailing_byte_is_an_error_not_a_panic() {
        let q = vec![Quat::from_rotation_x(1.0); 5];
        let mut enc = ChunkEncoder::new();
        let kb = frame(FrameKind::Key, 1, 1, &mut enc, &pose(q));
        for len in 0..kb.len() {
            assert!(
                FrameDecoder::new().decode(&kb[..len]).is_err(),
                "length {len}"
            );
        }
        let mut long = kb.clone();
        long.push(0);
        assert_eq!(
            FrameDecoder::new().decode(&long),
            Err(FrameError::Trailing(1))
        );
    }

    proptest! {
        #[test]
        fn garbage_never_panics(bytes in prop::collection::vec(any::<u8>(), 0..400)) {
            let mut dec = FrameDecoder::new();
            let _ = dec.decode(&bytes);
            let mut framed = vec![MAGIC, 1];
            framed.extend_from_slice(&bytes);
            let _ = dec.decode(&framed);
        }
    }
}
