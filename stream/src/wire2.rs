//! Wire v2 for a scene's binary subscribers that asked for protocol version 2
//! ([`posecast_proto::frame2`]): each tick's poses as levels, kept for a few ticks, and the
//! frames made from them — per tick at most one keyframe and one delta per distinct chain of
//! frames a subscriber holds ([`super::outbox::Outbox::chain`]), shared by every subscriber
//! holding that chain (and, for subscribers limited to some joints, per joint set: their
//! frames are the levels cut to those joints, predicted from frames cut alike; and for
//! subscribers asking for a precision, per precision: their frames code the levels on that
//! precision's grid, [`posecast_proto::precision`], predicted from frames coded alike).

use super::publish::{self, Published};
use axum::extract::ws::Message;
use bytes::Bytes;
use posecast_proto::description::AvatarDescription;
use posecast_proto::frame::{FrameHeader, FrameKind};
use posecast_proto::frame2::{self, PackedDeltas, QuantPose, ReferencedKind, Spacing};
use posecast_proto::msg::AvatarId;
use posecast_proto::precision::{Grid, GridKey, Steps};
use posecast_proto::subset::{JointSet, Selection};
use std::borrow::Cow;
use std::collections::{HashMap, VecDeque};
use std::hash::{BuildHasherDefault, Hasher};
use std::ops::Deref;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, PoisonError};

/// Ticks of levels kept: deltas may refer to this far back (a subscriber at 10 Hz of a 60 Hz
/// scene refers to 6 ticks per frame, [`frame2::MAX_DEPTH`] frames deep). A subscriber whose
/// frames are older gets a keyframe.
pub const RING_TICKS: usize = 6 * frame2::MAX_DEPTH;

/// One avatar's levels at a tick: its number, the description hash they belong to, and the
/// levels.
#[derive(Debug)]
pub(super) struct AvatarLevels {
    num: u32,
    hash: u64,
    levels: QuantPose,
}

/// Every avatar's levels at one tick, in the order of the tick's pieces (scene order), and
/// where each avatar number is. Frames look an avatar up at the position it had in the last
/// tick looked at (avatars rarely change places between ticks), so a delta's history is read
/// in order from each tick, not through a hash lookup per avatar and tick.
#[derive(Debug, Default)]
pub(super) struct TickLevels {
    /// The tick's server time (a packed delta's is sent as a difference from its base's).
    time_us: u64,
    avatars: Vec<AvatarLevels>,
    by_num: HashMap<u32, usize, BuildHasherDefault<NumHasher>>,
}

impl TickLevels {
    /// Avatar `num`'s levels and their position, looked for at `at` first.
    fn find(&self, num: u32, at: usize) -> Option<(usize, &AvatarLevels)> {
        match self.avatars.get(at) {
            Some(a) if a.num == num => Some((at, a)),
            _ => {
                let at = *self.by_num.get(&num)?;
                Some((at, self.avatars.get(at)?))
            }
        }
    }
}

/// Hashes an avatar number with one multiplication (Fibonacci hashing): the tick's levels are
/// looked up once per avatar and frame of history for every distinct chain, where SipHash's
/// cost showed in the tick's profile. Avatar numbers are the server's own, not an attacker's.
#[derive(Debug, Default, Clone, Copy)]
pub(super) struct NumHasher(u64);

impl Hasher for NumHasher {
    fn finish(&self) -> u64 {
        self.0
    }

    fn write(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.0 = (self.0.rotate_left(8) ^ u64::from(b)).wrapping_mul(0x9e37_79b9_7f4a_7c15);
        }
    }

    fn write_u32(&mut self, n: u32) {
        self.0 = (u64::from(n) ^ self.0).wrapping_mul(0x9e37_79b9_7f4a_7c15);
    }
}

/// A map keyed by small numbers the server makes, hashed with [`NumHasher`].
type NumMap<K, V> = HashMap<K, V, BuildHasherDefault<NumHasher>>;

/// Levels on a precision's grid by (tick, avatar number, precision).
type CoarseCache = NumMap<(u64, u32, GridKey), Arc<QuantPose>>;

