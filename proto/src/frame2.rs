//! Wire v2 binary pose frames: every delta against the previous frame its receiver decoded,
//! with predicted, Rice-coded residuals (protocol version 2; `proto/PROTOCOL.md` has the full
//! layout).
//!
//! Rotations are the same 48-bit smallest-three levels as v1 ([`crate::quant`]), so a v2
//! frame decodes to exactly the rotations a v1 frame of the same tick does. Translations are
//! quantised to [`TRANSLATION_STEP`] (error ≤ [`MAX_TRANSLATION_ERROR`] m). Scales and the
//! placement travel as f32, in a delta only when they changed.
//!
//! ```text
//! header   u8 magic 0x51 ('Q'), u8 kind (1 keyframe, 2 delta),
//!          varints: avatar chunk count, scene number, seq, server time (µs since the epoch),
//!          delta only: seq − base_seq (≥ 1)
//! key chunk    varint avatar number, u64 description hash, varints J, T, S, u8 flags
//!              (bit 0: placement follows), J × 6-byte rotations, T × 3 zigzag-varint
//!              translation levels, S × 3 f32 scales, [placement: 3 f32 position, 4 f32 rotation]
//! delta chunk  varint avatar number, u8 flags (bit 0 placement follows, bit 1 scales follow,
//!              bit 2 escape mask present, bits 4–7 depth − 1), then a bit stream (LSB first,
//!              padded to a byte): [J escape bits], per joint either 2 + 3 × 15 bits in full
//!              (escaped) or 3 Rice-coded residuals, then 3 Rice-coded residuals per
//!              translation; then [S × 3 f32 scales], [placement]
//! ```
//!
//! **Packed deltas** (kind 3, protocol version 7, [`PackedDeltas`]): the header gives
//! `seq − base_seq` and then the time as `zigzag(time − the base frame's time)`
//! ([`FrameClock`]), and every chunk goes into one bit stream padded once: its avatar number
//! (1 bit when it is the previous chunk's + 1, else 5 bits `n − 1` and `n` bits), a head (1 bit
//! for depth 8 without flags, else 0, 3 bits depth − 1 and the 4 flag bits), the same bits as a
//! kind 2 chunk's stream, the scales and placement as 32-bit floats, and the weights' bits.
//!
//! **Prediction.** A delta chunk of depth `d` refers to the receiver's last `d` decoded frames
//! of the avatar, newest first: `h₀` (at `base_seq`), `h₁`, … For each component (a rotation
//! level of a joint whose dropped component is the same in `h₀…`, or a translation level), the
//! history values `h₀…hₙ₋₁` (`n ≤ d`; for rotations only the leading frames with `h₀`'s dropped
//! component count) give still residuals `sᵢ = hᵢ − hᵢ₊₁` and velocity residuals
//! `vᵢ = hᵢ − 2hᵢ₊₁ + hᵢ₊₂`. With `n ≥ 3` and `mean zigzag(v) < mean zigzag(s)` the prediction is
//! `2h₀ − h₁` (constant velocity), otherwise `h₀`; the Rice parameter is
//! `k = ⌊log₂(m + 1)⌋` of the chosen mean `m` (integer division), [`K_WITHOUT_HISTORY`] when
//! `n = 1`. A kind 5 delta predicts over the ticks from its newest named frame instead
//! ([`Spacing::predict`]). Rotation predictions are clamped to the level range.
//! The encoder and the decoder compute this from the same decoded levels, so nothing about it
//! is sent, and a frame's state is a function of the frames it refers to alone (any receiver
//! holding them decodes it).
//!
//! **Residuals.** `u = zigzag(level − prediction)`; Rice code of parameter `k`: `q = u >> k`
//! one-bits, a zero, then the low `k` bits of `u`; when `q ≥` [`RICE_ESCAPE`]: that many
//! one-bits, then 6 bits `n − 1` and the `n`-bit value of `u` (`n` its bit length).
//!
//! **Escape.** A joint whose dropped component differs from `h₀`'s is sent in full; the chunk
//! then carries one escape bit per joint.
//!
//! **Grids** (protocol versions 5 and 6, [`crate::precision`]). A keyframe chunk with flag 16
//! carries grid steps and its levels are grid values; with flag 32 as well (version 6) each
//! joint also has a near-axis step, and each rotation's bit 47 (its *tier*) says which of the
//! two grids it is on. A rotation's dropped component and tier form its *tag*: its history runs
//! while the tag is `h₀`'s, and a joint whose tag changed goes escaped: on such a grid a bit
//! follows its escape, 1 when only its tier changed (its residuals then follow, predicted from
//! its history put on the new grid), 0 before its 48 bits; 47 bits otherwise.

use crate::frame::{AvatarPose, Frame, FrameHeader, FrameKind};
use crate::placement::Placement;
use crate::precision::{self, Steps};
use crate::quant;
use glam::{Quat, Vec3};
use std::collections::{HashMap, VecDeque};
use std::sync::Arc;

/// First byte of every v2 frame (v1's is [`crate::frame::MAGIC`]).
pub const MAGIC: u8 = 0x51;
/// Most frames a delta chunk may refer to (its depth).
pub const MAX_DEPTH: usize = 8;
pub use crate::precision::TRANSLATION_STEP;
/// Bound on a translation's error after quantisation, metres (half a step), for
/// |x| < 2³¹ · [`TRANSLATION_STEP`] (262,144 m; larger values are clamped).
pub const MAX_TRANSLATION_ERROR: f64 = TRANSLATION_STEP / 2.0;
/// Rice parameter of a component with no history beyond the base.
pub const K_WITHOUT_HISTORY: u32 = 5;
/// Unary quotient at which a residual is written raw.
pub const RICE_ESCAPE: u64 = 20;
/// Most joints, translations or scales a chunk may declare (a bound on what a decoder
/// allocates from a few bytes).
pub const MAX_COUNT: usize = 1 << 16;

const FLAG_PLACEMENT: u8 = 1;
const FLAG_SCALES: u8 = 2;
const FLAG_ESCAPES: u8 = 4;
/// Chunk flag (key and delta, protocol version 4): morph weights follow the placement.
const FLAG_WEIGHTS: u8 = 8;
/// Keyframe chunk flag (protocol version 5): the grid steps follow the flags byte
/// ([`crate::precision`]); the chunk's levels and the deltas after it are on that grid.
const FLAG_STEPS: u8 = 16;
/// Keyframe chunk flag (protocol version 6, with [`FLAG_STEPS`]): each joint's near-axis step
/// follows the steps ([`Steps::near`]); rotations carry a tier bit, escaped joints 48 bits.
const FLAG_NEAR: u8 = 32;
/// Frame kind byte of a packed delta (protocol version 7): every chunk in one bit stream, the
/// time a difference from the base frame's.
const KIND_PACKED: u8 = 3;
/// Frame kind byte of a delta naming the frames it refers to, predicted a frame at a time
/// (protocol version 8, over datagrams): [`write_referenced_header`].
const KIND_REFERENCED: u8 = 4;
/// Frame kind byte of a delta naming the frames it refers to, predicted over the ticks between
/// them (protocol version 9): [`ReferencedKind::Ticks`].
const KIND_SPACED: u8 = 5;

/// How a delta naming the frames it refers to (over datagrams) predicts.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum ReferencedKind {
    /// Kind 4 (protocol version 8): as a delta of kind 2, as if its frame were a tick after
    /// the newest it names.
    Frames,
    /// Kind 5 (protocol version 9): over the ticks from the frames it names to its frame
    /// ([`Spacing::of`]).
    #[default]
    Ticks,
}

impl ReferencedKind {
    /// The kind a receiver speaking protocol `version` reads (5 from version 9, else 4).
    pub fn for_version(version: u32) -> Self {
        if version >= 9 {
            Self::Ticks
        } else {
            Self::Frames
        }
    }

    /// How a delta of this kind at tick `seq` naming `refs` predicts: over its [`Spacing`]
    /// (kind 5), or a frame at a time as a delta of kind 2 (`None`: kind 4).
    pub fn spacing(self, seq: u64, refs: &[u64]) -> Option<Spacing> {
        match self {
            Self::Frames => None,
            Self::Ticks => Some(Spacing::of(seq, refs)),
        }
    }

    fn byte(self) -> u8 {
        match self {
            Self::Frames => KIND_REFERENCED,
            Self::Ticks => KIND_SPACED,
        }
    }
}
/// Bits of a streamed morph weight level ([`crate::morph::WEIGHT_LEVELS`] = 2¹⁰ − 1).
pub const WEIGHT_BITS: u32 = 10;
const LEVEL_MAX: i64 = (1 << 15) - 2;
const LEVEL_MASK: u64 = (1 << 15) - 1;

/// Why a v2 frame could not be decoded (or encoded as asked).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum Frame2Error {
    /// Ran out of bytes.
    #[error("frame truncated at byte {at}")]
    Truncated {
        /// Offset where data ran out.
        at: usize,
    },
    /// Not a v2 frame.
    #[error("bad magic byte {0:#04x} (a v2 frame starts with 0x51)")]
    Magic(u8),
    /// Unknown frame kind.
    #[error("unknown frame kind {0}")]
    Kind(u8),
    /// A varint longer than 10 bytes or a number too large for its field.
    #[error("number out of range at byte {at}")]
    Number {
        /// Offset of the number.
        at: usize,
    },
    /// A count above [`MAX_COUNT`].
    #[error("avatar {avatar}: {count} items exceed the limit of {MAX_COUNT}")]
    Count {
        /// The avatar.
        avatar: u32,
        /// The declared count.
        count: u64,
    },
    /// Bytes left over after the last chunk.
    #[error("{0} trailing bytes after the last avatar chunk")]
    Trailing(usize),
    /// A delta of seq gap 0 or larger than seq.
    #[error("delta base gap {gap} invalid for seq {seq}")]
    BaseGap {
        /// The frame's seq.
        seq: u64,
        /// The gap read.
        gap: u64,
    },
    /// A delta whose base frame is not this decoder's newest of the avatar, or that refers to
    /// more frames than it holds. Wait for the next keyframe.
    #[error(
        "avatar {avatar}: delta against frame {base_seq} (depth {depth}), which this decoder does not hold"
    )]
    MissingBase {
        /// The avatar.
        avatar: u32,
        /// The frame the delta needs.
        base_seq: u64,
        /// Frames it refers to.
        depth: usize,
    },
    /// A packed delta (protocol version 7) whose base frame is not the last frame the reader
    /// took of its scene: its time (a difference from the base frame's) cannot be read. Wait
    /// for the next keyframe.
    #[error(
        "scene {scene}: packed delta against frame {base_seq}, which this reader does not hold"
    )]
    BaseTime {
        /// The scene.
        scene: u32,
        /// The frame the delta needs.
        base_seq: u64,
    },
    /// A delta chunk of depth 0 or a reserved flag bit set.
    #[error("avatar {avatar}: invalid chunk flags {flags:#04x}")]
    Flags {
        /// The avatar.
        avatar: u32,
        /// The flags byte.
        flags: u8,
    },
    /// The same avatar twice in one frame.
    #[error("avatar {0} appears twice in one frame")]
    Duplicate(u32),
}

