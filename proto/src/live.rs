//! Live driving: the pose messages a driver sends (see `proto/PROTOCOL.md`, "Live driving").
//!
//! A driver sends poses as JSON text ([`crate::msg::ClientMsg::Pose`], joints by name) or as
//! compact binary websocket messages ([`BinaryPose`], joints by index into the `joints` list
//! of the `drive` answer, rotations smallest-three quantised as in pose frames). Both carry
//! local rotations of the source rig (normalised, as the server streams that rig), an optional
//! root position and an optional driver timestamp — or, for a tracker drive
//! ([`crate::trackers`]), tracker transforms in the scene's space (by index into the `drive`
//! answer's `trackers` in binary).
//!
//! Binary layout, little-endian:
//!
//! ```text
//!  0  u8   magic 0x44 ('D')
//!  1  u8   flags: bit 0 root position present, bit 1 time present, bit 2 morph weights
//!          present, bit 3 trackers present (other bits zero)
//!  2  u16  rotation count N
//!  4  u32  avatar number (the description's `num`)
//!  8  u64  driver time, µs (any epoch; 0 when bit 1 is clear)
//! 16  3×f32 root position (only when bit 0 is set)
//!     N × (u16 joint index, 6 bytes smallest-three rotation)
//!     only when bit 2 is set: u16 weight count M, then M × (u16 morph channel index into the
//!     avatar's `morph_targets`, u16 level 0…1023: weight = level / 1023)
//!     only when bit 3 is set: u8 tracker count K, then K × (u8 tracker index into the `drive`
//!     answer's `trackers`, 3×f32 position in the scene's space (metres), 6 bytes
//!     smallest-three rotation in the scene's space)
//! ```

use crate::quant;
use glam::{Quat, Vec3};

/// First byte of a binary pose message.
pub const MAGIC: u8 = 0x44;
/// Flag: a root position follows the header.
pub const FLAG_ROOT: u8 = 1;
/// Flag: the time field is set.
pub const FLAG_TIME: u8 = 2;
/// Flag: morph weights follow the rotations.
pub const FLAG_WEIGHTS: u8 = 4;
/// Flag: tracker transforms follow the weights (or the rotations when there are none).
pub const FLAG_TRACKERS: u8 = 8;
/// Bytes per tracker entry (tracker index + position + smallest-three rotation).
pub const TRACKER_ENTRY_BYTES: usize = 1 + 12 + quant::BYTES;
/// Bytes per morph weight entry (channel index + level).
pub const WEIGHT_ENTRY_BYTES: usize = 4;
/// Bytes before the optional root position.
pub const HEADER_BYTES: usize = 16;
/// Bytes per rotation entry (joint index + smallest-three).
pub const ENTRY_BYTES: usize = 2 + quant::BYTES;

/// The most poses per second the server accepts from one driver.
pub const MAX_RATE_HZ: f32 = 120.0;

/// Largest root position a live pose may carry, metres from the origin (a typo, not a
/// performer).
pub const MAX_ROOT_METRES: f32 = 10_000.0;

/// The `source` of a `drive` that sends VMC poses: the server's VMC performer rig (Unity's
/// humanoid in its T-pose, normalised, its torso fitted to the avatar), as a `--vmc-in` input
/// drives with. `posecast-client vmc-relay` drives with it. Not an asset name (those cannot
/// hold `@`).
pub const VMC_SOURCE: &str = "@vmc";

/// A binary pose message, decoded.
#[derive(Debug, Clone, PartialEq)]
pub struct BinaryPose {
    /// The avatar's number.
    pub avatar_num: u32,
    /// Driver time, µs, when sent.
    pub time_us: Option<u64>,
    /// The source root's local translation, metres.
    pub root_position: Option<Vec3>,
    /// `(joint index, local rotation)`.
    pub rotations: Vec<(u16, Quat)>,
    /// `(morph channel index, weight level 0…1023)` ([`crate::morph::weight_level`]).
    pub weights: Vec<(u16, u16)>,
    /// `(tracker index, position, rotation)` in the scene's space, for a tracker drive: the
    /// index is into the `drive` answer's `trackers` (at most 255 are sent).
    pub trackers: Vec<(u8, Vec3, Quat)>,
}

/// Why bytes are not a binary pose message.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum PoseDecodeError {
    /// The first byte is not [`MAGIC`].
    #[error("binary message starts with {0:#04x}, not 0x44 (a pose)")]
    Magic(u8),
    /// Unknown flag bits.
    #[error("unknown flag bits {0:#04x}")]
    Flags(u8),
    /// The length does not match the header.
    #[error("binary pose of {actual} bytes; its header needs {expected}")]
    Length {
        /// Bytes the header implies.
        expected: usize,
        /// Bytes received.
        actual: usize,
    },
    /// A morph weight level above [`crate::morph::WEIGHT_LEVELS`].
    #[error("morph weight level {0} is above 1023")]
    WeightLevel(u16),
}