/// Most rigs × precisions whose steps are kept (a bound on what many distinct subscriptions
/// can make the ring hold; past it the cache starts again).
const MAX_STEPS_CACHED: usize = 4096;

/// The scene's recent ticks as levels, newest first.
#[derive(Debug, Default)]
pub(super) struct Ring {
    ticks: VecDeque<(u64, Arc<TickLevels>)>,
    /// Levels on a precision's grid, made once per (tick, avatar number, precision) for every
    /// subscriber holding that precision. Only ticks still in the ring.
    coarse: Mutex<CoarseCache>,
    /// Grid steps by (description hash, precision).
    steps: Mutex<HashMap<(u64, GridKey), Arc<Steps>>>,
    /// The length of the last frame made, to allocate the next one at once.
    last_len: AtomicUsize,
}

/// Levels a frame is made from: the ring's own, or made for a precision (and shared).
enum Held<'a> {
    Ring(&'a QuantPose),
    Coarse(Arc<QuantPose>),
}

impl Deref for Held<'_> {
    type Target = QuantPose;

    fn deref(&self) -> &QuantPose {
        match self {
            Held::Ring(l) => l,
            Held::Coarse(l) => l,
        }
    }
}

impl Ring {
    /// Forgets everything (a new source of frames, or no v2 subscriber left).
    pub(super) fn clear(&mut self) {
        self.ticks.clear();
        self.coarse
            .get_mut()
            .unwrap_or_else(PoisonError::into_inner)
            .clear();
    }

    /// The steps of rig `d` (of description hash `hash`) at `precision` (`None`: the finest, frames coded as without one).
    fn steps_of(&self, d: &AvatarDescription, hash: u64, grid: &Grid) -> Option<Arc<Steps>> {
        let key = (hash, grid.key());
        let mut cache = self.steps.lock().unwrap_or_else(PoisonError::into_inner);
        if cache.len() >= MAX_STEPS_CACHED && !cache.contains_key(&key) {
            cache.clear();
        }
        let steps = cache
            .entry(key)
            .or_insert_with(|| Arc::new(grid.resolve(d)))
            .clone();
        (!steps.is_finest()).then_some(steps)
    }