/// One avatar's pose as levels: what v2 codes losslessly.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct QuantPose {
    /// Smallest-three bits of each joint's rotation ([`quant::encode`]).
    pub rotations: Vec<u64>,
    /// Translation levels, units of [`TRANSLATION_STEP`].
    pub translations: Vec<[i32; 3]>,
    /// Scales, as sent (f32).
    pub scales: Vec<Vec3>,
    /// World placement.
    pub placement: Placement,
    /// Morph weight levels, one per channel ([`crate::morph::weight_level`]); empty for a rig
    /// without morph targets, or a receiver that does not take them.
    pub weights: Vec<u16>,
    /// The grid these levels are on ([`crate::precision`]): `None`, the finest (rotation
    /// levels as [`quant::encode`] gives them, translations in [`TRANSLATION_STEP`]s); else
    /// grid values of these steps, which [`QuantPose::to_pose`] turns back into levels.
    pub steps: Option<Arc<Steps>>,
}

/// The level of a translation component: `round(x / TRANSLATION_STEP)`, clamped to i32;
/// non-finite values give 0.
#[must_use]
pub fn translation_level(x: f32) -> i32 {
    if !x.is_finite() {
        return 0;
    }
    (f64::from(x) / TRANSLATION_STEP)
        .round()
        .clamp(f64::from(i32::MIN), f64::from(i32::MAX)) as i32
}

/// The translation component a level stands for (`level · TRANSLATION_STEP`).
#[must_use]
pub fn translation_value(level: i32) -> f32 {
    (f64::from(level) * TRANSLATION_STEP) as f32
}

impl QuantPose {
    /// Quantises a pose.
    #[must_use]
    pub fn from_pose(pose: &AvatarPose) -> Self {
        Self::from_pose_with(pose, None)
    }

    /// Quantises a pose whose rotations were already quantised ([`quant::encode`] of each, in
    /// order: e.g. by the v1 [`crate::frame::ChunkEncoder`]); `None`, or bits of another
    /// length, quantises them here.
    #[must_use]
    pub fn from_pose_with(pose: &AvatarPose, rotation_bits: Option<&[u64]>) -> Self {
        let rotations = match rotation_bits {
            Some(bits) if bits.len() == pose.rotations.len() => bits.to_vec(),
            _ => pose.rotations.iter().map(|&q| quant::encode(q)).collect(),
        };
        Self {
            rotations,
            translations: pose
                .translations
                .iter()
                .map(|t| t.to_array().map(translation_level))
                .collect(),
            scales: pose.scales.clone(),
            placement: pose.placement,
            weights: pose
                .weights
                .iter()
                .map(|&w| crate::morph::weight_level(w))
                .collect(),
            steps: None,
        }
    }

    /// The same levels on the grid of `steps` (one rotation step per joint of this pose),
    /// or unchanged when every step is 1. Levels already on a grid are returned as they are.
    #[must_use]
    pub fn coarsen(&self, steps: &Arc<Steps>) -> Self {
        if self.steps.is_some() || steps.is_finest() {
            return self.clone();
        }
        let rotations = self
            .rotations
            .iter()
            .enumerate()
            .map(|(j, &bits)| {
                let levels = [0, 1, 2].map(|c| level(bits, c));
                let m = steps.rotations.get(j).copied().unwrap_or(1);
                // A rotation near an axis goes on its joint's near grid when that is coarser
                // (tier bit 47 set).
                let (m, tier) = match steps.near.get(j) {
                    Some(&near) if near != m && precision::near_axis(levels) => (near, 1u64 << 47),
                    _ => (m, 0),
                };
                let mut out = (bits & (3u64 << 45)) | tier;
                for (c, l) in levels.into_iter().enumerate() {
                    let l = precision::coarse_rotation_level(l, m);
                    out |= (l as u64) << (15 * (2 - c));
                }
                out
            })
            .collect();
        let translations = self
            .translations
            .iter()
            .map(|t| t.map(|l| precision::coarse_translation_level(l, steps.translation)))
            .collect();
        Self {
            rotations,
            translations,
            steps: Some(steps.clone()),
            ..self.clone()
        }
    }

    /// Joint `j`'s rotation bits on the finest grid (as [`quant::encode`] gives them).
    #[must_use]
    pub fn fine_rotation(&self, j: usize) -> u64 {
        let bits = self.rotations[j];
        let Some(steps) = self.steps.as_ref() else {
            return bits;
        };
        let m = steps.rotation_step(j, bits);
        let bits = bits & !(1u64 << 47);
        if m == 1 {
            return bits;
        }
        let mut out = bits & !((1u64 << 45) - 1);
        for c in 0..3 {
            let l = precision::fine_rotation_level(level(bits, c), m);
            out |= (l as u64) << (15 * (2 - c));
        }
        out
    }

    /// Translation `t`'s levels on the finest grid (see [`QuantPose::fine_rotation`]).
    #[must_use]
    pub fn fine_translation(&self, t: usize) -> [i32; 3] {
        let l = self.translations[t];
        match &self.steps {
            Some(s) if s.translation != 1 => {
                l.map(|c| precision::fine_translation_level(c, s.translation))
            }
            _ => l,
        }
    }

    /// The pose these levels stand for.
    #[must_use]
    pub fn to_pose(&self, avatar_num: u32, hash: u64) -> AvatarPose {
        AvatarPose {
            avatar_num,
            hash,
            rotations: (0..self.rotations.len())
                .map(|j| quant::decode(self.fine_rotation(j)))
                .collect(),
            translations: (0..self.translations.len())
                .map(|t| Vec3::from_array(self.fine_translation(t).map(translation_value)))
                .collect(),
            scales: self.scales.clone(),
            placement: self.placement,
            weights: self
                .weights
                .iter()
                .map(|&l| crate::morph::weight_value(l))
                .collect(),
        }
    }

    /// The same levels without morph weights (for a receiver of protocol version 2 or 3).
    #[must_use]
    pub fn without_weights(&self) -> Self {
        Self {
            weights: Vec::new(),
            ..self.clone()
        }
    }

    /// The levels of the joints `selection` names: their rotations, and of the streamed
    /// translations and scales the selected ones, in order (what a frame cut to a joint
    /// subset carries; `proto/PROTOCOL.md`, "Joint subsets"). Indices the pose lacks are
    /// skipped (the counts then differ from the selection's and a decoder refuses the pose).
    #[must_use]
    pub fn select(&self, selection: &crate::subset::Selection) -> Self {
        Self {
            rotations: crate::subset::Selection::pick(&self.rotations, selection.joint_indices()),
            translations: crate::subset::Selection::pick(
                &self.translations,
                selection.translations.iter().copied(),
            ),
            scales: crate::subset::Selection::pick(&self.scales, selection.scales.iter().copied()),
            placement: self.placement,
            weights: self.weights.clone(),
            steps: self.steps.as_ref().map(|s| {
                Arc::new(Steps {
                    rotations: crate::subset::Selection::pick(
                        &s.rotations,
                        selection.joint_indices(),
                    ),
                    translation: s.translation,
                    near: if s.tiered() {
                        crate::subset::Selection::pick(&s.near, selection.joint_indices())
                    } else {
                        Vec::new()
                    },
                })
            }),
        }
    }

    fn same_shape(&self, other: &Self) -> bool {
        self.rotations.len() == other.rotations.len()
            && self.translations.len() == other.translations.len()
            && self.scales.len() == other.scales.len()
            && self.weights.len() == other.weights.len()
            && self.steps == other.steps
    }
}

/// Writes a v2 frame header. `base_seq` is ignored for a keyframe.
pub fn write_header(header: &FrameHeader, avatar_count: usize, out: &mut Vec<u8>) {
    out.push(MAGIC);
    out.push(match header.kind {
        FrameKind::Key => 1,
        FrameKind::Delta => 2,
    });
    varint(avatar_count as u64, out);
    varint(u64::from(header.scene_num), out);
    varint(header.seq, out);
    varint(header.server_time_us, out);
    if header.kind == FrameKind::Delta {
        varint(header.seq.saturating_sub(header.base_seq), out);
    }
}

/// Writes the header of a delta that names the frames it refers to (kind 4, protocol version
/// 8: frames sent as datagrams, any of which may be lost): `header` as a kind 2 delta's, with
/// its `base_seq` the first of `refs`, then the number of `refs` and each one's distance from
/// `seq`. `refs` are the ticks of frames the receiver acknowledged, newest first (at most
/// [`MAX_DEPTH`], each older than `seq` and than the one before it); a chunk of depth `d`
/// refers to the first `d`, wherever they are among the frames the receiver holds.
///
/// # Panics
/// `refs` is empty, longer than [`MAX_DEPTH`], or not strictly decreasing below `seq`.
pub fn write_referenced_header(
    header: &FrameHeader,
    kind: ReferencedKind,
    refs: &[u64],
    avatar_count: usize,
    out: &mut Vec<u8>,
) {
    assert!(
        !refs.is_empty()
            && refs.len() <= MAX_DEPTH
            && refs[0] < header.seq
            && refs.windows(2).all(|w| w[1] < w[0]),
        "references {refs:?} of frame {}",
        header.seq
    );
    out.push(MAGIC);
    out.push(kind.byte());
    varint(avatar_count as u64, out);
    varint(u64::from(header.scene_num), out);
    varint(header.seq, out);
    varint(header.server_time_us, out);
    varint(refs.len() as u64, out);
    for r in refs {
        varint(header.seq - r, out);
    }
}

fn varint(mut v: u64, out: &mut Vec<u8>) {
    while v >= 0x80 {
        out.push((v as u8) | 0x80);
        v >>= 7;
    }
    out.push(v as u8);
}

fn zigzag(r: i64) -> u64 {
    ((r << 1) ^ (r >> 63)) as u64
}

fn unzigzag(u: u64) -> i64 {
    ((u >> 1) as i64) ^ -((u & 1) as i64)
}

/// Appends a keyframe chunk of `pose`.
pub fn encode_key(avatar_num: u32, hash: u64, pose: &QuantPose, out: &mut Vec<u8>) {
    varint(u64::from(avatar_num), out);
    out.extend_from_slice(&hash.to_le_bytes());
    varint(pose.rotations.len() as u64, out);
    varint(pose.translations.len() as u64, out);
    varint(pose.scales.len() as u64, out);
    let placement = !pose.placement.is_identity();
    let weights = !pose.weights.is_empty();
    let mut flags = 0;
    if placement {
        flags |= FLAG_PLACEMENT;
    }
    if weights {
        flags |= FLAG_WEIGHTS;
    }
    let steps = pose.steps.as_ref().filter(|s| !s.is_finest());
    if steps.is_some() {
        flags |= FLAG_STEPS;
    }
    if steps.is_some_and(|s| s.tiered()) {
        flags |= FLAG_NEAR;
    }
    out.push(flags);
    if let Some(steps) = steps {
        varint(u64::from(steps.translation), out);
        out.extend((0..pose.rotations.len()).map(|j| steps.rotations.get(j).copied().unwrap_or(1)));
        if steps.tiered() {
            out.extend((0..pose.rotations.len()).map(|j| steps.near.get(j).copied().unwrap_or(1)));
        }
    }
    for bits in &pose.rotations {
        out.extend_from_slice(&bits.to_le_bytes()[..quant::BYTES]);
    }
    for t in &pose.translations {
        for c in t {
            varint(zigzag(i64::from(*c)), out);
        }
    }
    write_scales_placement(pose, true, placement, out);
    if weights {
        varint(pose.weights.len() as u64, out);
        let mut w = BitWriter::new(out);
        for &l in &pose.weights {
            w.put(u64::from(l), WEIGHT_BITS);
        }
        w.finish();
    }
}

