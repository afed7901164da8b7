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
use posecast_proto::frame2::{self, QuantPose};
use posecast_proto::msg::AvatarId;
use posecast_proto::precision::{Precision, PrecisionKey, Steps};
use posecast_proto::subset::{JointSet, Selection};
use std::borrow::Cow;
use std::collections::{HashMap, VecDeque};
use std::hash::{BuildHasherDefault, Hasher};
use std::sync::{Arc, Mutex, PoisonError};

/// Ticks of levels kept: deltas may refer to this far back (a subscriber at 10 Hz of a 60 Hz
/// scene refers to 6 ticks per frame, [`frame2::MAX_DEPTH`] frames deep). A subscriber whose
/// frames are older gets a keyframe.
pub const RING_TICKS: usize = 6 * frame2::MAX_DEPTH;

/// One avatar's levels at a tick, with the description hash they belong to.
type Levels = (u64, Arc<QuantPose>);

/// Every avatar's levels at one tick, by avatar number.
pub(super) type TickLevels = HashMap<u32, Levels, BuildHasherDefault<NumHasher>>;

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

/// Most rigs × precisions whose steps are kept (a bound on what many distinct subscriptions
/// can make the ring hold; past it the cache starts again).
const MAX_STEPS_CACHED: usize = 4096;

/// The scene's recent ticks as levels, newest first.
#[derive(Debug, Default)]
pub(super) struct Ring {
    ticks: VecDeque<(u64, Arc<TickLevels>)>,
    /// Levels on a precision's grid, made once per (tick, avatar number, precision) for every
    /// subscriber holding that precision. Only ticks still in the ring.
    coarse: Mutex<HashMap<(u64, u32, PrecisionKey), Arc<QuantPose>>>,
    /// Grid steps by (description hash, precision).
    steps: Mutex<HashMap<(u64, PrecisionKey), Arc<Steps>>>,
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
    fn steps_of(
        &self,
        d: &AvatarDescription,
        hash: u64,
        precision: &Precision,
    ) -> Option<Arc<Steps>> {
        let key = (hash, precision.key());
        let mut cache = self.steps.lock().unwrap_or_else(PoisonError::into_inner);
        if cache.len() >= MAX_STEPS_CACHED && !cache.contains_key(&key) {
            cache.clear();
        }
        let steps = cache
            .entry(key)
            .or_insert_with(|| Arc::new(precision.resolve(d)))
            .clone();
        (!steps.is_finest()).then_some(steps)
    }

    /// `levels` of avatar `num` at tick `seq` on the grid of `steps` (made once, then shared).
    fn coarse_of(
        &self,
        seq: u64,
        num: u32,
        levels: &Arc<QuantPose>,
        steps: &Arc<Steps>,
        key: PrecisionKey,
    ) -> Arc<QuantPose> {
        let mut cache = self.coarse.lock().unwrap_or_else(PoisonError::into_inner);
        cache
            .entry((seq, num, key))
            .or_insert_with(|| Arc::new(levels.coarsen(steps)))
            .clone()
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
    /// With a `precision`, every avatar's levels (now and in the chain) are on its grid.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn message(
        &self,
        published: &Published,
        now: &TickLevels,
        chain: Option<&[u64]>,
        filter: Option<&[AvatarId]>,
        joints: Option<&JointSet>,
        weights: bool,
        precision: Option<&Precision>,
    ) -> Option<Message> {
        let pieces = publish::select(&published.pieces, filter, joints);
        let seq = published.header.seq;
        let mut body = Vec::with_capacity(16 + 8 * pieces.len());
        let ticks = chain.map(|c| self.ticks_of(c)).unwrap_or_default();
        for (p, selection) in &pieces {
            let num = p.pose.avatar_num;
            let (hash, levels) = now.get(&num)?;
            let selection = selection.as_deref();
            let grid = precision
                .and_then(|pr| Some((self.steps_of(p.description(), *hash, pr)?, pr.key())));
            let on_grid = |tick: u64, levels: &Arc<QuantPose>| match &grid {
                Some((steps, key)) => self.coarse_of(tick, num, levels, steps, *key),
                None => levels.clone(),
            };
            let levels = on_grid(seq, levels);
            let levels = cut(&levels, selection, weights);
            if chain.is_none() {
                frame2::encode_key(num, *hash, &levels, &mut body);
                continue;
            }
            let history: Vec<Arc<QuantPose>> = ticks
                .iter()
                .map_while(|(tick, t)| {
                    t.get(&num)
                        .filter(|(h, _)| h == hash)
                        .map(|(_, l)| on_grid(*tick, l))
                })
                .collect();
            let history: Vec<Cow<'_, QuantPose>> =
                history.iter().map(|l| cut(l, selection, weights)).collect();
            let history: Vec<&QuantPose> = history.iter().map(|h| &**h).collect();
            if !frame2::encode_delta(num, &levels, &history, &mut body) {
                return None;
            }
        }
        let header = FrameHeader {
            kind: if chain.is_some() {
                FrameKind::Delta
            } else {
                FrameKind::Key
            },
            base_seq: chain.and_then(|c| c.first().copied()).unwrap_or(seq),
            ..published.header
        };
        let mut out = Vec::with_capacity(24 + body.len());
        frame2::write_header(&header, pieces.len(), &mut out);
        out.extend_from_slice(&body);
        Some(Message::Binary(Bytes::from(out)))
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

/// Every avatar's levels in `published`, by avatar number.
pub(super) fn levels(published: &Published) -> TickLevels {
    published
        .pieces
        .iter()
        .map(|p| {
            (
                p.pose.avatar_num,
                (
                    p.pose.hash,
                    Arc::new(QuantPose::from_pose_with(
                        &p.pose,
                        Some(&p.rotation_bits)
                            .filter(|b| !b.is_empty())
                            .map(|b| &b[..]),
                    )),
                ),
            )
        })
        .collect()
}