    /// `levels` of avatar `num` at tick `seq` on the grid of `steps` (made once, then shared),
    /// or as they are without a grid. `cache` is the locked [`Ring::coarse`], when there is a grid.
    fn on_grid<'l>(
        cache: &mut Option<MutexGuard<'_, CoarseCache>>,
        grid: Option<&(Arc<Steps>, GridKey)>,
        seq: u64,
        num: u32,
        levels: &'l QuantPose,
    ) -> Held<'l> {
        match (grid, cache) {
            (Some((steps, key)), Some(cache)) => Held::Coarse(
                cache
                    .entry((seq, num, *key))
                    .or_insert_with(|| Arc::new(levels.coarsen(steps)))
                    .clone(),
            ),
            _ => Held::Ring(levels),
        }
    }

    /// The levels of `published`, recorded as its tick's when that tick is newer than every
    /// tick recorded (an older one, e.g. a cached frame for a joiner, is not: a subscriber
    /// holding it gets a keyframe next).
    pub(super) fn record(&mut self, published: &Published) -> Arc<TickLevels> {
        let seq = published.header.seq;
        if let Some((_, levels)) = self.ticks.iter().find(|(s, _)| *s == seq) {
            return levels.clone();
        }
        let levels = Arc::new(levels(published));
        if self.ticks.front().is_none_or(|(s, _)| *s < seq) {
            self.ticks.push_front((seq, levels.clone()));
            self.ticks.truncate(RING_TICKS);
            let oldest = self.ticks.back().map_or(seq, |(s, _)| *s);
            let coarse = self
                .coarse
                .get_mut()
                .unwrap_or_else(PoisonError::into_inner);
            if !coarse.is_empty() {
                coarse.retain(|(s, _, _), _| *s >= oldest);
            }
        }
        levels
    }

    /// The recorded ticks of `chain` (newest first), up to the first one no longer kept.
    fn ticks_of(&self, chain: &[u64]) -> Vec<(u64, &TickLevels)> {
        chain
            .iter()
            .take(frame2::MAX_DEPTH)
            .map_while(|&seq| {
                self.ticks
                    .iter()
                    .find(|(s, _)| *s == seq)
                    .map(|(_, l)| (seq, &**l))
            })
            .collect()
    }

    /// A v2 frame of `published` (whose levels are `now`) for a subscriber holding `chain`
    /// (`None`: a keyframe), with only the avatars `filter` names and of each only the joints
    /// of `joints` (levels and history cut alike, so a subset's deltas predict from the
    /// subset's own frames). `None` when some avatar cannot be coded against the chain (it is
    /// new, changed rig, or its frames left the ring): the subscriber needs a keyframe.
    /// With a `precision`, every avatar's levels (now and in the chain) are on its grid;
    /// `layout` says how a delta is laid out (a keyframe's is always the same).
    #[allow(clippy::too_many_arguments)]
    pub(super) fn message(
        &self,
        published: &Published,
        now: &TickLevels,
        chain: Option<&[u64]>,
        filter: Option<&[AvatarId]>,
        joints: Option<&JointSet>,
        weights: bool,
        precision: Option<&Grid>,
        layout: DeltaLayout,
    ) -> Option<Message> {
        let pieces = publish::select(&published.pieces, filter, joints);
        let seq = published.header.seq;
        let header = FrameHeader {
            kind: if chain.is_some() {
                FrameKind::Delta
            } else {
                FrameKind::Key
            },
            base_seq: chain.and_then(|c| c.first().copied()).unwrap_or(seq),
            ..published.header
        };
        // The header first and the chunks after it, in the message's own buffer.
        let mut out = Vec::with_capacity(self.last_len.load(Ordering::Relaxed).max(64));
        let ticks = chain.map(|c| self.ticks_of(c)).unwrap_or_default();
        let mut chunks = match chain {
            Some(_) if let DeltaLayout::Referenced(kind) = layout => {
                // It names the ticks still kept (a delta codes against no others).
                let refs: Vec<u64> = ticks.iter().map(|(s, _)| *s).collect();
                if refs.is_empty() {
                    return None;
                }
                frame2::write_referenced_header(&header, kind, &refs, pieces.len(), &mut out);
                Chunks::Referenced(&mut out, kind.spacing(header.seq, &refs))
            }
            Some(chain) if layout == DeltaLayout::Packed => {
                // The base frame's time, which the delta's is sent against.
                let base = ticks.first().filter(|(s, _)| Some(s) == chain.first())?;
                Chunks::Packed(PackedDeltas::new(
                    &header,
                    base.1.time_us,
                    pieces.len(),
                    &mut out,
                ))
            }
            _ => {
                frame2::write_header(&header, pieces.len(), &mut out);
                Chunks::Bytes(&mut out)
            }
        };
        // Locked once for the frame rather than once per avatar and tick.
        let mut coarse =
            precision.map(|_| self.coarse.lock().unwrap_or_else(PoisonError::into_inner));
        // The steps of the last rig seen (a scene's avatars mostly share a few rigs).
        let mut rig_steps: Option<(u64, Option<Arc<Steps>>)> = None;
        let empty = QuantPose::default();
        let mut at = 0;
        for (p, selection) in &pieces {
            let num = p.pose.avatar_num;
            let (pos, a) = now.find(num, at)?;
            at = pos + 1;
            let hash = a.hash;
            let selection = selection.as_deref();
            let grid = match precision {
                Some(pr) => {
                    let steps = match &rig_steps {
                        Some((h, steps)) if *h == hash => steps.clone(),
                        _ => {
                            let steps = self.steps_of(p.description(), hash, pr);
                            rig_steps = Some((hash, steps.clone()));
                            steps
                        }
                    };
                    steps.map(|s| (s, pr.key()))
                }
                None => None,
            };
            let grid = grid.as_ref();
            // Most frames take every joint of the ring's own levels, as they are: the history
            // is references into the ring, on the stack (this runs for every avatar of every
            // frame made).
            if chain.is_some() && grid.is_none() && selection.is_none() {
                let mut history: [&QuantPose; frame2::MAX_DEPTH] = [&empty; frame2::MAX_DEPTH];
                let mut depth = 0;
                let mut plain = weights || a.levels.weights.is_empty();
                for (slot, (_, t)) in history.iter_mut().zip(&ticks) {
                    match t.find(num, pos) {
                        Some((_, h)) if h.hash == hash => {
                            plain &= weights || h.levels.weights.is_empty();
                            *slot = &h.levels;
                            depth += 1;
                        }
                        _ => break,
                    }
                }
                if plain {
                    if !chunks.delta(num, &a.levels, &history[..depth]) {
                        return None;
                    }
                    continue;
                }
            }
            let levels = Self::on_grid(&mut coarse, grid, seq, num, &a.levels);
            let levels = cut(&levels, selection, weights);
            if chain.is_none() {
                chunks.key(num, hash, &levels);
                continue;
            }
            // The avatar's frames in the chain, newest first, while they are of its rig.
            let held: Vec<Held<'_>> = ticks
                .iter()
                .map_while(|(tick, t)| {
                    t.find(num, pos)
                        .filter(|(_, h)| h.hash == hash)
                        .map(|(_, h)| Self::on_grid(&mut coarse, grid, *tick, num, &h.levels))
                })
                .collect();
            let history: Vec<Cow<'_, QuantPose>> =
                held.iter().map(|h| cut(h, selection, weights)).collect();
            let history: Vec<&QuantPose> = history.iter().map(|h| &**h).collect();
            if !chunks.delta(num, &levels, &history) {
                return None;
            }
        }
        if let Chunks::Packed(packed) = chunks {
            packed.finish();
        }
        self.last_len.store(out.len(), Ordering::Relaxed);
        Some(Message::Binary(Bytes::from(out)))
    }
}