fn write_scales_placement(pose: &QuantPose, scales: bool, placement: bool, out: &mut Vec<u8>) {
    for c in scale_placement_floats(pose, scales, placement) {
        out.extend_from_slice(&c.to_le_bytes());
    }
}

/// The floats a chunk sends after its levels, in order: every scale's x, y, z when `scales`,
/// then the placement's position and rotation (x, y, z, w) when `placement`.
fn scale_placement_floats(
    pose: &QuantPose,
    scales: bool,
    placement: bool,
) -> impl Iterator<Item = f32> + '_ {
    let p = &pose.placement;
    let scales = pose.scales.iter().filter(move |_| scales);
    let placement = placement.then(|| {
        p.position
            .to_array()
            .into_iter()
            .chain(p.rotation.to_array())
    });
    scales
        .flat_map(|s| s.to_array())
        .chain(placement.into_iter().flatten())
}

/// Appends a delta chunk of `pose` against `history` (the receiver's last decoded frames of
/// the avatar, newest first; at most [`MAX_DEPTH`] are used), in a frame of kind 2 (each
/// chunk byte-aligned). Returns `false`, writing nothing, when there is no history or the
/// newest differs in its joint, translation or scale counts (send a keyframe then).
pub fn encode_delta(
    avatar_num: u32,
    pose: &QuantPose,
    history: &[&QuantPose],
    out: &mut Vec<u8>,
) -> bool {
    delta_chunk(avatar_num, pose, history, None, out)
}

/// [`encode_delta`] of a chunk predicted over `spacing` (kind 5), or a frame at a time.
fn delta_chunk(
    avatar_num: u32,
    pose: &QuantPose,
    history: &[&QuantPose],
    spacing: Option<Spacing>,
    out: &mut Vec<u8>,
) -> bool {
    let Some(plan) = DeltaPlan::of(pose, history) else {
        return false;
    };
    varint(u64::from(avatar_num), out);
    out.push(plan.flags());
    let mut w = BitWriter::new(out);
    delta_body(&mut w, pose, &plan, &history[..plan.depth], spacing);
    w.finish();
    write_scales_placement(pose, plan.scales, plan.placement, out);
    if plan.weights {
        let mut w = BitWriter::new(out);
        changed_weights(&mut w, pose, history[0]);
        w.finish();
    }
    true
}

/// Appends a delta chunk of `pose` against `history` (the frames the header names, newest
/// first) in a frame of kind 4: its length in bytes (a varint), then the chunk as in a frame of
/// kind 2 — so a sender can cut the frame by avatar without decoding it
/// ([`split_by_avatar`]). `spacing` is [`ReferencedKind::spacing`] of the header's kind, tick
/// and references: predicted over the ticks between the frames (kind 5), or a frame at a time
/// (kind 4). Returns `false`, writing nothing, as [`encode_delta`] does.
pub fn encode_referenced_delta(
    avatar_num: u32,
    pose: &QuantPose,
    history: &[&QuantPose],
    spacing: Option<Spacing>,
    out: &mut Vec<u8>,
) -> bool {
    let mut chunk = Vec::with_capacity(16 + 4 * pose.rotations.len());
    if !delta_chunk(avatar_num, pose, history, spacing, &mut chunk) {
        return false;
    }
    varint(chunk.len() as u64, out);
    out.extend_from_slice(&chunk);
    true
}

/// A part of a frame cut by avatar ([`split_by_avatar`]): its bytes, and the avatars it holds.
pub type Part = (Vec<u8>, Vec<u32>);

/// Most avatars in one part of a frame cut by avatar ([`split_by_avatar`]): an
/// acknowledgement names at most this many ([`crate::quic::MAX_ACKED_AVATARS`]).
pub const MAX_PART_AVATARS: usize = 256;

/// A keyframe (kind 1) or a delta of kind 4 cut by avatar into frames of at most `max` bytes
/// and [`MAX_PART_AVATARS`] avatars (as few as it takes, each with the same header but for its
/// chunk count, each decodable alone), with the avatar numbers each holds. A frame that fits
/// is one part. An avatar's chunk too large for `max` with the header is a part of its own,
/// larger than `max`.
///
/// # Errors
/// Malformed bytes, or a frame of another kind (2 or 3: their chunks cannot be told apart
/// without the frames they refer to).
pub fn split_by_avatar(frame: &[u8], max: usize) -> Result<Vec<Part>, Frame2Error> {
    let mut r = Reader {
        bytes: frame,
        at: 0,
    };
    let (header, count, layout) = FrameClock::default().header(&mut r)?;
    let referenced = match (header.kind, layout) {
        (FrameKind::Key, _) => None,
        (FrameKind::Delta, Layout::Referenced(refs)) => Some(refs),
        (FrameKind::Delta, _) => return Err(Frame2Error::Kind(frame[1])),
    };
    // Each chunk's bytes (with a kind 4 chunk's length) and avatar number.
    let mut chunks: Vec<(&[u8], u32)> = Vec::with_capacity(count.min(frame.len()));
    for _ in 0..count {
        let start = r.at;
        let avatar = match referenced {
            None => key_chunk(&mut r)?.avatar_num,
            Some(_) => {
                let len =
                    usize::try_from(r.varint()?).map_err(|_| Frame2Error::Number { at: start })?;
                let chunk = r.take(len)?;
                Reader {
                    bytes: chunk,
                    at: 0,
                }
                .varint_u32()?
            }
        };
        chunks.push((&frame[start..r.at], avatar));
    }
    if r.at != frame.len() {
        return Err(Frame2Error::Trailing(frame.len() - r.at));
    }
    let write_header = |n: usize, out: &mut Vec<u8>| match referenced {
        None => self::write_header(&header, n, out),
        Some(refs) => write_referenced_header(&header, refs.kind, refs.as_slice(), n, out),
    };
    let mut whole = Vec::new();
    write_header(count, &mut whole);
    let header_len = whole.len();
    if frame.len() <= max && chunks.len() <= MAX_PART_AVATARS {
        return Ok(vec![(frame.to_vec(), chunks.iter().map(|c| c.1).collect())]);
    }
    let mut parts = Vec::new();
    let mut i = 0;
    while i < chunks.len() {
        let mut bytes = header_len + 2;
        let mut n = 0;
        while i + n < chunks.len()
            && n < MAX_PART_AVATARS
            && (n == 0 || bytes + chunks[i + n].0.len() <= max)
        {
            bytes += chunks[i + n].0.len();
            n += 1;
        }
        let mut out = Vec::with_capacity(bytes);
        write_header(n, &mut out);
        let mut avatars = Vec::with_capacity(n);
        for (chunk, avatar) in &chunks[i..i + n] {
            out.extend_from_slice(chunk);
            avatars.push(*avatar);
        }
        parts.push((out, avatars));
        i += n;
    }
    Ok(parts)
}

/// Writes the header of a packed delta (kind 3, protocol version 7) of `avatar_count` chunks:
/// `header`'s time as a difference from `base_time_us`, its base frame's.
pub fn write_packed_header(
    header: &FrameHeader,
    base_time_us: u64,
    avatar_count: usize,
    out: &mut Vec<u8>,
) {
    out.push(MAGIC);
    out.push(KIND_PACKED);
    varint(avatar_count as u64, out);
    varint(u64::from(header.scene_num), out);
    varint(header.seq, out);
    varint(header.seq.saturating_sub(header.base_seq), out);
    varint(
        zigzag(header.server_time_us.wrapping_sub(base_time_us) as i64),
        out,
    );
}

/// Writes a packed delta frame (kind 3, protocol version 7): the header, then every avatar's
/// chunk in one bit stream. Made by [`PackedDeltas::new`], filled by [`PackedDeltas::push`],
/// ended by [`PackedDeltas::finish`].
#[derive(Debug)]
pub struct PackedDeltas<'a> {
    w: BitWriter<'a>,
    /// The previous chunk's avatar number.
    prev: Option<u32>,
}

impl<'a> PackedDeltas<'a> {
    /// Starts a packed delta frame of `avatar_count` chunks in `out`: `header` is the frame's
    /// (a delta) and `base_time_us` the server time of its base frame (`header.base_seq`), from
    /// which its own time is sent as a difference.
    pub fn new(
        header: &FrameHeader,
        base_time_us: u64,
        avatar_count: usize,
        out: &'a mut Vec<u8>,
    ) -> Self {
        write_packed_header(header, base_time_us, avatar_count, out);
        Self {
            w: BitWriter::new(out),
            prev: None,
        }
    }

    /// Appends avatar `avatar_num`'s chunk: `pose` against `history` (as [`encode_delta`]).
    /// Returns `false`, writing nothing, when it cannot be coded against `history`.
    pub fn push(&mut self, avatar_num: u32, pose: &QuantPose, history: &[&QuantPose]) -> bool {
        let Some(plan) = DeltaPlan::of(pose, history) else {
            return false;
        };
        let w = &mut self.w;
        match self.prev {
            Some(p) if p.checked_add(1) == Some(avatar_num) => w.put(1, 1),
            prev => {
                if prev.is_some() {
                    w.put(0, 1);
                }
                let n = (32 - avatar_num.leading_zeros()).max(1);
                w.put(u64::from(n - 1), 5);
                w.put(u64::from(avatar_num), n);
            }
        }
        self.prev = Some(avatar_num);
        let flags = plan.flags();
        if plan.depth == MAX_DEPTH && flags & 0x0f == 0 {
            w.put(1, 1);
        } else {
            w.put(0, 1);
            w.put(u64::from(flags >> 4), 3);
            w.put(u64::from(flags & 0x0f), 4);
        }
        delta_body(w, pose, &plan, &history[..plan.depth], None);
        for c in scale_placement_floats(pose, plan.scales, plan.placement) {
            w.put(u64::from(c.to_bits()), 32);
        }
        if plan.weights {
            changed_weights(w, pose, history[0]);
        }
        true
    }

    /// Ends the frame: the bits waiting, padded with zeros to a whole byte.
    pub fn finish(self) {
        self.w.finish();
    }
}

/// What a delta chunk of a pose against its history holds: its depth and what changed.
struct DeltaPlan {
    depth: usize,
    escapes: bool,
    scales: bool,
    placement: bool,
    weights: bool,
}