impl BinaryPose {
    /// Encodes the message.
    #[must_use]
    pub fn encode(&self) -> Vec<u8> {
        let mut flags = 0;
        if self.root_position.is_some() {
            flags |= FLAG_ROOT;
        }
        if self.time_us.is_some() {
            flags |= FLAG_TIME;
        }
        if !self.weights.is_empty() {
            flags |= FLAG_WEIGHTS;
        }
        if !self.trackers.is_empty() {
            flags |= FLAG_TRACKERS;
        }
        let count = u16::try_from(self.rotations.len()).unwrap_or(u16::MAX);
        let mut out = Vec::with_capacity(HEADER_BYTES + 12 + usize::from(count) * ENTRY_BYTES);
        out.push(MAGIC);
        out.push(flags);
        out.extend_from_slice(&count.to_le_bytes());
        out.extend_from_slice(&self.avatar_num.to_le_bytes());
        out.extend_from_slice(&self.time_us.unwrap_or(0).to_le_bytes());
        if let Some(p) = self.root_position {
            for c in p.to_array() {
                out.extend_from_slice(&c.to_le_bytes());
            }
        }
        for &(j, q) in self.rotations.iter().take(usize::from(count)) {
            out.extend_from_slice(&j.to_le_bytes());
            quant::write(q, &mut out);
        }
        if !self.weights.is_empty() {
            let m = u16::try_from(self.weights.len()).unwrap_or(u16::MAX);
            out.extend_from_slice(&m.to_le_bytes());
            for &(c, level) in self.weights.iter().take(usize::from(m)) {
                out.extend_from_slice(&c.to_le_bytes());
                out.extend_from_slice(&level.to_le_bytes());
            }
        }
        if !self.trackers.is_empty() {
            let k = u8::try_from(self.trackers.len()).unwrap_or(u8::MAX);
            out.push(k);
            for &(t, p, q) in self.trackers.iter().take(usize::from(k)) {
                out.push(t);
                for c in p.to_array() {
                    out.extend_from_slice(&c.to_le_bytes());
                }
                quant::write(q, &mut out);
            }
        }
        out
    }