/// How a wire v2 delta is laid out, by what its receiver speaks.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub(super) enum DeltaLayout {
    /// Kind 2: each chunk byte-aligned, against the receiver's newest frames.
    Chunks,
    /// Kind 3 (protocol version 7): every chunk in one bit stream.
    Packed,
    /// Kind 4 or 5 (protocol versions 8 and 9, frames as datagrams): naming the frames it
    /// refers to, each chunk with its length.
    Referenced(ReferencedKind),
}

/// Where a frame's chunks go: after its header, each byte-aligned (keyframes and deltas of
/// kind 2), with its length (kind 4), or into a packed delta's one bit stream.
enum Chunks<'o> {
    Bytes(&'o mut Vec<u8>),
    Referenced(&'o mut Vec<u8>, Option<Spacing>),
    Packed(PackedDeltas<'o>),
}

impl Chunks<'_> {
    /// Appends avatar `num`'s delta chunk; `false` when it cannot be coded against `history`.
    fn delta(&mut self, num: u32, levels: &QuantPose, history: &[&QuantPose]) -> bool {
        match self {
            Chunks::Bytes(out) => frame2::encode_delta(num, levels, history, out),
            Chunks::Referenced(out, spacing) => {
                frame2::encode_referenced_delta(num, levels, history, *spacing, out)
            }
            Chunks::Packed(packed) => packed.push(num, levels, history),
        }
    }

    /// Appends avatar `num`'s keyframe chunk (a keyframe's chunks are never packed).
    fn key(&mut self, num: u32, hash: u64, levels: &QuantPose) {
        if let Chunks::Bytes(out) = self {
            frame2::encode_key(num, hash, levels, out);
        }
    }
}

/// `levels`, or of them the joints `selection` names; without morph weights unless
/// `weights` (a receiver of protocol version 2 or 3, whose decoder knows none).
fn cut<'l>(
    levels: &'l QuantPose,
    selection: Option<&Selection>,
    weights: bool,
) -> Cow<'l, QuantPose> {
    let strip = !weights && !levels.weights.is_empty();
    match (selection, strip) {
        (None, false) => Cow::Borrowed(levels),
        (None, true) => Cow::Owned(levels.without_weights()),
        (Some(sel), false) => Cow::Owned(levels.select(sel)),
        (Some(sel), true) => Cow::Owned(levels.select(sel).without_weights()),
    }
}