impl DeltaPlan {
    /// `None` when there is no history or the newest differs in shape.
    fn of(pose: &QuantPose, history: &[&QuantPose]) -> Option<Self> {
        let base = history.first()?;
        if !pose.same_shape(base) {
            return None;
        }
        // Older frames of another shape cannot be predicted from: the depth stops before them.
        let depth = history
            .iter()
            .take(MAX_DEPTH)
            .take_while(|h| h.same_shape(base))
            .count();
        Some(Self {
            depth,
            escapes: pose
                .rotations
                .iter()
                .zip(&base.rotations)
                .any(|(a, b)| tag(*a) != tag(*b)),
            scales: pose.scales != base.scales,
            placement: pose.placement != base.placement,
            // Compared element by element: equal slices of `u16` compile to a call of
            // `memcmp`, whose cost showed in the tick's profile although most rigs have no
            // weights.
            weights: pose.weights.len() != base.weights.len()
                || pose.weights.iter().zip(&base.weights).any(|(a, b)| a != b),
        })
    }

    /// The chunk's flags byte: what changed in the low bits, depth − 1 in bits 4–6.
    fn flags(&self) -> u8 {
        let mut flags = ((self.depth - 1) as u8) << 4;
        for (set, bit) in [
            (self.placement, FLAG_PLACEMENT),
            (self.scales, FLAG_SCALES),
            (self.escapes, FLAG_ESCAPES),
            (self.weights, FLAG_WEIGHTS),
        ] {
            if set {
                flags |= bit;
            }
        }
        flags
    }
}

/// A weight change mask over the channels, then the new level of each changed one.
fn changed_weights(w: &mut BitWriter<'_>, pose: &QuantPose, base: &QuantPose) {
    for (a, b) in pose.weights.iter().zip(&base.weights) {
        w.put(u64::from(a != b), 1);
    }
    for (a, b) in pose.weights.iter().zip(&base.weights) {
        if a != b {
            w.put(u64::from(*a), WEIGHT_BITS);
        }
    }
}

/// A delta chunk's bits: the escape mask, each joint's residuals (or full bits) and each
/// translation's residuals, against `history` (already cut to the plan's depth).
fn delta_body(
    w: &mut BitWriter<'_>,
    pose: &QuantPose,
    plan: &DeltaPlan,
    history: &[&QuantPose],
    spacing: Option<Spacing>,
) {
    let depth = plan.depth;
    let base = history[0];
    let full = full_bits(pose);
    let tiered = pose.steps.as_deref().filter(|s| s.tiered());
    if plan.escapes {
        for (a, b) in pose.rotations.iter().zip(&base.rotations) {
            w.put(u64::from(tag(*a) != tag(*b)), 1);
        }
    }
    let mut h = [0i64; MAX_DEPTH];
    let frames: [&[u64]; MAX_DEPTH] =
        std::array::from_fn(|f| history.get(f).map_or(&[][..], |h| &h.rotations[..]));
    for (block, (now, was)) in pose
        .rotations
        .chunks(LANES)
        .zip(base.rotations.chunks(LANES))
        .enumerate()
    {
        let p = predict_rotations(&frames[..depth], block * LANES, spacing);
        for (l, (&bits, &base_bits)) in now.iter().zip(was).enumerate() {
            if tag(bits) != tag(base_bits) {
                // On a tiered grid a joint that only changed tier is coded against its history
                // put on its new grid (bit 1); anything else goes in full (bit 0, 48 bits).
                if let Some(steps) = tiered
                    && index(bits) == index(base_bits)
                {
                    w.put(1, 1);
                    for c in 0..3 {
                        let (pred, k) =
                            regridded(&frames[..depth], block * LANES + l, bits, steps, c, spacing);
                        w.rice(zigzag(level(bits, c) - pred), k);
                    }
                    continue;
                }
                if tiered.is_some() {
                    w.put(0, 1);
                }
                w.put(bits & ((1 << full) - 1), full);
                continue;
            }
            for c in 0..3 {
                w.rice(zigzag(level(bits, c) - i64::from(p.pred[c][l])), p.k[c][l]);
            }
        }
    }
    for (t, now) in pose.translations.iter().enumerate() {
        for (c, &value) in now.iter().enumerate() {
            for (slot, f) in h.iter_mut().zip(history) {
                *slot = i64::from(f.translations[t][c]);
            }
            let (pred, k) = predict(&h[..depth], false, spacing);
            w.rice(zigzag(i64::from(value) - pred), k);
        }
    }
}

/// A rotation's dropped component (bits 45–46) and grid tier (bit 47, protocol version 6):
/// a joint's history runs while its tag is the newest frame's; a change goes escaped.
fn tag(bits: u64) -> u64 {
    (bits >> 45) & 7
}

/// A rotation's dropped component (bits 45–46).
fn index(bits: u64) -> u64 {
    (bits >> 45) & 3
}

/// The prediction and Rice parameter of component `c` of joint `j` whose rotation `now` changed
/// tier since the newest frame (its dropped component the same): [`predict`] over the leading
/// frames whose dropped component is the newest's, each level put on the grid of `now`'s tier
/// (`coarse(fine(l, its step), the new step)`).
fn regridded(
    frames: &[&[u64]],
    j: usize,
    now: u64,
    steps: &Steps,
    c: usize,
    spacing: Option<Spacing>,
) -> (i64, u32) {
    let to = steps.rotation_step(j, now);
    let dropped = index(frames[0][j]);
    let mut h = [0i64; MAX_DEPTH];
    let mut n = 0;
    for (slot, f) in h.iter_mut().zip(frames) {
        let bits = f[j];
        if index(bits) != dropped {
            break;
        }
        let fine = precision::fine_rotation_level(level(bits, c), steps.rotation_step(j, bits));
        *slot = precision::coarse_rotation_level(fine, to);
        n += 1;
    }
    predict(&h[..n], true, spacing)
}

/// Bits of an escaped joint: 47 (tier, then dropped component and levels: 48) when the
/// avatar's grid has near-axis steps.
fn full_bits(pose: &QuantPose) -> u32 {
    if pose.steps.as_ref().is_some_and(|s| s.tiered()) {
        48
    } else {
        47
    }
}

fn level(bits: u64, c: usize) -> i64 {
    ((bits >> (15 * (2 - c))) & LEVEL_MASK) as i64
}

/// The prediction and Rice parameter of a component from its history `h` (newest first, at
/// least one value); see the module docs.
fn predict(h: &[i64], rotation: bool, spacing: Option<Spacing>) -> (i64, u32) {
    if let Some(spacing) = spacing {
        return spacing.predict(h, rotation);
    }
    let n = h.len();
    if n < 2 {
        return (h[0], K_WITHOUT_HISTORY);
    }
    // Levels are 15-bit rotation components or i32 translations, so no residual's zigzag
    // reaches 2⁴⁰ (the cap the JavaScript decoder applies to stay exact): none is capped.
    let still: u64 = (0..n - 1).map(|i| zigzag(h[i] - h[i + 1])).sum();
    let velocity: u64 = (0..n.saturating_sub(2))
        .map(|i| zigzag(h[i] - 2 * h[i + 1] + h[i + 2]))
        .sum();
    let (pred, mean) = if n >= 3 && velocity * (n as u64 - 1) < still * (n as u64 - 2) {
        (2 * h[0] - h[1], div_small(velocity, n as u64 - 2))
    } else {
        (h[0], div_small(still, n as u64 - 1))
    };
    let pred = if rotation {
        pred.clamp(0, LEVEL_MAX)
    } else {
        pred
    };
    (pred, (mean + 1).ilog2())
}

/// Joints whose rotations [`predict_rotations`] predicts at once.
const LANES: usize = 8;

/// What [`predict_rotations`] gives for a block of [`LANES`] joints, `[component][lane]`.
struct RotationPredictions {
    /// The predicted levels (clamped to the level range).
    pred: [[i32; LANES]; 3],
    /// The Rice parameters.
    k: [[u32; LANES]; 3],
}

/// [`predict`] of the three rotation components of joints `j0 … j0 + LANES − 1` (lanes past
/// the joint count are zero), from `frames` (the history's rotations, newest first, 1…
/// [`MAX_DEPTH`] of them, each of the same length). A joint's history runs while its dropped
/// component is `frames[0]`'s; lanes of a joint sent escaped are meaningless.
///
/// The same predictions and parameters as [`predict`], in 32-bit lanes laid out
/// `[component][frame][joint]`: each sum runs over every frame and masks off the frames past
/// a joint's history, so the loops have fixed lengths and no branches and compile to vector
/// operations across joints. The choice `mean zigzag(v) < mean zigzag(s)` is tested as
/// `Σv · (n − 1) < Σs · (n − 2)`, in f32 (exact: both products are below 2²⁴), which is false
/// by itself for `n < 3` (the right side is ≤ 0); the parameter is [`rice_parameter`].
#[inline]
fn predict_rotations(
    frames: &[&[u64]],
    j0: usize,
    spacing: Option<Spacing>,
) -> RotationPredictions {
    // The joints' levels (per component and frame) and dropped components (per frame), split
    // from each rotation's two 32-bit halves (index in bits 13–14 of the high half, level 0 across both).
    let mut h = [[[0i32; LANES]; MAX_DEPTH]; 3];
    let mut dropped = [[0i32; LANES]; MAX_DEPTH];
    for (f, (dropped, src)) in dropped.iter_mut().zip(frames).enumerate() {
        let src = src.get(j0..).unwrap_or_default();
        let row = match src.first_chunk::<LANES>() {
            Some(full) => *full,
            None => {
                let mut row = [0u64; LANES];
                for (slot, &b) in row.iter_mut().zip(src) {
                    *slot = b;
                }
                row
            }
        };
        for l in 0..LANES {
            let (lo, hi) = (row[l] as u32, (row[l] >> 32) as u32);
            h[0][f][l] = ((lo >> 30) | ((hi & 0x1fff) << 2)) as i32;
            h[1][f][l] = ((lo >> 15) & 0x7fff) as i32;
            h[2][f][l] = (lo & 0x7fff) as i32;
            dropped[l] = ((hi >> 13) & 7) as i32;
        }
    }
    // Per frame −1 while the joint's history runs (its dropped component that of frame 0, in
    // every frame from 0 to this one, and the frame within the depth), else 0.
    let mut keep = [[0i32; LANES]; MAX_DEPTH];
    let mut run = [-1i32; LANES];
    for (f, kept) in keep.iter_mut().enumerate().take(frames.len()) {
        for l in 0..LANES {
            run[l] &= -i32::from(dropped[f][l] == dropped[0][l]);
        }
        *kept = run;
    }
    let mut n = [0i32; LANES];
    for kept in &keep {
        for l in 0..LANES {
            n[l] -= kept[l];
        }
    }
    // Levels are 0…32767: residuals fit i32 and their zigzags are non-negative.
    let zz = |r: i32| (r << 1) ^ (r >> 31);
    let mut out = RotationPredictions {
        pred: [[0; LANES]; 3],
        k: [[0; LANES]; 3],
    };
    for ((h, pred_out), k_out) in h.iter().zip(&mut out.pred).zip(&mut out.k) {
        // Still residuals `hᵢ − hᵢ₊₁`, and velocity residuals as differences of two of them.
        let mut diff = [[0i32; LANES]; MAX_DEPTH - 1];
        for (i, d) in diff.iter_mut().enumerate() {
            for l in 0..LANES {
                d[l] = h[i][l] - h[i + 1][l];
            }
        }
        let mut still = [0i32; LANES];
        for i in 0..MAX_DEPTH - 1 {
            for l in 0..LANES {
                still[l] += zz(diff[i][l]) & keep[i + 1][l];
            }
        }
        let mut velocity = [0i32; LANES];
        for i in 0..MAX_DEPTH - 2 {
            for l in 0..LANES {
                velocity[l] += zz(diff[i][l] - diff[i + 1][l]) & keep[i + 2][l];
            }
        }
        // Per lane, without branches (so as vector operations): masks of −1 or 0 select.
        if let Some(spacing) = spacing {
            // A kind 5 delta: over the ticks between the frames (scalar: only datagram
            // receivers pay for it).
            for l in 0..LANES {
                let n = n[l].max(1) as usize;
                let mut hl = [0i64; MAX_DEPTH];
                for (f, slot) in hl.iter_mut().enumerate().take(n) {
                    *slot = i64::from(h[f][l]);
                }
                let (p, k) = spacing.predict(&hl[..n], true);
                pred_out[l] = p as i32;
                k_out[l] = k;
            }
            continue;
        }
        for l in 0..LANES {
            let nf = n[l] as f32;
            let moving =
                -i32::from((velocity[l] as f32) * (nf - 1.0) < (still[l] as f32) * (nf - 2.0));
            let based = -i32::from(n[l] < 2);
            let (h0, h1) = (h[0][l], h[1][l]);
            let pred = (h0 + (moving & (h0 - h1))).clamp(0, LEVEL_MAX as i32);
            pred_out[l] = (based & h0) | (!based & pred);
            let sum = still[l] ^ ((still[l] ^ velocity[l]) & moving);
            let k = rice_parameter(sum, n[l] - 1 + moving) as i32;
            k_out[l] = ((based & K_WITHOUT_HISTORY as i32) | (!based & k)) as u32;
        }
    }
    out
}

