//! Wire v2 for a scene's binary subscribers that asked for protocol version 2
//! ([`posecast_proto::frame2`]): each tick's poses as levels, kept for a few ticks, and the
//! frames made from them — per tick at most one keyframe and one delta per distinct chain of
//! frames a subscriber holds ([`super::outbox::Outbox::chain`]), shared by every subscriber
//! holding that chain (and, for subscribers limited to some joints, per joint set: their
//! frames are the levels cut to those joints, predicted from frames cut alike).

use super::publish::{self, Published};
use axum::extract::ws::Message;
use bytes::Bytes;
use posecast_proto::frame::{FrameHeader, FrameKind};
use posecast_proto::frame2::{self, QuantPose};
use posecast_proto::msg::AvatarId;
use posecast_proto::subset::{JointSet, Selection};
use std::borrow::Cow;
use std::collections::{HashMap, VecDeque};
use std::sync::Arc;

/// Ticks of levels kept: deltas may refer to this far back (a subscriber at 10 Hz of a 60 Hz
/// scene refers to 6 ticks per frame, [`frame2::MAX_DEPTH`] frames deep). A subscriber whose
/// frames are older gets a keyframe.
pub const RING_TICKS: usize = 6 * frame2::MAX_DEPTH;

/// One avatar's levels at a tick, with the description hash they belong to.
type Levels = (u64, Arc<QuantPose>);

/// Every avatar's levels at one tick, by avatar number.
pub(super) type TickLevels = HashMap<u32, Levels>;

/// The scene's recent ticks as levels, newest first.
#[derive(Debug, Default)]
pub(super) struct Ring {
    ticks: VecDeque<(u64, Arc<TickLevels>)>,
}

impl Ring {
    /// Forgets everything (a new source of frames, or no v2 subscriber left).
    pub(super) fn clear(&mut self) {
        self.ticks.clear();
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
        }
        levels
    }

    /// The recorded ticks of `chain` (newest first), up to the first one no longer kept.
    fn ticks_of(&self, chain: &[u64]) -> Vec<&TickLevels> {
        chain
            .iter()
            .take(frame2::MAX_DEPTH)
            .map_while(|&seq| {
                self.ticks
                    .iter()
                    .find(|(s, _)| *s == seq)
                    .map(|(_, l)| &**l)
            })
            .collect()
    }

    /// A v2 frame of `published` (whose levels are `now`) for a subscriber holding `chain`
    /// (`None`: a keyframe), with only the avatars `filter` names and of each only the joints
    /// of `joints` (levels and history cut alike, so a subset's deltas predict from the
    /// subset's own frames). `None` when some avatar cannot be coded against the chain (it is
    /// new, changed rig, or its frames left the ring): the subscriber needs a keyframe.
    pub(super) fn message(
        &self,
        published: &Published,
        now: &TickLevels,
        chain: Option<&[u64]>,
        filter: Option<&[AvatarId]>,
        joints: Option<&JointSet>,
        weights: bool,
    ) -> Option<Message> {
        let pieces = publish::select(&published.pieces, filter, joints);
        let seq = published.header.seq;
        let mut body = Vec::with_capacity(16 + 8 * pieces.len());
        let ticks = chain.map(|c| self.ticks_of(c)).unwrap_or_default();
        for (p, selection) in &pieces {
            let num = p.pose.avatar_num;
            let (hash, levels) = now.get(&num)?;
            let selection = selection.as_deref();
            let levels = cut(levels, selection, weights);
            if chain.is_none() {
                frame2::encode_key(num, *hash, &levels, &mut body);
                continue;
            }
            let history: Vec<Cow<'_, QuantPose>> = ticks
                .iter()
                .map_while(|t| t.get(&num).filter(|(h, _)| h == hash))
                .map(|(_, l)| cut(l, selection, weights))
                .collect();
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
                (p.pose.hash, Arc::new(QuantPose::from_pose(&p.pose))),
            )
        })
        .collect()
}