    /// Decodes a message.
    ///
    /// # Errors
    /// A wrong magic byte, unknown flags, a length that does not match the header (and the
    /// counts of weights and trackers), or a weight level above 1023.
    pub fn decode(bytes: &[u8]) -> Result<Self, PoseDecodeError> {
        let short = |expected| PoseDecodeError::Length {
            expected,
            actual: bytes.len(),
        };
        let header = bytes.get(..HEADER_BYTES).ok_or(short(HEADER_BYTES))?;
        if header[0] != MAGIC {
            return Err(PoseDecodeError::Magic(header[0]));
        }
        let flags = header[1];
        if flags & !(FLAG_ROOT | FLAG_TIME | FLAG_WEIGHTS | FLAG_TRACKERS) != 0 {
            return Err(PoseDecodeError::Flags(flags));
        }
        let count = usize::from(u16::from_le_bytes([header[2], header[3]]));
        let avatar_num = u32::from_le_bytes([header[4], header[5], header[6], header[7]]);
        let mut time = [0u8; 8];
        time.copy_from_slice(&header[8..16]);
        let root_bytes = if flags & FLAG_ROOT != 0 { 12 } else { 0 };
        let rotations_end = HEADER_BYTES + root_bytes + count * ENTRY_BYTES;
        let weights_count = if flags & FLAG_WEIGHTS != 0 {
            let m = bytes
                .get(rotations_end..rotations_end + 2)
                .ok_or(short(rotations_end + 2))?;
            usize::from(u16::from_le_bytes([m[0], m[1]]))
        } else {
            0
        };
        let weights_end = if flags & FLAG_WEIGHTS != 0 {
            rotations_end + 2 + weights_count * WEIGHT_ENTRY_BYTES
        } else {
            rotations_end
        };
        let expected = if flags & FLAG_TRACKERS != 0 {
            let k = bytes.get(weights_end).ok_or(short(weights_end + 1))?;
            weights_end + 1 + usize::from(*k) * TRACKER_ENTRY_BYTES
        } else {
            weights_end
        };
        if bytes.len() != expected {
            return Err(short(expected));
        }
        let f32_at =
            |i: usize| f32::from_le_bytes([bytes[i], bytes[i + 1], bytes[i + 2], bytes[i + 3]]);
        let root_position = (root_bytes > 0).then(|| {
            Vec3::new(
                f32_at(HEADER_BYTES),
                f32_at(HEADER_BYTES + 4),
                f32_at(HEADER_BYTES + 8),
            )
        });
        let weights = bytes
            .get(rotations_end + 2..weights_end)
            .unwrap_or_default()
            .chunks_exact(WEIGHT_ENTRY_BYTES)
            .map(|e| {
                let level = u16::from_le_bytes([e[2], e[3]]);
                if level > crate::morph::WEIGHT_LEVELS {
                    Err(PoseDecodeError::WeightLevel(level))
                } else {
                    Ok((u16::from_le_bytes([e[0], e[1]]), level))
                }
            })
            .collect::<Result<Vec<_>, _>>()?;
        let rotations = bytes[HEADER_BYTES + root_bytes..rotations_end]
            .chunks_exact(ENTRY_BYTES)
            .map(|e| {
                let mut q = [0u8; quant::BYTES];
                q.copy_from_slice(&e[2..]);
                (u16::from_le_bytes([e[0], e[1]]), quant::read(q))
            })
            .collect();
        let trackers = bytes
            .get(weights_end + 1..)
            .filter(|_| flags & FLAG_TRACKERS != 0)
            .unwrap_or_default()
            .chunks_exact(TRACKER_ENTRY_BYTES)
            .map(|e| {
                let c = |i: usize| f32::from_le_bytes([e[i], e[i + 1], e[i + 2], e[i + 3]]);
                let mut q = [0u8; quant::BYTES];
                q.copy_from_slice(&e[13..]);
                (e[0], Vec3::new(c(1), c(5), c(9)), quant::read(q))
            })
            .collect();
        Ok(Self {
            avatar_num,
            time_us: (flags & FLAG_TIME != 0).then(|| u64::from_le_bytes(time)),
            root_position,
            rotations,
            weights,
            trackers,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn binary_poses_round_trip_within_the_quantisation_bound() {
        let pose = BinaryPose {
            avatar_num: 7,
            time_us: Some(1_234_567),
            root_position: Some(Vec3::new(0.1, 0.9, -2.0)),
            rotations: vec![
                (0, Quat::IDENTITY),
                (3, Quat::from_rotation_x(0.7)),
                (513, Quat::from_euler(glam::EulerRot::XYZ, 0.3, -1.2, 2.0)),
            ],
            weights: Vec::new(),
            trackers: Vec::new(),
        };
        let bytes = pose.encode();
        assert_eq!(bytes.len(), HEADER_BYTES + 12 + 3 * ENTRY_BYTES);
        let back = BinaryPose::decode(&bytes).unwrap();
        assert_eq!(back.avatar_num, 7);
        assert_eq!(back.time_us, Some(1_234_567));
        assert_eq!(back.root_position, pose.root_position);
        for ((j, q), (k, r)) in pose.rotations.iter().zip(&back.rotations) {
            assert_eq!(j, k);
            assert!(quant::angle_between_degrees(*q, *r) <= quant::MAX_ERROR_DEGREES);
        }
    }

    #[test]
    fn malformed_binary_poses_are_refused() {
        let bytes = BinaryPose {
            avatar_num: 1,
            time_us: None,
            root_position: None,
            rotations: vec![(0, Quat::IDENTITY)],
            weights: Vec::new(),
            trackers: Vec::new(),
        }
        .encode();
        assert!(BinaryPose::decode(&bytes).unwrap().time_us.is_none());
        assert!(matches!(
            BinaryPose::decode(&bytes[..bytes.len() - 1]),
            Err(PoseDecodeError::Length { .. })
        ));
        let mut wrong = bytes.clone();
        wrong[0] = 0x50;
        assert_eq!(
            BinaryPose::decode(&wrong),
            Err(PoseDecodeError::Magic(0x50))
        );
        let mut flags = bytes;
        flags[1] = 0x80;
        assert_eq!(
            BinaryPose::decode(&flags),
            Err(PoseDecodeError::Flags(0x80))
        );
        assert!(BinaryPose::decode(&[]).is_err());
    }

    /// Weights (flag bit 2): after the rotations, a count and (channel, level) pairs, exactly
    /// as sent; a level above 1023, a count beyond the bytes and a missing count are refused.
    #[test]
    fn binary_poses_carry_morph_weights() {
        let pose = BinaryPose {
            avatar_num: 3,
            time_us: None,
            root_position: None,
            rotations: vec![(1, Quat::from_rotation_y(0.4))],
            weights: vec![(0, 1023), (4, 512), (2, 0)],
            trackers: Vec::new(),
        };
        let bytes = pose.encode();
        // By hand: 16 header + 8 rotation + 2 count + 3 × 4.
        assert_eq!(bytes.len(), 16 + 8 + 2 + 12);
        assert_eq!(bytes[1], FLAG_WEIGHTS);
        let back = BinaryPose::decode(&bytes).unwrap();
        assert_eq!(back.weights, pose.weights);
        assert_eq!(back.rotations.len(), 1);
        let mut over = bytes.clone();
        let n = over.len();
        over[n - 2..].copy_from_slice(&1024u16.to_le_bytes());
        assert_eq!(
            BinaryPose::decode(&over),
            Err(PoseDecodeError::WeightLevel(1024))
        );
        assert!(matches!(
            BinaryPose::decode(&bytes[..n - 1]),
            Err(PoseDecodeError::Length { .. })
        ));
        assert!(matches!(
            BinaryPose::decode(&bytes[..16 + 8 + 1]),
            Err(PoseDecodeError::Length { .. })
        ));
    }

    /// Trackers (flag bit 3): after the weights (or the rotations), a u8 count and (index,
    /// position, rotation) entries: positions exact, rotations within the quantisation bound;
    /// a truncated block, a count beyond the bytes and bytes beyond the count are refused.
    #[test]
    fn binary_poses_carry_trackers() {
        let trackers = vec![
            (0, Vec3::new(0.1, 1.62, -0.05), Quat::from_rotation_y(0.3)),
            (1, Vec3::new(-0.3, 1.1, 0.25), Quat::from_rotation_x(-1.2)),
            (2, Vec3::new(0.3, 1.05, 0.2), Quat::IDENTITY),
        ];
        for weights in [Vec::new(), vec![(1, 700)]] {
            let pose = BinaryPose {
                avatar_num: 9,
                time_us: Some(77),
                root_position: None,
                rotations: Vec::new(),
                weights: weights.clone(),
                trackers: trackers.clone(),
            };
            let bytes = pose.encode();
            let weight_bytes = if weights.is_empty() { 0 } else { 2 + 4 };
            // By hand: 16 header + weights + 1 count + 3 × (1 + 12 + 6).
            assert_eq!(bytes.len(), 16 + weight_bytes + 1 + 3 * 19);
            assert_eq!(bytes[1] & FLAG_TRACKERS, FLAG_TRACKERS);
            assert_eq!(bytes[16 + weight_bytes], 3);
            let back = BinaryPose::decode(&bytes).unwrap();
            assert_eq!(back.weights, weights);
            assert!(back.rotations.is_empty());
            assert_eq!(back.trackers.len(), 3);
            for ((i, p, q), (j, r, s)) in trackers.iter().zip(&back.trackers) {
                assert_eq!((i, p), (j, r));
                assert!(quant::angle_between_degrees(*q, *s) <= quant::MAX_ERROR_DEGREES);
            }
            let n = bytes.len();
            for cut in [n - 1, n - 19, 16 + weight_bytes] {
                assert!(
                    matches!(
                        BinaryPose::decode(&bytes[..cut]),
                        Err(PoseDecodeError::Length { .. })
                    ),
                    "cut at {cut}"
                );
            }
            let mut longer = bytes.clone();
            longer.push(0);
            assert!(matches!(
                BinaryPose::decode(&longer),
                Err(PoseDecodeError::Length { .. })
            ));
            let mut more = bytes.clone();
            more[16 + weight_bytes] = 4;
            assert_eq!(
                BinaryPose::decode(&more),
                Err(PoseDecodeError::Length {
                    expected: n + 19,
                    actual: n
                })
            );
            // Without the flag the tracker block is bytes too many.
            let mut unflagged = bytes;
            unflagged[1] &= !FLAG_TRACKERS;
            assert!(matches!(
                BinaryPose::decode(&unflagged),
                Err(PoseDecodeError::Length { .. })
            ));
        }
        // Unknown flags are still refused.
        let mut bits = BinaryPose {
            avatar_num: 1,
            time_us: None,
            root_position: None,
            rotations: Vec::new(),
            weights: Vec::new(),
            trackers: trackers[..1].to_vec(),
        }
        .encode();
        bits[1] |= 0x10;
        assert_eq!(
            BinaryPose::decode(&bits),
            Err(PoseDecodeError::Flags(FLAG_TRACKERS | 0x10))
        );
    }
}