/// How far apart in ticks a kind 5 delta's frame and the two newest frames it names are
/// (protocol version 9), and how it predicts over them ([`Spacing::predict`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Spacing {
    /// Ticks from the newest named frame to the frame, 1 … [`MAX_SPACING`].
    ahead: i64,
    /// Ticks between the two newest named frames, 1 … [`MAX_SPACING`].
    apart: i64,
}

/// The most ticks a [`Spacing`] counts: gaps beyond it count as this many.
pub const MAX_SPACING: u64 = 255;

impl Spacing {
    /// The spacing of a kind 5 delta of tick `seq` naming `refs` (newest first): `ahead` is
    /// `seq − refs[0]`, `apart` is `refs[0] − refs[1]` (`ahead` when it names one frame), each
    /// clamped to 1 … [`MAX_SPACING`].
    pub fn of(seq: u64, refs: &[u64]) -> Self {
        let clamp = |d: u64| d.clamp(1, MAX_SPACING) as i64;
        let ahead = clamp(seq.saturating_sub(refs.first().copied().unwrap_or(seq)));
        let apart = match refs {
            [a, b, ..] => clamp(a.saturating_sub(*b)),
            _ => ahead,
        };
        Spacing { ahead, apart }
    }

    /// The prediction and Rice parameter of a component of a kind 5 chunk from its history
    /// `h` (newest first, at least one value), `g = ahead / apart` history steps past `h₀`.
    ///
    /// With `dᵢ = hᵢ − hᵢ₊₁`, the history's residuals of holding still (`dᵢ`), of constant
    /// velocity (`dᵢ − dᵢ₊₁`, from 3 values) and of constant acceleration
    /// (`dᵢ − 2dᵢ₊₁ + dᵢ₊₂`, from 4) are one step's errors of each model; over `g` steps they
    /// grow by `g`, `g(g + 1)/2` and `g(g + 1)(g + 2)/6`. Each model's expected error is the
    /// mean zigzag of its residuals times its growth, in f64 and in this order:
    /// `(Σ / count) · (a / b)`, `(Σ / count) · (a(a + b) / (2b²))`,
    /// `(Σ / count) · (a(a + b)(a + 2b) / (6b³))` (`a` ahead, `b` apart; each product of
    /// integers exact). The least wins, the simpler on a tie. It predicts `h₀`,
    /// `h₀ + ⌊(2·d₀·a + b) / (2b)⌋` or `h₀ + ⌊(2·d₀·a·b + (d₀ − d₁)·a·(a + b) + b²) / (2b²)⌋`
    /// (the motion carried over `g` steps, rounded half up), rotations clamped to the level
    /// range; the Rice parameter is `min(⌊log₂(⌊e⌋ + 1)⌋, 32)` of the winner's expected
    /// error `e`; with one value, `h₀` and [`K_WITHOUT_HISTORY`].
    pub fn predict(self, h: &[i64], rotation: bool) -> (i64, u32) {
        let n = h.len();
        if n < 2 {
            return (h[0], K_WITHOUT_HISTORY);
        }
        let (a, b) = (self.ahead, self.apart);
        let d = |i: usize| h[i] - h[i + 1];
        let still: u64 = (0..n - 1).map(|i| zigzag(d(i))).sum();
        let velocity: u64 = (0..n.saturating_sub(2))
            .map(|i| zigzag(d(i) - d(i + 1)))
            .sum();
        let acceleration: u64 = (0..n.saturating_sub(3))
            .map(|i| zigzag(d(i) - 2 * d(i + 1) + d(i + 2)))
            .sum();
        let (af, bf) = (a as f64, b as f64);
        let mut best = (0, (still as f64 / (n - 1) as f64) * (af / bf));
        if n >= 3 {
            let e = (velocity as f64 / (n - 2) as f64) * (af * (af + bf) / (2.0 * bf * bf));
            if e < best.1 {
                best = (1, e);
            }
        }
        if n >= 4 {
            let e = (acceleration as f64 / (n - 3) as f64)
                * (af * (af + bf) * (af + 2.0 * bf) / (6.0 * bf * bf * bf));
            if e < best.1 {
                best = (2, e);
            }
        }
        let d0 = d(0);
        let pred = match best.0 {
            0 => h[0],
            1 => h[0] + (2 * d0 * a + b).div_euclid(2 * b),
            _ => {
                let d2 = d0 - d(1);
                h[0] + (2 * d0 * a * b + d2 * a * (a + b) + b * b).div_euclid(2 * b * b)
            }
        };
        let pred = if rotation {
            pred.clamp(0, LEVEL_MAX)
        } else {
            pred
        };
        // `as` floors the error (saturating far above 2³², where the parameter stops anyway).
        (pred, ((best.1 as u64) + 1).ilog2().min(32))
    }
}

/// `⌊log₂(⌊sum / d⌋ + 1)⌋` for `0 ≤ sum < 2²¹` and `1 ≤ d <` [`MAX_DEPTH`] (a rotation
/// component's sums; other `d` give any value), in f32: the exponent of `(sum + d) / d`.
/// `⌊sum / d⌋ + 1 ≥ 2ᵐ` exactly when `(sum + d) / d ≥ 2ᵐ`, and a quotient below a power of two
/// is below it by at least `1/d ≥ 1/7`, more than f32's rounding error up to 2²¹ (`1/16`), so
/// the rounded quotient has the exponent of the exact one. Vector operations, without an
/// integer division, a float-to-integer conversion or a bit scan per lane.
#[inline]
fn rice_parameter(sum: i32, d: i32) -> u32 {
    ((((sum + d) as f32 / d as f32).to_bits() >> 23) & 0xff).wrapping_sub(127)
}

/// `x / d` for a divisor below [`MAX_DEPTH`]: each arm divides by a constant, which compiles
/// to a multiplication (the same quotient, without a slow 64-bit division per component).
fn div_small(x: u64, d: u64) -> u64 {
    match d {
        1 => x,
        2 => x / 2,
        3 => x / 3,
        4 => x / 4,
        5 => x / 5,
        6 => x / 6,
        7 => x / 7,
        _ => x / d.max(1),
    }
}

#[derive(Debug)]
struct BitWriter<'a> {
    out: &'a mut Vec<u8>,
    acc: u64,
    bits: u32,
}

impl<'a> BitWriter<'a> {
    fn new(out: &'a mut Vec<u8>) -> Self {
        Self {
            out,
            acc: 0,
            bits: 0,
        }
    }

    /// Appends the low `n` bits of `v` (`n ≤ 32`).
    #[inline]
    fn put(&mut self, v: u64, n: u32) {
        if n > 32 {
            self.put(v, 32);
            self.put(v >> 32, n - 32);
            return;
        }
        let v = if n == 0 {
            0
        } else {
            v & (u64::MAX >> (64 - n))
        };
        // Whole 32-bit words out at once (little-endian: the stream's first bit is the
        // lowest of its first byte); at most 31 bits wait in the accumulator.
        self.acc |= v << self.bits;
        self.bits += n;
        if self.bits >= 32 {
            self.out.extend_from_slice(&(self.acc as u32).to_le_bytes());
            self.acc >>= 32;
            self.bits -= 32;
        }
    }

    /// Appends the Rice code of `u` with parameter `k` (module docs, "Residuals").
    #[inline]
    fn rice(&mut self, u: u64, k: u32) {
        let q = u >> k;
        if q < RICE_ESCAPE && q as u32 + 1 + k <= 32 {
            // The unary quotient, its zero and the low `k` bits as one value below 2^len
            // (the same bits as writing them one after the other), straight into the
            // accumulator: the common case, small enough to inline where residuals are coded.
            let low = u & ((1u64 << k) - 1);
            self.acc |= (((1u64 << q) - 1) | (low << (q + 1))) << self.bits;
            self.bits += q as u32 + 1 + k;
            if self.bits >= 32 {
                self.out.extend_from_slice(&(self.acc as u32).to_le_bytes());
                self.acc >>= 32;
                self.bits -= 32;
            }
        } else {
            self.rice_long(u, k);
        }
    }

    /// [`BitWriter::rice`] of a code longer than 32 bits or escaped.
    #[cold]
    #[inline(never)]
    fn rice_long(&mut self, u: u64, k: u32) {
        let q = u >> k;
        if q < RICE_ESCAPE {
            let low = u & ((1u64 << k) - 1);
            let len = q as u32 + 1 + k;
            let code = ((1u64 << q) - 1) | (low << (q + 1));
            self.put(code, 32);
            self.put(code >> 32, len - 32);
        } else {
            self.put((1 << RICE_ESCAPE) - 1, RICE_ESCAPE as u32);
            let n = (64 - u.leading_zeros()).max(1);
            self.put(u64::from(n - 1), 6);
            self.put(u, n);
        }
    }

    /// Writes the bits waiting, padded with zeros to a whole byte.
    fn finish(self) {
        let bytes = self.bits.div_ceil(8) as usize;
        self.out.extend_from_slice(&self.acc.to_le_bytes()[..bytes]);
    }
}

struct Reader<'a> {
    bytes: &'a [u8],
    at: usize,
}