/// Every avatar's levels in `published`, in its order.
pub(super) fn levels(published: &Published) -> TickLevels {
    let avatars: Vec<AvatarLevels> = published
        .pieces
        .iter()
        .map(|p| AvatarLevels {
            num: p.pose.avatar_num,
            hash: p.pose.hash,
            levels: QuantPose::from_pose_with(
                &p.pose,
                Some(&p.rotation_bits)
                    .filter(|b| !b.is_empty())
                    .map(|b| &b[..]),
            ),
        })
        .collect();
    let by_num = avatars
        .iter()
        .enumerate()
        .map(|(i, a)| (a.num, i))
        .collect();
    TickLevels {
        time_us: published.header.server_time_us,
        avatars,
        by_num,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::publish::{Piece, Snapshot};
    use posecast_proto::frame::ChunkEncoder;
    use posecast_proto::frame2::Frame2Decoder;
    use posecast_sim::avatar::Avatar;
    use posecast_sim::avatar::playback::Layer;

    fn walkers(ids: &[(&str, u32)]) -> Vec<Avatar> {
        let rig = Arc::new(posecast_rigs::builtin::rig().unwrap());
        let walk = rig.clip("walk").cloned().unwrap();
        ids.iter()
            .map(|&(id, num)| {
                let mut a = Avatar::new(AvatarId(id.into()), num, rig.clone());
                a.play(
                    Layer::new(walk.clone(), None, num as f32 * 0.3, 1.0, true),
                    0.0,
                );
                a
            })
            .collect()
    }

    fn published(avatars: &[&Avatar], seq: u64, kind: FrameKind) -> Published {
        Published {
            header: FrameHeader {
                kind,
                scene_num: 3,
                seq,
                server_time_us: 1_764_000_000_000_000 + seq,
                base_seq: seq,
            },
            pieces: avatars
                .iter()
                .map(|a| {
                    let snapshot = Snapshot::of(a);
                    Piece::encode(snapshot, &mut ChunkEncoder::new(), kind, false, true)
                })
                .collect(),
        }
    }

    /// Deltas stay right when avatars change places between ticks (one leaves, the others
    /// move up, the order changes): each avatar's history is its own, so a decoder that got
    /// every frame reads exactly each pose's levels, quantised here independently.
    #[test]
    fn deltas_follow_avatars_that_change_places() {
        let mut avatars = walkers(&[("a", 7), ("b", 8), ("c", 9)]);
        let mut ring = Ring::default();
        let mut decoder = Frame2Decoder::new();
        let mut chain: Vec<u64> = Vec::new();
        for seq in 1..=30u64 {
            for a in &mut avatars {
                a.tick(seq as f64 / 60.0);
            }
            // Scene order, then a reordering, then "a" gone.
            let order: Vec<&Avatar> = match seq {
                ..=10 => avatars.iter().collect(),
                11..=20 => [2, 0, 1].iter().map(|&i| &avatars[i]).collect(),
                _ => [2, 1].iter().map(|&i| &avatars[i]).collect(),
            };
            let kind = if chain.is_empty() {
                FrameKind::Key
            } else {
                FrameKind::Delta
            };
            let p = published(&order, seq, kind);
            let now = ring.record(&p);
            let held = (!chain.is_empty()).then_some(&chain[..]);
            let Some(Message::Binary(bytes)) =
                ring.message(&p, &now, held, None, None, true, None, DeltaLayout::Chunks)
            else {
                panic!("no frame at tick {seq}");
            };
            let got = decoder.decode_levels(&bytes).unwrap();
            assert_eq!(got.header.kind, kind, "tick {seq}");
            assert_eq!(got.avatars.len(), order.len());
            for (a, g) in order.iter().zip(&got.avatars) {
                assert_eq!(g.avatar_num, a.description.num);
                assert_eq!(
                    *g.levels,
                    QuantPose::from_pose(a.pose()),
                    "avatar {} at tick {seq}",
                    a.description.num
                );
            }
            chain.insert(0, seq);
            chain.truncate(frame2::MAX_DEPTH);
        }
    }
}