impl<'a> Reader<'a> {
    fn take(&mut self, n: usize) -> Result<&'a [u8], Frame2Error> {
        let end = self
            .at
            .checked_add(n)
            .filter(|&e| e <= self.bytes.len())
            .ok_or(Frame2Error::Truncated { at: self.at })?;
        let s = &self.bytes[self.at..end];
        self.at = end;
        Ok(s)
    }
    fn u8(&mut self) -> Result<u8, Frame2Error> {
        Ok(self.take(1)?[0])
    }
    fn u64(&mut self) -> Result<u64, Frame2Error> {
        let mut a = [0u8; 8];
        a.copy_from_slice(self.take(8)?);
        Ok(u64::from_le_bytes(a))
    }
    fn f32(&mut self) -> Result<f32, Frame2Error> {
        let mut a = [0u8; 4];
        a.copy_from_slice(self.take(4)?);
        Ok(f32::from_le_bytes(a))
    }
    fn vec3(&mut self) -> Result<Vec3, Frame2Error> {
        Ok(Vec3::new(self.f32()?, self.f32()?, self.f32()?))
    }
    fn varint(&mut self) -> Result<u64, Frame2Error> {
        let start = self.at;
        let mut v = 0u64;
        for shift in (0..70).step_by(7) {
            let b = self.u8()?;
            let part = u64::from(b & 0x7f);
            if shift == 63 && part > 1 {
                break;
            }
            v |= part << shift;
            if b & 0x80 == 0 {
                return Ok(v);
            }
        }
        Err(Frame2Error::Number { at: start })
    }
    fn varint_u32(&mut self) -> Result<u32, Frame2Error> {
        let at = self.at;
        u32::try_from(self.varint()?).map_err(|_| Frame2Error::Number { at })
    }
    fn count(&mut self, avatar: u32) -> Result<usize, Frame2Error> {
        let count = self.varint()?;
        match usize::try_from(count) {
            Ok(n) if n <= MAX_COUNT => Ok(n),
            _ => Err(Frame2Error::Count { avatar, count }),
        }
    }
    fn placement(&mut self) -> Result<Placement, Frame2Error> {
        let position = self.vec3()?;
        let q = [self.f32()?, self.f32()?, self.f32()?, self.f32()?];
        Ok(Placement {
            position,
            rotation: Quat::from_array(q),
        })
    }
}

struct BitReader<'r, 'a> {
    r: &'r mut Reader<'a>,
    acc: u64,
    bits: u32,
}

impl BitReader<'_, '_> {
    fn get(&mut self, n: u32) -> Result<u64, Frame2Error> {
        if n > 32 {
            let low = self.get(32)?;
            return Ok(low | self.get(n - 32)? << 32);
        }
        while self.bits < n {
            self.acc |= u64::from(self.r.u8()?) << self.bits;
            self.bits += 8;
        }
        let v = if n == 0 {
            0
        } else {
            self.acc & (u64::MAX >> (64 - n))
        };
        self.acc = if n == 64 { 0 } else { self.acc >> n };
        self.bits -= n;
        Ok(v)
    }

    fn rice(&mut self, k: u32) -> Result<u64, Frame2Error> {
        let mut q = 0;
        while q < RICE_ESCAPE && self.get(1)? == 1 {
            q += 1;
        }
        if q < RICE_ESCAPE {
            return Ok(q << k | self.get(k)?);
        }
        let n = self.get(6)? as u32 + 1;
        self.get(n)
    }
}

/// One avatar of a decoded v2 frame, as levels.
#[derive(Debug, Clone, PartialEq)]
pub struct DecodedAvatar {
    /// The avatar's number.
    pub avatar_num: u32,
    /// Its description hash (a delta's is its base's).
    pub hash: u64,
    /// Its pose as levels.
    pub levels: Arc<QuantPose>,
}

/// A decoded v2 frame, as levels.
#[derive(Debug, Clone, PartialEq)]
pub struct LevelFrame {
    /// Its header (`base_seq == seq` for a keyframe).
    pub header: FrameHeader,
    /// One entry per avatar chunk.
    pub avatars: Vec<DecodedAvatar>,
}

impl LevelFrame {
    /// The frame as poses (rotations and translations from their levels).
    #[must_use]
    pub fn to_frame(&self) -> Frame {
        Frame {
            header: self.header,
            avatars: self
                .avatars
                .iter()
                .map(|a| a.levels.to_pose(a.avatar_num, a.hash))
                .collect(),
        }
    }
}

#[derive(Debug, Default)]
struct AvatarHistory {
    hash: u64,
    /// Newest first: (seq, levels).
    frames: VecDeque<(u64, Arc<QuantPose>)>,
}

/// Decodes v2 frames, keeping each (scene, avatar)'s last [`MAX_DEPTH`] decoded frames
/// ([`DATAGRAM_RETENTION`] for [`Frame2Decoder::for_datagrams`]).
#[derive(Debug, Default)]
pub struct Frame2Decoder {
    history: HashMap<(u32, u32), AvatarHistory>,
    clock: FrameClock,
    /// Frames come as datagrams ([`Frame2Decoder::for_datagrams`]).
    datagrams: bool,
}

/// How recent the frames a kind 4 delta names are: of the sender's last this many ticks.
pub const DATAGRAM_REFERENCE_TICKS: u64 = 6 * MAX_DEPTH as u64;

/// Frames a receiver of datagrams keeps per avatar ([`Frame2Decoder::for_datagrams`]): every
/// frame a kind 4 delta may name ([`DATAGRAM_REFERENCE_TICKS`], one frame a tick at most) and
/// [`MAX_DEPTH`] × 2 more, of older ticks that came late, out of order.
pub const DATAGRAM_RETENTION: usize = DATAGRAM_REFERENCE_TICKS as usize + 2 * MAX_DEPTH;

/// Reads a v2 frame's header and chunk count, for a keyframe or a delta of kind 2. A packed
/// delta (kind 3) gives its time as a difference from its base frame's: read it with a
/// [`FrameClock`] that saw the frames before it.
///
/// # Errors
/// Truncated, bad magic, unknown kind, a bad number; [`Frame2Error::BaseTime`] for a packed
/// delta.
pub fn read_header(bytes: &[u8]) -> Result<(FrameHeader, usize), Frame2Error> {
    FrameClock::default().read(bytes)
}

/// The server time of each scene's last frame a reader took, from which a packed delta's
/// (protocol version 7) is read. A reader of headers alone (a load generator) keeps one; a
/// [`Frame2Decoder`] keeps its own.
#[derive(Debug, Default, Clone)]
pub struct FrameClock {
    /// (seq, server time) of the last frame recorded, by scene number.
    last: HashMap<u32, (u64, u64)>,
}

impl FrameClock {
    /// Reads a v2 frame's header and chunk count, a packed delta's time from its base
    /// frame's (which must be the scene's last frame recorded). Records nothing.
    ///
    /// # Errors
    /// As [`read_header`]; [`Frame2Error::BaseTime`] for a packed delta whose base frame is
    /// not the last one recorded of its scene.
    pub fn read(&self, bytes: &[u8]) -> Result<(FrameHeader, usize), Frame2Error> {
        let mut r = Reader { bytes, at: 0 };
        self.header(&mut r).map(|(h, count, _)| (h, count))
    }

    /// As [`FrameClock::read`], but a packed delta whose base frame is not the last one
    /// recorded is read too, with `server_time_us` 0: the header and whether its time is
    /// known (a reader counting frames it cannot time, such as a load generator joining a
    /// broadcast between keyframes).
    ///
    /// # Errors
    /// As [`read_header`], except [`Frame2Error::BaseTime`].
    pub fn read_untimed(&self, bytes: &[u8]) -> Result<(FrameHeader, usize, bool), Frame2Error> {
        match self.read(bytes) {
            Ok((header, count)) => Ok((header, count, true)),
            Err(Frame2Error::BaseTime { scene, base_seq }) => {
                // Read it against a clock that holds its base frame at time 0.
                let mut clock = Self::default();
                clock.last.insert(scene, (base_seq, 0));
                let (mut header, count) = clock.read(bytes)?;
                header.server_time_us = 0;
                Ok((header, count, false))
            }
            Err(e) => Err(e),
        }
    }

    /// Takes `header` (of a frame read whole) as its scene's last frame.
    pub fn record(&mut self, header: &FrameHeader) {
        self.last
            .insert(header.scene_num, (header.seq, header.server_time_us));
    }

    /// The server time of frame `seq` of scene `scene_num`, when it is the last one recorded.
    #[must_use]
    pub fn time_of(&self, scene_num: u32, seq: u64) -> Option<u64> {
        self.last
            .get(&scene_num)
            .filter(|(s, _)| *s == seq)
            .map(|(_, t)| *t)
    }

    /// Forgets a scene's frames.
    pub fn forget(&mut self, scene_num: u32) {
        self.last.remove(&scene_num);
    }

    /// The header, the chunk count, and how the chunks are laid out.
    fn header(&self, r: &mut Reader<'_>) -> Result<(FrameHeader, usize, Layout), Frame2Error> {
        let magic = r.u8()?;
        if magic != MAGIC {
            return Err(Frame2Error::Magic(magic));
        }
        let (kind, mut layout) = match r.u8()? {
            1 => (FrameKind::Key, Layout::Chunks),
            2 => (FrameKind::Delta, Layout::Chunks),
            KIND_PACKED => (FrameKind::Delta, Layout::Packed),
            KIND_REFERENCED => (
                FrameKind::Delta,
                Layout::Referenced(Refs {
                    kind: ReferencedKind::Frames,
                    ..Refs::default()
                }),
            ),
            KIND_SPACED => (FrameKind::Delta, Layout::Referenced(Refs::default())),
            k => return Err(Frame2Error::Kind(k)),
        };
        let packed = layout == Layout::Packed;
        let at = r.at;
        let count = usize::try_from(r.varint()?).map_err(|_| Frame2Error::Number { at })?;
        let scene_num = r.varint_u32()?;
        let seq = r.varint()?;
        let server_time_us = if packed { 0 } else { r.varint()? };
        let mut header = FrameHeader {
            kind,
            scene_num,
            seq,
            server_time_us,
            base_seq: seq,
        };
        if let Layout::Referenced(refs) = &mut layout {
            let at = r.at;
            let n = r.varint()?;
            if n == 0 || n > MAX_DEPTH as u64 {
                return Err(Frame2Error::Number { at });
            }
            let mut last_gap = 0;
            for slot in refs.ticks.iter_mut().take(n as usize) {
                let gap = r.varint()?;
                if gap <= last_gap || gap > seq {
                    return Err(Frame2Error::BaseGap { seq, gap });
                }
                last_gap = gap;
                *slot = seq - gap;
            }
            refs.len = n as usize;
            header.base_seq = refs.ticks[0];
        } else if kind == FrameKind::Delta {
            let gap = r.varint()?;
            if gap == 0 || gap > seq {
                return Err(Frame2Error::BaseGap { seq, gap });
            }
            header.base_seq = seq - gap;
        }
        if packed {
            let since = unzigzag(r.varint()?);
            let base_seq = header.base_seq;
            match self.last.get(&scene_num) {
                Some(&(last, time)) if last == base_seq => {
                    header.server_time_us = time.wrapping_add(since as u64);
                }
                _ => {
                    return Err(Frame2Error::BaseTime {
                        scene: scene_num,
                        base_seq,
                    });
                }
            }
        }
        Ok((header, count, layout))
    }
}

/// How a frame's chunks are laid out, from its kind.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Layout {
    /// Each chunk byte-aligned (kinds 1 and 2): a delta chunk refers to the receiver's newest
    /// frames of the avatar, the first of them its `base_seq`.
    Chunks,
    /// Every chunk in one bit stream (kind 3).
    Packed,
    /// Byte-aligned delta chunks referring to the frames the header names (kind 4).
    Referenced(Refs),
}

/// The ticks a kind 4 or 5 delta refers to, newest first, and its kind.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
struct Refs {
    ticks: [u64; MAX_DEPTH],
    len: usize,
    kind: ReferencedKind,
}

impl Refs {
    fn as_slice(&self) -> &[u64] {
        &self.ticks[..self.len]
    }
}

impl Frame2Decoder {
    /// A decoder holding nothing.
    #[must_use]
    pub fn new() -> Self {
        Self::default()
    }

    /// A decoder of frames that come as datagrams (protocol version 8 over WebTransport), any
    /// of which may be lost or come out of order. Its deltas are of kind 4, naming the frames
    /// they refer to, so it keeps each avatar's last [`DATAGRAM_RETENTION`] frames in the
    /// order they came, and a keyframe of the rig it holds does not drop the frames before it
    /// (a keyframe that comes late must not drop the newer frames a delta names).
    #[must_use]
    pub fn for_datagrams() -> Self {
        Self {
            datagrams: true,
            ..Self::default()
        }
    }

    /// Decodes one v2 frame into poses. On error nothing is changed.
    ///
    /// # Errors
    /// Malformed bytes, or a delta whose base this decoder does not hold.
    pub fn decode(&mut self, bytes: &[u8]) -> Result<Frame, Frame2Error> {
        Ok(self.decode_levels(bytes)?.to_frame())
    }

    /// Decodes one v2 frame into levels, remembering it for the deltas after it. On error
    /// nothing is changed.
    ///
    /// # Errors
    /// Malformed bytes, or a delta whose base this decoder does not hold.
    pub fn decode_levels(&mut self, bytes: &[u8]) -> Result<LevelFrame, Frame2Error> {
        let mut r = Reader { bytes, at: 0 };
        let (header, count, layout) = self.clock.header(&mut r)?;
        let refs = match &layout {
            Layout::Referenced(refs) => Some(refs),
            _ => None,
        };
        let mut avatars: Vec<DecodedAvatar> = Vec::with_capacity(count.min(bytes.len() / 2));
        let mut push = |a: DecodedAvatar| {
            if avatars.iter().any(|b| b.avatar_num == a.avatar_num) {
                return Err(Frame2Error::Duplicate(a.avatar_num));
            }
            avatars.push(a);
            Ok(())
        };
        if layout == Layout::Packed {
            let mut b = BitReader {
                r: &mut r,
                acc: 0,
                bits: 0,
            };
            let mut prev = None;
            for _ in 0..count {
                let a = self.packed_chunk(&mut b, &header, prev)?;
                prev = Some(a.avatar_num);
                push(a)?;
            }
        } else {
            for _ in 0..count {
                push(match (header.kind, refs) {
                    (FrameKind::Key, _) => key_chunk(&mut r)?,
                    (FrameKind::Delta, None) => self.delta_chunk(&mut r, &header, None)?,
                    (FrameKind::Delta, Some(refs)) => {
                        // Its length, then a chunk of exactly that many bytes.
                        let at = r.at;
                        let len =
                            usize::try_from(r.varint()?).map_err(|_| Frame2Error::Number { at })?;
                        let base = r.at;
                        r.take(len)?;
                        // Read within its bytes, at their offsets in the frame.
                        let mut chunk = Reader {
                            bytes: &bytes[..r.at],
                            at: base,
                        };
                        let a = self.delta_chunk(&mut chunk, &header, Some(refs))?;
                        if chunk.at != r.at {
                            return Err(Frame2Error::Trailing(r.at - chunk.at));
                        }
                        a
                    }
                })?;
            }
        }
        if r.at != bytes.len() {
            return Err(Frame2Error::Trailing(bytes.len() - r.at));
        }
        let retained = if self.datagrams {
            DATAGRAM_RETENTION
        } else {
            MAX_DEPTH
        };
        for a in &avatars {
            let h = self
                .history
                .entry((header.scene_num, a.avatar_num))
                .or_default();
            let new_rig = h.frames.is_empty() || h.hash != a.hash;
            if header.kind == FrameKind::Key && (new_rig || !self.datagrams) {
                h.frames.clear();
                h.hash = a.hash;
            }
            // In the order frames came: a kind 4 delta finds the frames it names by tick
            // (the newest that came of each, should a new source of frames count its ticks
            // again), and those are among the last `retained` that came.
            h.frames.push_front((header.seq, a.levels.clone()));
            h.frames.truncate(retained);
        }
        self.clock.record(&header);
        Ok(LevelFrame { header, avatars })
    }

    /// Forgets a scene's frames (the client left it).
    pub fn forget_scene(&mut self, scene_num: u32) {
        self.history.retain(|(s, _), _| *s != scene_num);
        self.clock.forget(scene_num);
    }

    /// Forgets one avatar's frames (it left the scene), so a long-lived decoder holds only
    /// avatars still there.
    pub fn forget_avatar(&mut self, scene_num: u32, avatar_num: u32) {
        self.history.remove(&(scene_num, avatar_num));
    }

    /// A delta chunk of a frame of kind 2, 4 or 5 (byte-aligned; `refs`: the frames a kind 4
    /// or 5 delta names).
    fn delta_chunk(
        &self,
        r: &mut Reader<'_>,
        header: &FrameHeader,
        refs: Option<&Refs>,
    ) -> Result<DecodedAvatar, Frame2Error> {
        let avatar = r.varint_u32()?;
        let flags = r.u8()?;
        let (hash, history) = self.history_for(header, refs.map(Refs::as_slice), avatar, flags)?;
        let mut pose = {
            let mut b = BitReader { r, acc: 0, bits: 0 };
            let spacing = refs.and_then(|refs| refs.kind.spacing(header.seq, refs.as_slice()));
            delta_levels(&mut b, &history, flags, spacing)?
        };
        if flags & FLAG_SCALES != 0 {
            for s in &mut pose.scales {
                *s = r.vec3()?;
            }
        }
        if flags & FLAG_PLACEMENT != 0 {
            pose.placement = r.placement()?;
        }
        if flags & FLAG_WEIGHTS != 0 {
            let mut b = BitReader { r, acc: 0, bits: 0 };
            read_weights(&mut b, &mut pose.weights)?;
        }
        Ok(DecodedAvatar {
            avatar_num: avatar,
            hash,
            levels: Arc::new(pose),
        })
    }

    /// A chunk of a packed delta (kind 3), read from the frame's one bit stream; `prev` is
    /// the previous chunk's avatar number.
    fn packed_chunk(
        &self,
        b: &mut BitReader<'_, '_>,
        header: &FrameHeader,
        prev: Option<u32>,
    ) -> Result<DecodedAvatar, Frame2Error> {
        let at = b.r.at;
        let avatar = match prev {
            Some(p) if b.get(1)? == 1 => p.checked_add(1).ok_or(Frame2Error::Number { at })?,
            _ => {
                let n = b.get(5)? as u32 + 1;
                u32::try_from(b.get(n)?).map_err(|_| Frame2Error::Number { at })?
            }
        };
        let flags = if b.get(1)? == 1 {
            ((MAX_DEPTH - 1) as u8) << 4
        } else {
            let depth = b.get(3)? as u8;
            depth << 4 | b.get(4)? as u8
        };
        let (hash, history) = self.history_for(header, None, avatar, flags)?;
        let mut pose = delta_levels(b, &history, flags, None)?;
        let mut f32 = || b.get(32).map(|v| f32::from_bits(v as u32));
        if flags & FLAG_SCALES != 0 {
            for s in &mut pose.scales {
                *s = Vec3::new(f32()?, f32()?, f32()?);
            }
        }
        if flags & FLAG_PLACEMENT != 0 {
            let position = Vec3::new(f32()?, f32()?, f32()?);
            let rotation = Quat::from_array([f32()?, f32()?, f32()?, f32()?]);
            pose.placement = Placement { position, rotation };
        }
        if flags & FLAG_WEIGHTS != 0 {
            read_weights(b, &mut pose.weights)?;
        }
        Ok(DecodedAvatar {
            avatar_num: avatar,
            hash,
            levels: Arc::new(pose),
        })
    }

    /// The description hash and the frames (newest first, `depth` of them from `flags`) a
    /// delta chunk of `avatar` refers to, checked against what this decoder holds: its newest
    /// frames, or those of `refs` (a kind 4 delta), wherever they are among those it holds.
    fn history_for(
        &self,
        header: &FrameHeader,
        refs: Option<&[u64]>,
        avatar: u32,
        flags: u8,
    ) -> Result<(u64, Vec<&QuantPose>), Frame2Error> {
        let depth = usize::from(flags >> 4) + 1;
        let missing = Frame2Error::MissingBase {
            avatar,
            base_seq: header.base_seq,
            depth,
        };
        let Some(held) = self.history.get(&(header.scene_num, avatar)) else {
            return Err(missing);
        };
        let history: Vec<&QuantPose> = match refs {
            Some(refs) => {
                if depth > refs.len() {
                    return Err(Frame2Error::Flags { avatar, flags });
                }
                let mut history = Vec::with_capacity(depth);
                for seq in &refs[..depth] {
                    let Some((_, f)) = held.frames.iter().find(|(s, _)| s == seq) else {
                        return Err(missing);
                    };
                    history.push(&**f);
                }
                history
            }
            None => {
                if depth > MAX_DEPTH
                    || held.frames.len() < depth
                    || held.frames.front().map(|f| f.0) != Some(header.base_seq)
                {
                    return Err(missing);
                }
                held.frames.iter().take(depth).map(|f| &*f.1).collect()
            }
        };
        let base = history[0];
        if history.iter().any(|h| !h.same_shape(base)) {
            return Err(missing);
        }
        if flags & FLAG_WEIGHTS != 0 && base.weights.is_empty() {
            return Err(Frame2Error::Flags { avatar, flags });
        }
        Ok((held.hash, history))
    }
}

/// The changed morph weights of a delta chunk: a change mask over `weights`' channels, then
/// a level for each changed one.
fn read_weights(b: &mut BitReader<'_, '_>, weights: &mut [u16]) -> Result<(), Frame2Error> {
    let mut changed = vec![false; weights.len()];
    for c in &mut changed {
        *c = b.get(1)? == 1;
    }
    for (w, _) in weights.iter_mut().zip(&changed).filter(|(_, c)| **c) {
        *w = weight(b)?;
    }
    Ok(())
}

/// A delta chunk's escape mask, rotations and translations, read against `history` (newest
/// first, the chunk's depth); scales, placement and weights are the base's.
fn delta_levels(
    b: &mut BitReader<'_, '_>,
    history: &[&QuantPose],
    flags: u8,
    spacing: Option<Spacing>,
) -> Result<QuantPose, Frame2Error> {
    let depth = history.len();
    let base = history[0];
    let mut pose = QuantPose {
        rotations: Vec::with_capacity(base.rotations.len()),
        translations: Vec::with_capacity(base.translations.len()),
        scales: base.scales.clone(),
        placement: base.placement,
        weights: base.weights.clone(),
        steps: base.steps.clone(),
    };
    let joints = base.rotations.len();
    let full = full_bits(base);
    let steps = base.steps.clone();
    let tiered = steps.as_deref().filter(|s| s.tiered());
    let mut escaped = vec![false; joints];
    if flags & FLAG_ESCAPES != 0 {
        for e in &mut escaped {
            *e = b.get(1)? == 1;
        }
    }
    let mut h = [0i64; MAX_DEPTH];
    let frames: Vec<&[u64]> = history.iter().map(|f| &f.rotations[..]).collect();
    let mut p = predict_rotations(&frames, 0, spacing);
    for (j, &esc) in escaped.iter().enumerate() {
        let l = j % LANES;
        if l == 0 && j > 0 {
            p = predict_rotations(&frames, j, spacing);
        }
        if esc {
            if let Some(steps) = tiered
                && b.get(1)? == 1
            {
                // The tier changed, the dropped component did not.
                let flipped = base.rotations[j] ^ (1 << 47);
                let mut bits = tag(flipped);
                for c in 0..3 {
                    let (pred, k) = regridded(&frames, j, flipped, steps, c, spacing);
                    let value = pred + unzigzag(b.rice(k)?);
                    if !(0..=LEVEL_MASK as i64).contains(&value) {
                        return Err(Frame2Error::Number { at: b.r.at });
                    }
                    bits = bits << 15 | value as u64;
                }
                pose.rotations.push(bits);
                continue;
            }
            pose.rotations.push(b.get(full)?);
            continue;
        }
        let mut bits = tag(base.rotations[j]);
        for c in 0..3 {
            let value = i64::from(p.pred[c][l]) + unzigzag(b.rice(p.k[c][l])?);
            if !(0..=LEVEL_MASK as i64).contains(&value) {
                return Err(Frame2Error::Number { at: b.r.at });
            }
            bits = bits << 15 | value as u64;
        }
        pose.rotations.push(bits);
    }
    for t in 0..base.translations.len() {
        let mut v = [0i32; 3];
        for (c, out) in v.iter_mut().enumerate() {
            for (slot, f) in h.iter_mut().zip(history) {
                *slot = i64::from(f.translations[t][c]);
            }
            let (pred, k) = predict(&h[..depth], false, spacing);
            *out = i32::try_from(pred.wrapping_add(unzigzag(b.rice(k)?)))
                .map_err(|_| Frame2Error::Number { at: b.r.at })?;
        }
        pose.translations.push(v);
    }
    Ok(pose)
}

/// One weight level from the bit stream, checked against [`crate::morph::WEIGHT_LEVELS`].
fn weight(b: &mut BitReader<'_, '_>) -> Result<u16, Frame2Error> {
    let at = b.r.at;
    match u16::try_from(b.get(WEIGHT_BITS)?) {
        Ok(l) if l <= crate::morph::WEIGHT_LEVELS => Ok(l),
        _ => Err(Frame2Error::Number { at }),
    }
}

fn key_chunk(r: &mut Reader<'_>) -> Result<DecodedAvatar, Frame2Error> {
    let avatar = r.varint_u32()?;
    let hash = r.u64()?;
    let joints = r.count(avatar)?;
    let translations = r.count(avatar)?;
    let scales = r.count(avatar)?;
    let flags = r.u8()?;
    if flags & !(FLAG_PLACEMENT | FLAG_WEIGHTS | FLAG_STEPS | FLAG_NEAR) != 0
        || (flags & FLAG_NEAR != 0 && flags & FLAG_STEPS == 0)
    {
        return Err(Frame2Error::Flags { avatar, flags });
    }
    let steps = if flags & FLAG_STEPS != 0 {
        let at = r.at;
        let translation = u16::try_from(r.varint()?)
            .ok()
            .filter(|&t| t >= 1)
            .ok_or(Frame2Error::Number { at })?;
        let at = r.at;
        let rotations = r.take(joints)?.to_vec();
        if rotations.contains(&0) {
            return Err(Frame2Error::Number { at });
        }
        let at = r.at;
        let near = if flags & FLAG_NEAR != 0 {
            r.take(joints)?.to_vec()
        } else {
            Vec::new()
        };
        if near.contains(&0) {
            return Err(Frame2Error::Number { at });
        }
        Some(Arc::new(Steps {
            rotations,
            translation,
            near,
        }))
    } else {
        None
    };
    // Check the bytes are there before allocating for them.
    let needed = joints * quant::BYTES + translations * 3 + scales * 12;
    if r.bytes.len() - r.at < needed {
        return Err(Frame2Error::Truncated { at: r.bytes.len() });
    }
    let mut pose = QuantPose {
        rotations: Vec::with_capacity(joints),
        translations: Vec::with_capacity(translations),
        scales: Vec::with_capacity(scales),
        placement: Placement::IDENTITY,
        weights: Vec::new(),
        steps,
    };
    // Bit 47 is a tier only on a grid with near-axis steps; elsewhere it is not part of a
    // rotation and is dropped.
    let kept = if pose.steps.as_ref().is_some_and(|s| s.tiered()) {
        u64::MAX
    } else {
        !(1u64 << 47)
    };
    for _ in 0..joints {
        let mut b = [0u8; 8];
        b[..quant::BYTES].copy_from_slice(r.take(quant::BYTES)?);
        pose.rotations.push(u64::from_le_bytes(b) & kept);
    }
    for _ in 0..translations {
        let mut v = [0i32; 3];
        for c in &mut v {
            let at = r.at;
            *c = i32::try_from(unzigzag(r.varint()?)).map_err(|_| Frame2Error::Number { at })?;
        }
        pose.translations.push(v);
    }
    for _ in 0..scales {
        pose.scales.push(r.vec3()?);
    }
    if flags & FLAG_PLACEMENT != 0 {
        pose.placement = r.placement()?;
    }
    if flags & FLAG_WEIGHTS != 0 {
        let count = r.count(avatar)?;
        if (r.bytes.len() - r.at) * 8 < count * WEIGHT_BITS as usize {
            return Err(Frame2Error::Truncated { at: r.bytes.len() });
        }
        let mut b = BitReader { r, acc: 0, bits: 0 };
        pose.weights = (0..count)
            .map(|_| weight(&mut b))
            .collect::<Result<_, _>>()?;
    }
    Ok(DecodedAvatar {
        avatar_num: avatar,
        hash,
        levels: Arc::new(pose),
    })
}

/// Encodes whole v2 frames for one receiver that gets every frame it is given: keeps its
/// last [`MAX_DEPTH`] frames per avatar as the decoder does. For tests, benches and single
/// streams; the server shares encodings between subscribers instead.
#[derive(Debug, Default)]
pub struct StreamEncoder {
    history: HashMap<u32, VecDeque<Arc<QuantPose>>>,
    last_seq: Option<u64>,
    /// The last frame's server time.
    last_time: u64,
    /// Whether deltas are packed (kind 3, protocol version 7).
    packed: bool,
    /// Grid steps by avatar number (a subscription's precision), else the finest.
    steps: HashMap<u32, Arc<Steps>>,
}

impl StreamEncoder {
    /// An encoder whose first frame will be a keyframe.
    #[must_use]
    pub fn new() -> Self {
        Self::default()
    }

    /// The same encoder, writing packed deltas (kind 3, protocol version 7) when `packed`.
    #[must_use]
    pub fn with_packing(mut self, packed: bool) -> Self {
        self.packed = packed;
        self
    }

    /// Codes avatar `avatar_num` on the grid of `steps` from now on (its next frame should be
    /// a keyframe: pass `key`).
    pub fn set_steps(&mut self, avatar_num: u32, steps: Arc<Steps>) {
        self.steps.insert(avatar_num, steps);
    }

    /// Encodes `poses` as tick `seq`: a keyframe when `key` or when some avatar has no
    /// compatible history, else a delta against the previous frame. Returns the bytes and
    /// the kind written.
    pub fn encode(
        &mut self,
        scene_num: u32,
        seq: u64,
        server_time_us: u64,
        poses: &[AvatarPose],
        key: bool,
    ) -> (Vec<u8>, FrameKind) {
        let quantised: Vec<Arc<QuantPose>> = poses
            .iter()
            .map(|p| {
                let q = QuantPose::from_pose(p);
                Arc::new(match self.steps.get(&p.avatar_num) {
                    Some(steps) => q.coarsen(steps),
                    None => q,
                })
            })
            .collect();
        let kind = FrameKind::Key;
        if !key && let Some(base_seq) = self.last_seq {
            let header = FrameHeader {
                kind: FrameKind::Delta,
                scene_num,
                seq,
                server_time_us,
                base_seq,
            };
            if let Some(out) = self.delta(&header, poses, &quantised) {
                self.remember(poses, quantised, seq, server_time_us, false);
                return (out, FrameKind::Delta);
            }
        }
        let mut out = Vec::new();
        write_header(
            &FrameHeader {
                kind,
                scene_num,
                seq,
                server_time_us,
                base_seq: seq,
            },
            poses.len(),
            &mut out,
        );
        for (p, q) in poses.iter().zip(&quantised) {
            encode_key(p.avatar_num, p.hash, q, &mut out);
        }
        self.remember(poses, quantised, seq, server_time_us, true);
        (out, kind)
    }

    /// A delta frame of `quantised` against the frames remembered, `None` when some avatar
    /// cannot be coded against them.
    fn delta(
        &self,
        header: &FrameHeader,
        poses: &[AvatarPose],
        quantised: &[Arc<QuantPose>],
    ) -> Option<Vec<u8>> {
        let history = |num: u32| -> Vec<&QuantPose> {
            self.history
                .get(&num)
                .map(|h| h.iter().map(|f| &**f).collect())
                .unwrap_or_default()
        };
        let mut out = Vec::new();
        if self.packed {
            let mut packed = PackedDeltas::new(header, self.last_time, poses.len(), &mut out);
            for (p, q) in poses.iter().zip(quantised) {
                if !packed.push(p.avatar_num, q, &history(p.avatar_num)) {
                    return None;
                }
            }
            packed.finish();
        } else {
            write_header(header, poses.len(), &mut out);
            for (p, q) in poses.iter().zip(quantised) {
                if !encode_delta(p.avatar_num, q, &history(p.avatar_num), &mut out) {
                    return None;
                }
            }
        }
        Some(out)
    }

    fn remember(
        &mut self,
        poses: &[AvatarPose],
        q: Vec<Arc<QuantPose>>,
        seq: u64,
        time: u64,
        key: bool,
    ) {
        if key {
            self.history.clear();
        }
        for (p, q) in poses.iter().zip(q) {
            let h = self.history.entry(p.avatar_num).or_default();
            h.push_front(q);
            h.truncate(MAX_DEPTH);
        }
        self.last_seq = Some(seq);
        self.last_time = time;
    }
}

#[cfg(test)]
mod tests;
