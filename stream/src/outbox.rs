//! A connection's outbox: what the writer task sends next, bounded whatever the client does.
//!
//! Control messages (welcome, descriptions, acks, errors, pongs) queue in order, bounded in
//! **bytes** by [`MAX_CONTROL_BYTES`]: a client that lets that much pile up is not reading and
//! is disconnected. A subscription's own descriptions (queued by [`Outbox::push_snapshot`]) do
//! not count towards that bound: a scene of 1,000 avatars sends ~5 MB of them at once to a
//! client that has done nothing wrong. They are bounded another way — one pending snapshot per
//! subscribed scene (a new subscription to the scene, or leaving it, drops the unsent one), so
//! they never exceed one description per avatar the client can watch, and the bytes are the
//! scene's cached description messages, shared by every subscriber.
//!
//! Pose frames barely queue: each subscribed scene has one slot holding at most the newest
//! keyframe not yet sent and the newest [`MAX_PENDING_DELTAS`] frames after it, so a writer
//! woken a tick late loses nothing while a slow reader gets the newest pose,
//! never a growing backlog, and never a delta whose keyframe it lacks. Everything sits behind one
//! lock so the writer takes control messages and frames together in publication order (a
//! description always reaches the client before the first frame that needs it).

use super::pace::Pace;
use crate::Counters;
use crate::direct::{DirectWrite, framed, header, parts};
use axum::extract::ws::{CloseFrame, Message};
use bytes::Bytes;
use posecast_proto::frame2;
use std::collections::{BTreeMap, VecDeque};
use std::io::IoSlice;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use tokio::sync::Notify;

/// Bytes of control messages a connection may have waiting before it counts as stalled.
///
/// Why 4 MiB: it comes on top of the kernel's socket buffers (a few MiB more on Linux), so a
/// client is only closed once it is ~8 MiB of acks, errors, pongs and live scene changes behind
/// — far more than a reading client ever has waiting (the writer takes everything queued each
/// time it wakes), yet small enough that a few thousand stalled connections cannot exhaust the
/// server's memory. Frames are not counted (they replace each other), nor are a subscription's
/// own descriptions (see the module docs).
pub const MAX_CONTROL_BYTES: usize = 4 << 20;

/// A frame handed to a subscriber.
#[derive(Debug, Clone)]
pub struct OutFrame {
    /// The websocket message (shared bytes: cloning is a reference count).
    pub message: Message,
    /// Whether deltas after it refer to it.
    pub key: bool,
}

/// Deltas a scene's slot holds behind its keyframe before the oldest is dropped: two, so a
/// writer that wakes a tick late (a busy machine) still delivers every frame, while a client
/// that does not keep up gets at most two ticks of backlog, never more.
pub const MAX_PENDING_DELTAS: usize = 2;

/// What a wire v2 delta pushed now may refer to ([`Outbox::chain`]).
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub struct Chain {
    /// The ticks of the frames the client will hold, newest first.
    pub ticks: Vec<u64>,
    /// The tick of the pending delta the frame will replace (not in `ticks`), if any.
    pub replacing: Option<u64>,
}

#[derive(Debug, Default)]
struct Slot {
    key: Option<OutFrame>,
    deltas: VecDeque<OutFrame>,
    /// Wire v2: the ticks of the frames the client will have decoded once everything pending
    /// is sent, newest first (what a v2 delta may refer to); empty until a v2 keyframe.
    chain: Vec<u64>,
}

#[derive(Debug)]
struct Queued {
    message: Message,
    bytes: usize,
    /// The scene whose subscription snapshot this belongs to (exempt from the byte bound).
    snapshot: Option<u32>,
}

#[derive(Debug, Default)]
struct State {
    control: VecDeque<Queued>,
    /// Bytes of queued control messages that count towards [`MAX_CONTROL_BYTES`].
    control_bytes: usize,
    /// Bytes of queued subscription snapshots (not counted).
    snapshot_bytes: usize,
    frames: BTreeMap<u32, Slot>,
    closed: bool,
    overflowed: bool,
    /// The close frame asked for by [`Outbox::close_with`], if any.
    close_frame: Option<CloseFrame>,
    /// The socket this outbox writes into itself ([`Outbox::attach_direct`]), if any.
    direct: Option<Direct>,
}

/// An outbox's own socket ([`Outbox::attach_direct`]) and what of its output is on the way.
#[derive(Debug)]
struct Direct {
    socket: Arc<dyn DirectWrite>,
    metrics: Arc<dyn Counters>,
    /// Bytes of a message the socket took part of: they go before anything else.
    unsent: VecDeque<Bytes>,
    /// The socket's buffer is full: the writer task waits for room; nothing is written
    /// until it has.
    held: bool,
    /// The socket failed: nothing more is written.
    failed: bool,
}

/// Where a queued message sits (what [`Outbox::pump`] takes once the socket took it).
#[derive(Debug, Clone, Copy)]
enum Src {
    Unsent,
    Control,
    Key(u32),
    Delta(u32),
}

/// What an outbox with its own socket waits on ([`crate::direct::run_direct`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DirectState {
    /// Everything queued is written.
    Idle,
    /// The socket's buffer is full: wait until it has room, then [`Outbox::resume`].
    Held,
    /// The socket failed.
    Failed,
    /// The outbox closed: write the close frame ([`Outbox::queue_close_frame`]).
    Closed,
}

/// Messages one vectored write takes at most (two slices each; Linux takes 1,024 slices).
const WRITE_BATCH: usize = 64;

impl State {
    fn drop_snapshot(&mut self, scene_num: u32) {
        let mut freed = 0;
        self.control.retain(|q| {
            let keep = q.snapshot != Some(scene_num);
            if !keep {
                freed += q.bytes;
            }
            keep
        });
        self.snapshot_bytes -= freed;
    }
}

/// One connection's pending output.
#[derive(Debug, Default)]
pub struct Outbox {
    state: Mutex<State>,
    notify: Notify,
    dropped: AtomicU64,
    /// Whether the writer is held by the socket: its last write or flush found the socket's
    /// buffer full and waits for room ([`Outbox::set_socket_full`]).
    socket_full: std::sync::atomic::AtomicBool,
    /// Frames replaced while the socket held the writer: the link's backpressure, not the
    /// writer's own lateness (a writer not scheduled in time on a busy host).
    dropped_held: AtomicU64,
    /// The connection's adaptive frame rate (its subscriptions' frames follow it).
    pace: Pace,
    /// Frames go out as datagrams, which may be lost (a WebTransport session): the feed then
    /// counts a keyframe as the client's only once the client acknowledged it
    /// ([`Outbox::key_acked`]), and sends wire v1 frames (whose deltas refer to the keyframe,
    /// never to the frame before, so a lost delta costs its own tick only).
    datagrams: std::sync::atomic::AtomicBool,
    /// The keyframes the client acknowledged, by scene number.
    acked_keys: Mutex<std::collections::HashMap<u32, KeyAcks>>,
    /// Protocol version 8: the smoothed time from sending a frame to its acknowledgement, µs
    /// (0: none measured yet).
    frame_rtt_us: AtomicU64,
    /// Protocol version 8: the least time from sending a frame to its acknowledgement since
    /// [`Outbox::take_frame_rtt_floor`] last took it, µs (0: none since).
    frame_rtt_floor_us: AtomicU64,
}

/// How long a keyframe sent as datagrams (protocol version 8) waits for its acknowledgement,
/// in round trips from sending a frame to its acknowledgement, before another goes.
pub const KEY_RETRY_RTTS: u32 = 2;

/// The least a keyframe sent as datagrams waits for its acknowledgement.
pub const KEY_RETRY_MIN: std::time::Duration = std::time::Duration::from_millis(50);

/// What a keyframe sent as datagrams waits for its acknowledgement before a round trip is
/// measured.
pub const KEY_RETRY_UNMEASURED: std::time::Duration = std::time::Duration::from_millis(250);

/// Split keyframes whose acknowledgements an outbox follows, per scene: older ones are
/// forgotten (a client that lost their parts gets a newer keyframe anyway).
const SPLIT_KEYS_KEPT: usize = 4;

/// Scenes whose acknowledgements an outbox keeps: a client naming more scene numbers than any
/// connection subscribes to (a flood of made-up acknowledgements) is ignored past it, so it
/// cannot grow the server's memory.
const ACKED_SCENES_KEPT: usize = 1024;

/// The keyframe acknowledgements of one scene of a datagram outbox.
#[derive(Debug, Default)]
struct KeyAcks {
    /// The newest keyframe tick the client holds whole: every avatar it was sent with.
    held: Option<u64>,
    /// Keyframes sent cut by avatar into several datagrams, by tick: their avatars not
    /// acknowledged yet (the newest [`SPLIT_KEYS_KEPT`]).
    split: std::collections::BTreeMap<u64, std::collections::HashSet<u32>>,
    /// The newest split keyframe forgotten: acknowledgements up to it are not taken as whole.
    forgotten: Option<u64>,
    /// Protocol version 8: wire v2 frames sent and not yet acknowledged for every avatar, by
    /// tick (of the last [`frame2::DATAGRAM_REFERENCE_TICKS`] ticks).
    sent: std::collections::BTreeMap<u64, SentFrame>,
    /// Protocol version 8: the ticks of the newest frames acknowledged whole, newest first
    /// (at most [`frame2::MAX_DEPTH`]): what a delta may name.
    acked: Vec<u64>,
}

/// A wire v2 frame sent as datagrams (protocol version 8), until it is acknowledged.
#[derive(Debug)]
struct SentFrame {
    at: std::time::Instant,
    key: bool,
    /// Its avatars not acknowledged yet, when it went cut by avatar into several datagrams;
    /// `None`: it went whole, and any acknowledgement of it is of all of it.
    missing: Option<std::collections::HashSet<u32>>,
}

/// The acknowledgements of scene number `scene`, made if fewer than [`ACKED_SCENES_KEPT`]
/// scenes have any.
fn scene_acks(
    acks: &mut std::collections::HashMap<u32, KeyAcks>,
    scene: u32,
) -> Option<&mut KeyAcks> {
    if !acks.contains_key(&scene) && acks.len() >= ACKED_SCENES_KEPT {
        return None;
    }
    Some(acks.entry(scene).or_default())
}

/// What the writer should do next.
#[derive(Debug)]
pub enum Next {
    /// Send these, in order.
    Send(Vec<Message>),
    /// The outbox was closed (or overflowed): send a close frame and stop.
    Close {
        /// Whether it closed because the client did not read.
        overflowed: bool,
    },
}

/// Payload bytes of a websocket message.
#[must_use]
pub fn message_len(m: &Message) -> usize {
    match m {
        Message::Binary(b) => b.len(),
        Message::Text(t) => t.len(),
        Message::Ping(b) | Message::Pong(b) => b.len(),
        Message::Close(c) => c.as_ref().map_or(0, |c| 2 + c.reason.len()),
    }
}

impl Outbox {
    /// An empty outbox.
    #[must_use]
    pub fn new() -> Self {
        Self::default()
    }

    /// An outbox whose frames go out as datagrams (see [`Outbox::key_acked`]).
    #[must_use]
    pub fn for_datagrams() -> Self {
        let outbox = Self::default();
        outbox
            .datagrams
            .store(true, std::sync::atomic::Ordering::Relaxed);
        outbox
    }

    /// Whether frames go out as datagrams.
    #[must_use]
    pub fn datagrams(&self) -> bool {
        self.datagrams.load(std::sync::atomic::Ordering::Relaxed)
    }

    fn key_acks(&self) -> std::sync::MutexGuard<'_, std::collections::HashMap<u32, KeyAcks>> {
        self.acked_keys
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// The keyframe of tick `seq` of scene number `scene` went out cut by avatar into several
    /// datagrams, with the chunks of `avatars`: the client holds it only once it acknowledged
    /// every one of them (any part may be lost). Sent again (the same tick), the avatars
    /// acknowledged already stay acknowledged.
    pub fn sent_split_key(&self, scene: u32, seq: u64, avatars: &[u32]) {
        let mut acks = self.key_acks();
        let Some(acks) = scene_acks(&mut acks, scene) else {
            return;
        };
        if acks.held.is_some_and(|held| held >= seq) || acks.split.contains_key(&seq) {
            return;
        }
        acks.split.insert(seq, avatars.iter().copied().collect());
        while acks.split.len() > SPLIT_KEYS_KEPT {
            if let Some((old, _)) = acks.split.pop_first() {
                acks.forgotten = acks.forgotten.max(Some(old));
            }
        }
    }

    /// The client acknowledged the chunks of `avatars` (none: all) in the keyframe of tick
    /// `seq` of scene number `scene` (it decoded them). A keyframe cut by avatar is held once
    /// all its avatars are acknowledged; a late acknowledgement of an older keyframe changes
    /// nothing.
    pub fn ack_key(&self, scene: u32, seq: u64, avatars: &[u32]) {
        let mut acks = self.key_acks();
        let Some(acks) = scene_acks(&mut acks, scene) else {
            return;
        };
        let whole = match acks.split.get_mut(&seq) {
            Some(missing) => {
                if avatars.is_empty() {
                    missing.clear();
                } else {
                    for a in avatars {
                        missing.remove(a);
                    }
                }
                missing.is_empty()
            }
            // A part of a split keyframe no longer followed: not known to be whole.
            None => acks.forgotten.is_none_or(|f| seq > f),
        };
        if whole {
            acks.held = acks.held.max(Some(seq));
            acks.split.retain(|&s, _| s > seq);
        }
    }

    /// The newest keyframe tick of scene number `scene` the client holds whole, as it
    /// acknowledged, if any.
    #[must_use]
    pub fn key_acked(&self, scene: u32) -> Option<u64> {
        self.key_acks().get(&scene).and_then(|a| a.held)
    }

    /// Protocol version 8: the wire v2 frame of tick `seq` of scene number `scene` (a keyframe
    /// when `key`) is going out as datagrams — whole (`parts` `None`), or cut by avatar with
    /// the avatars of every part. Frames older than [`frame2::DATAGRAM_REFERENCE_TICKS`] are
    /// forgotten (a delta never names them).
    pub fn datagram_frame_sent(&self, scene: u32, seq: u64, key: bool, parts: Option<&[u32]>) {
        let mut acks = self.key_acks();
        let Some(acks) = scene_acks(&mut acks, scene) else {
            return;
        };
        let frame = acks.sent.entry(seq).or_insert(SentFrame {
            at: std::time::Instant::now(),
            key,
            missing: None,
        });
        frame.missing = parts.map(|avatars| avatars.iter().copied().collect());
        let oldest = seq.saturating_sub(frame2::DATAGRAM_REFERENCE_TICKS);
        while acks
            .sent
            .first_key_value()
            .is_some_and(|(&s, _)| s < oldest)
        {
            acks.sent.pop_first();
        }
    }

    /// Protocol version 8: the client decoded the chunks of `avatars` (none: all, of a frame
    /// that went whole) in the frame of tick `seq` of scene number `scene`. Once every avatar it was sent with is
    /// acknowledged, a delta may name it. An acknowledgement of a frame not sent (or
    /// forgotten) changes nothing.
    pub fn ack_frame(&self, scene: u32, seq: u64, avatars: &[u32]) {
        let mut acks = self.key_acks();
        let Some(acks) = acks.get_mut(&scene) else {
            return;
        };
        let Some(frame) = acks.sent.get_mut(&seq) else {
            return;
        };
        // Any acknowledgement, of a part too, is a round trip of the path.
        let rtt = frame
            .at
            .elapsed()
            .as_micros()
            .clamp(1, u128::from(u32::MAX)) as u64;
        self.frame_rtt_floor_us
            .fetch_update(Ordering::Relaxed, Ordering::Relaxed, |f| {
                Some(if f == 0 { rtt } else { f.min(rtt) })
            })
            .ok();
        let whole = match &mut frame.missing {
            // A part names its avatars (at most `frame2::MAX_PART_AVATARS`): one naming none
            // says nothing of which part came.
            Some(missing) => {
                for a in avatars {
                    missing.remove(a);
                }
                missing.is_empty()
            }
            None => true,
        };
        if !whole {
            return;
        }
        acks.sent.remove(&seq);
        let at = acks.acked.partition_point(|&s| s > seq);
        if acks.acked.get(at) != Some(&seq) {
            acks.acked.insert(at, seq);
            acks.acked.truncate(frame2::MAX_DEPTH);
        }
        // RFC 6298's smoothing, ⅛ of each sample.
        let old = self.frame_rtt_us.load(Ordering::Relaxed);
        let new = if old == 0 {
            rtt
        } else {
            old - old / 8 + rtt / 8
        };
        self.frame_rtt_us.store(new.max(1), Ordering::Relaxed);
    }

    /// Protocol version 8: the least time from sending a frame as datagrams to its
    /// acknowledgement since the last call, if any came — the adaptive rate's round trip over
    /// datagrams: it rises with a queue on the path, and a lost datagram (never acknowledged)
    /// or a lost acknowledgement does not delay it, as a retransmission delays a pong on a
    /// stream.
    #[must_use]
    pub fn take_frame_rtt_floor(&self) -> Option<std::time::Duration> {
        match self.frame_rtt_floor_us.swap(0, Ordering::Relaxed) {
            0 => None,
            us => Some(std::time::Duration::from_micros(us)),
        }
    }

    /// Protocol version 8: whether a frame sent as datagrams awaits its acknowledgement.
    #[must_use]
    pub fn frames_in_flight(&self) -> bool {
        self.key_acks().values().any(|a| !a.sent.is_empty())
    }

    /// Protocol version 8: the ticks a delta of tick `seq` of scene number `scene` may name —
    /// the newest frames acknowledged whole, newest first, of the last
    /// [`frame2::DATAGRAM_REFERENCE_TICKS`] ticks. Empty: it needs a keyframe.
    #[must_use]
    pub fn datagram_refs(&self, scene: u32, seq: u64) -> Vec<u64> {
        self.key_acks().get(&scene).map_or_else(Vec::new, |a| {
            a.acked
                .iter()
                .copied()
                .filter(|&r| r < seq && seq - r < frame2::DATAGRAM_REFERENCE_TICKS)
                .collect()
        })
    }

    /// Protocol version 8: whether a keyframe of scene number `scene` may go now — none is on
    /// its way, unacknowledged, sent less than [`KEY_RETRY_RTTS`] round trips ago (at least
    /// [`KEY_RETRY_MIN`]). A lost keyframe goes again then; one on its way is not doubled
    /// each tick (a thin link would carry nothing else).
    #[must_use]
    pub fn datagram_key_due(&self, scene: u32) -> bool {
        let rtt = self.frame_rtt();
        let wait = rtt.map_or(KEY_RETRY_UNMEASURED, |r| {
            (r * KEY_RETRY_RTTS).max(KEY_RETRY_MIN)
        });
        self.key_acks().get(&scene).is_none_or(|a| {
            a.sent
                .values()
                .filter(|f| f.key)
                .all(|f| f.at.elapsed() >= wait)
        })
    }

    /// Protocol version 8: the smoothed time from sending a frame as datagrams to its
    /// acknowledgement, once one was measured.
    #[must_use]
    pub fn frame_rtt(&self) -> Option<std::time::Duration> {
        match self.frame_rtt_us.load(Ordering::Relaxed) {
            0 => None,
            us => Some(std::time::Duration::from_micros(us)),
        }
    }

    /// Forgets what scene number `scene`'s frames sent as datagrams were and which were
    /// acknowledged (protocol version 8): its next frame is a keyframe.
    fn forget_datagram_frames(&self, scene: u32) {
        if let Some(a) = self.key_acks().get_mut(&scene) {
            a.sent.clear();
            a.acked.clear();
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, State> {
        // A panic while holding this lock cannot leave the state inconsistent (every update is
        // a single push or replace), so a poisoned lock is still usable.
        self.state
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// Queues a control message. Returns `false` (and marks the outbox overflowed, which makes
    /// the writer close the connection) when it would take the counted control bytes past
    /// [`MAX_CONTROL_BYTES`]. A single message larger than the bound is still queued when
    /// nothing counted is waiting: the server made it, and a reading client gets it.
    pub fn push_control(&self, message: Message) -> bool {
        let bytes = message_len(&message);
        let mut s = self.lock();
        if s.closed {
            return false;
        }
        if s.control_bytes > 0 && s.control_bytes + bytes > MAX_CONTROL_BYTES {
            s.overflowed = true;
            s.closed = true;
            // Nothing queued will be sent: free it now rather than when the connection ends.
            s.control.clear();
            s.frames.clear();
            s.control_bytes = 0;
            s.snapshot_bytes = 0;
            drop(s);
            self.notify.notify_one();
            return false;
        }
        s.control_bytes += bytes;
        s.control.push_back(Queued {
            message,
            bytes,
            snapshot: None,
        });
        self.queued(s);
        true
    }

    /// Queues the descriptions a new subscription to scene `scene_num` starts with. They do
    /// not count towards [`MAX_CONTROL_BYTES`] (a big scene is not a stalled client); an unsent
    /// earlier snapshot of the same scene is dropped first, so at most one per scene waits.
    /// Returns `false` when the outbox is closed.
    pub fn push_snapshot(
        &self,
        scene_num: u32,
        messages: impl IntoIterator<Item = Message>,
    ) -> bool {
        let mut s = self.lock();
        if s.closed {
            return false;
        }
        s.drop_snapshot(scene_num);
        for message in messages {
            let bytes = message_len(&message);
            s.snapshot_bytes += bytes;
            s.control.push_back(Queued {
                message,
                bytes,
                snapshot: Some(scene_num),
            });
        }
        self.queued(s);
        true
    }

    /// Offers scene `scene_num`'s newest frame. A keyframe replaces everything pending for the
    /// scene; a delta replaces only a pending delta (the keyframe it needs stays).
    pub fn push_frame(&self, scene_num: u32, frame: OutFrame) {
        self.push_frame_at(scene_num, frame, true);
    }

    /// [`Outbox::push_frame`], leaving the write into an outbox's own socket to
    /// [`Outbox::flush`] (the fan-out queues a tick's frame everywhere, then spreads the
    /// writes over the runtime's threads: [`flush_all`]).
    pub fn push_frame_later(&self, scene_num: u32, frame: OutFrame) {
        self.push_frame_at(scene_num, frame, false);
    }

    /// Writes what waits into the outbox's own socket ([`Outbox::attach_direct`]), as much as
    /// it takes now; nothing without one.
    pub fn flush(&self) {
        let mut s = self.lock();
        if s.direct.is_some() && self.pump(&mut s) {
            drop(s);
            self.notify.notify_one();
        }
    }

    fn push_frame_at(&self, scene_num: u32, frame: OutFrame, now: bool) {
        let mut s = self.lock();
        if s.closed {
            return;
        }
        let slot = s.frames.entry(scene_num).or_default();
        let mut replaced = 0;
        if frame.key {
            replaced += u64::from(slot.key.take().is_some());
            replaced += slot.deltas.len() as u64;
            slot.deltas.clear();
            slot.key = Some(frame);
        } else {
            if slot.deltas.len() >= MAX_PENDING_DELTAS {
                slot.deltas.pop_front();
                replaced += 1;
            }
            slot.deltas.push_back(frame);
        }
        if replaced > 0 {
            self.count_dropped(replaced);
        }
        if now || s.direct.is_none() {
            self.queued(s);
        }
    }

    /// Wire v2: the ticks a delta pushed now may refer to — the frames the client will have
    /// decoded once everything pending is sent, newest first (at most
    /// [`posecast_proto::frame2::MAX_DEPTH`]). When [`MAX_PENDING_DELTAS`] deltas are already
    /// waiting (a client that does not keep up), the newest of them will be replaced, so the
    /// chain is the one without it, and [`Chain::replacing`] names it. `None` when there is
    /// no chain (no v2 keyframe yet, the scene was cleared, or nothing below the frame to be
    /// replaced): the subscriber needs a keyframe then.
    #[must_use]
    pub fn chain(&self, scene_num: u32) -> Option<Chain> {
        let s = self.lock();
        let slot = s.frames.get(&scene_num)?;
        if slot.chain.is_empty() {
            return None;
        }
        if slot.deltas.len() < MAX_PENDING_DELTAS {
            return Some(Chain {
                ticks: slot.chain.clone(),
                replacing: None,
            });
        }
        (slot.chain.len() >= 2).then(|| Chain {
            ticks: slot.chain[1..].to_vec(),
            replacing: Some(slot.chain[0]),
        })
    }

    /// Wire v2: offers scene `scene_num`'s frame of tick `seq`, as [`Outbox::push_frame`]
    /// does, and records it in the scene's chain ([`Outbox::chain`]): a keyframe starts a new
    /// chain, a delta extends it. A delta coded against a chain that was `replacing` the
    /// newest pending delta takes that delta's place — unless the writer sent it meanwhile,
    /// and then the frame refers to a chain the client no longer ends with: it is dropped
    /// (the next tick's delta follows what was sent). A delta that would otherwise replace a
    /// pending frame breaks the chain (the next frame must be a keyframe).
    pub fn push_chained(&self, scene_num: u32, frame: OutFrame, seq: u64, replacing: Option<u64>) {
        self.push_chained_at(scene_num, frame, seq, replacing, true);
    }

    /// [`Outbox::push_chained`], leaving the write to [`Outbox::flush`]
    /// ([`Outbox::push_frame_later`]).
    pub fn push_chained_later(
        &self,
        scene_num: u32,
        frame: OutFrame,
        seq: u64,
        replacing: Option<u64>,
    ) {
        self.push_chained_at(scene_num, frame, seq, replacing, false);
    }

    fn push_chained_at(
        &self,
        scene_num: u32,
        frame: OutFrame,
        seq: u64,
        replacing: Option<u64>,
        now: bool,
    ) {
        let mut s = self.lock();
        if s.closed {
            return;
        }
        let slot = s.frames.entry(scene_num).or_default();
        let key = frame.key;
        if key {
            slot.chain.clear();
        } else if let Some(newest) = replacing {
            let pending =
                slot.deltas.len() >= MAX_PENDING_DELTAS && slot.chain.first() == Some(&newest);
            if !pending {
                return;
            }
            slot.deltas.pop_back();
            slot.chain.remove(0);
            slot.deltas.push_back(frame);
            slot.chain.insert(0, seq);
            slot.chain.truncate(posecast_proto::frame2::MAX_DEPTH);
            self.count_dropped(1);
            if now || s.direct.is_none() {
                self.queued(s);
            }
            return;
        }
        let broke = !key && slot.deltas.len() >= MAX_PENDING_DELTAS;
        if broke {
            slot.chain.clear();
        } else {
            slot.chain.insert(0, seq);
            slot.chain.truncate(posecast_proto::frame2::MAX_DEPTH);
        }
        drop(s);
        self.push_frame_at(scene_num, frame, now);
    }

    /// Wire v2: the next frame of the scene must be a keyframe (what was pushed last is not
    /// what the other subscribers' deltas refer to).
    pub fn break_chain(&self, scene_num: u32) {
        if let Some(slot) = self.lock().frames.get_mut(&scene_num) {
            slot.chain.clear();
        }
        self.forget_datagram_frames(scene_num);
    }

    /// Forgets what is pending for a scene: its frames and its unsent subscription snapshot
    /// (on unsubscribe, or before a new subscription to it).
    pub fn clear_scene(&self, scene_num: u32) {
        let mut s = self.lock();
        s.frames.remove(&scene_num);
        s.drop_snapshot(scene_num);
        drop(s);
        self.forget_datagram_frames(scene_num);
    }

    /// Frames waiting to be sent (at most `1 + MAX_PENDING_DELTAS` per subscribed scene,
    /// whatever the client does).
    #[must_use]
    pub fn pending_frames(&self) -> usize {
        self.lock()
            .frames
            .values()
            .map(|f| usize::from(f.key.is_some()) + f.deltas.len())
            .sum()
    }

    /// Bytes of control messages waiting that count towards [`MAX_CONTROL_BYTES`] (never more).
    #[must_use]
    pub fn control_bytes(&self) -> usize {
        self.lock().control_bytes
    }

    /// Bytes of subscription descriptions waiting (not counted towards the bound).
    #[must_use]
    pub fn snapshot_bytes(&self) -> usize {
        self.lock().snapshot_bytes
    }

    /// The connection's adaptive frame rate.
    #[must_use]
    pub fn pace(&self) -> &Pace {
        &self.pace
    }

    /// Frames replaced before the writer could send them (the client read too slowly, or the
    /// writer ran late).
    #[must_use]
    pub fn dropped_frames(&self) -> u64 {
        self.dropped.load(Ordering::Relaxed)
    }

    /// Of [`Outbox::dropped_frames`], those replaced while the socket held the writer (its
    /// buffer full: the link or the reader does not keep up). The adaptive rate counts only
    /// these: a writer that was merely not scheduled in time (the server's host is busy) loses
    /// frames to the next ones without the link being at fault, and cutting the rate would
    /// not bring them back (issue 38: on a busy host that cut 45 % of the frames of 2,000
    /// viewers whose links had room).
    #[must_use]
    pub fn dropped_while_held(&self) -> u64 {
        self.dropped_held.load(Ordering::Relaxed)
    }

    /// The writer tells whether the socket holds it: `true` when a write or flush found the
    /// socket's buffer full (it waits for room), `false` once one went through.
    pub fn set_socket_full(&self, full: bool) {
        self.socket_full.store(full, Ordering::Relaxed);
    }

    /// A frame the link could not take: the transport held frames already (QUIC's congestion
    /// control), so this one was dropped unsent ([`Outbox::dropped_frames`] counts it).
    pub fn dropped_by_link(&self) {
        self.dropped.fetch_add(1, Ordering::Relaxed);
    }

    fn count_dropped(&self, replaced: u64) {
        self.dropped.fetch_add(replaced, Ordering::Relaxed);
        if self.socket_full.load(Ordering::Relaxed) {
            self.dropped_held.fetch_add(replaced, Ordering::Relaxed);
        }
    }

    /// Whether the outbox closed because the client stopped reading.
    #[must_use]
    pub fn overflowed(&self) -> bool {
        self.lock().overflowed
    }

    /// Marks the outbox closed: the writer sends a close frame and stops.
    pub fn close(&self) {
        self.lock().closed = true;
        self.notify.notify_one();
    }

    /// Closes like [`Outbox::close`], asking the writer to send this close code and reason
    /// (e.g. 1009 after an oversized message, 1001 at shutdown). The first request wins, and
    /// an overflow still closes with its own code: the client was not reading, so no explanation
    /// can reach it anyway.
    pub fn close_with(&self, code: u16, reason: &str) {
        let mut s = self.lock();
        if !s.closed {
            s.closed = true;
            s.close_frame = Some(CloseFrame {
                code,
                reason: reason.into(),
            });
        }
        drop(s);
        self.notify.notify_one();
    }

    /// The close frame [`Outbox::close_with`] asked for (`None`: a plain close or an overflow).
    #[must_use]
    pub fn close_frame(&self) -> Option<CloseFrame> {
        let s = self.lock();
        if s.overflowed {
            None
        } else {
            s.close_frame.clone()
        }
    }

    /// Makes the outbox write into `socket` itself from now on: whatever queues a message
    /// writes it at once when the socket takes it ([`crate::direct`]); the writer task
    /// ([`crate::direct::run_direct`]) acts only when the socket is full, failed, or the
    /// outbox closed. `metrics` counts what is written.
    pub fn attach_direct(&self, socket: Arc<dyn DirectWrite>, metrics: Arc<dyn Counters>) {
        let mut s = self.lock();
        s.direct = Some(Direct {
            socket,
            metrics,
            unsent: VecDeque::new(),
            held: false,
            failed: false,
        });
        self.queued(s);
    }

    /// Lets go of the socket [`Outbox::attach_direct`] gave (the connection is ending: its
    /// descriptor must close when the session's last handle goes, whoever still holds the
    /// outbox).
    pub fn detach_direct(&self) {
        self.lock().direct = None;
    }

    /// Whether the writer task of an outbox with its own socket has something to do.
    #[must_use]
    pub fn direct_state(&self) -> DirectState {
        let s = self.lock();
        match &s.direct {
            None => DirectState::Failed,
            Some(d) if d.failed => DirectState::Failed,
            Some(_) if s.closed => DirectState::Closed,
            Some(d) if d.held => DirectState::Held,
            Some(_) => DirectState::Idle,
        }
    }

    /// The socket has room again: writes what waits, as much as it takes. Returns `Held` when
    /// it filled up again, `Failed` when it failed, `Idle` otherwise.
    pub fn resume(&self) -> DirectState {
        let mut s = self.lock();
        let Some(d) = s.direct.as_mut() else {
            return DirectState::Failed;
        };
        d.held = false;
        self.pump(&mut s);
        match &s.direct {
            Some(d) if d.failed => DirectState::Failed,
            Some(d) if d.held => DirectState::Held,
            Some(_) => DirectState::Idle,
            None => DirectState::Failed,
        }
    }

    /// The outbox closed: its pending frames are dropped and the close frame queued behind
    /// its control messages (1008 alone when the client stopped reading; the close asked for
    /// by [`Outbox::close_with`], or 1000).
    pub fn queue_close_frame(&self) {
        let mut s = self.lock();
        s.frames.clear();
        let frame = if s.overflowed {
            s.control.clear();
            CloseFrame {
                code: 1008,
                reason: "client is not reading".into(),
            }
        } else {
            s.close_frame.clone().unwrap_or(CloseFrame {
                code: 1000,
                reason: "bye".into(),
            })
        };
        s.control.push_back(Queued {
            message: Message::Close(Some(frame)),
            bytes: 0,
            snapshot: None,
        });
    }

    /// Counts a wake-up of the writer task ([`Counters::writer_woke`]).
    pub fn count_writer_wake(&self) {
        if let Some(d) = &self.lock().direct {
            d.metrics.writer_woke();
        }
    }

    /// A future that resolves at the next wake-up of the writer (take it before checking the
    /// state, so a wake-up in between is not lost).
    pub fn notified(&self) -> tokio::sync::futures::Notified<'_> {
        self.notify.notified()
    }

    /// Something was queued: with a socket of its own the outbox writes it now (and wakes the
    /// writer only when the socket filled up or failed); otherwise the writer task wakes.
    fn queued(&self, mut s: std::sync::MutexGuard<'_, State>) {
        let wake = s.direct.is_none() || self.pump(&mut s);
        drop(s);
        if wake {
            self.notify.notify_one();
        }
    }

    /// Writes what is queued into the outbox's socket, in order (control messages, then each
    /// scene's frames), as much as the socket takes without waiting: one vectored write of
    /// each message's header and its own bytes (shared by every subscriber of a frame, never
    /// copied here). Returns whether the writer must wake: the socket just filled up (a part
    /// of a message that did not go waits in front of everything) or failed.
    fn pump(&self, s: &mut State) -> bool {
        let frames = !s.closed;
        loop {
            let Some(d) = s.direct.as_ref() else {
                return false;
            };
            if d.held || d.failed {
                return false;
            }
            // What goes, in order, where each sits; then their headers (the write's slices
            // borrow them), then the slices.
            let items: Vec<(Src, Item<'_>)> = pending(s, frames).take(WRITE_BATCH).collect();
            if items.is_empty() {
                self.set_socket_full(false);
                return false;
            }
            let mut heads: Vec<([u8; 10], usize)> = Vec::with_capacity(items.len());
            let mut closes: Vec<Bytes> = Vec::new();
            // (where it sits, its bytes framed, its payload's bytes)
            let mut meta: Vec<(Src, usize, usize)> = Vec::with_capacity(items.len());
            for (src, item) in &items {
                match item {
                    Item::Raw(b) => {
                        heads.push(([0; 10], 0));
                        meta.push((*src, b.len(), 0));
                    }
                    Item::Msg(m) => match parts(m) {
                        Some((opcode, body)) => {
                            let h = header(opcode, body.len());
                            meta.push((*src, h.1 + body.len(), body.len()));
                            heads.push(h);
                        }
                        None => {
                            let f = framed(m);
                            meta.push((*src, f.len(), message_len(m)));
                            heads.push(([0; 10], 0));
                            closes.push(f);
                        }
                    },
                }
            }
            let written = {
                let mut slices = Vec::with_capacity(items.len() * 2);
                let mut closes = closes.iter();
                for ((_, item), (h, n)) in items.iter().zip(&heads) {
                    match item {
                        Item::Raw(b) => slices.push(IoSlice::new(b)),
                        Item::Msg(m) => match parts(m) {
                            Some((_, body)) => {
                                slices.push(IoSlice::new(&h[..*n]));
                                if !body.is_empty() {
                                    slices.push(IoSlice::new(body));
                                }
                            }
                            None => {
                                if let Some(f) = closes.next() {
                                    slices.push(IoSlice::new(f));
                                }
                            }
                        },
                    }
                }
                d.socket.try_write_vectored(&slices)
            };
            drop(items);
            let mut n = match written {
                Ok(n) => n,
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
                Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {
                    self.hold(s);
                    return true;
                }
                Err(_) => {
                    if let Some(d) = s.direct.as_mut() {
                        d.failed = true;
                        d.unsent.clear();
                    }
                    s.control.clear();
                    s.frames.clear();
                    s.control_bytes = 0;
                    s.snapshot_bytes = 0;
                    return true;
                }
            };
            let batch = meta.len();
            let (mut messages, mut bytes, mut partial) = (0u64, 0u64, false);
            for (src, len, payload) in meta {
                if n == 0 {
                    partial = true;
                    break;
                }
                let taken = take(s, src);
                if !matches!(src, Src::Unsent) {
                    messages += 1;
                    bytes += payload as u64;
                }
                if n >= len {
                    n -= len;
                    continue;
                }
                // Part of it went: the rest goes before anything else.
                let rest = match taken {
                    Some(Taken::Raw(b)) => b.slice(n..),
                    Some(Taken::Msg(m)) => framed(&m).slice(n..),
                    None => Bytes::new(),
                };
                if let Some(d) = s.direct.as_mut() {
                    d.unsent.push_front(rest);
                }
                partial = true;
                break;
            }
            if let Some(d) = s.direct.as_ref()
                && messages > 0
            {
                d.metrics.sent(messages, bytes);
            }
            if partial {
                self.hold(s);
                return true;
            }
            if batch < WRITE_BATCH {
                self.set_socket_full(false);
                return false;
            }
        }
    }

    /// The socket's buffer is full: nothing is written until the writer saw it has room.
    fn hold(&self, s: &mut State) {
        if let Some(d) = s.direct.as_mut() {
            d.held = true;
        }
        self.set_socket_full(true);
    }

    /// Waits until there is something to send, then takes all of it.
    pub async fn next(&self) -> Next {
        loop {
            let notified = self.notify.notified();
            {
                let mut s = self.lock();
                if s.closed {
                    // A normal close still delivers what was queued before it (e.g. the error
                    // that explains the close); an overflowed client gets only the close.
                    if !s.overflowed && !s.control.is_empty() {
                        return Next::Send(take_control(&mut s));
                    }
                    return Next::Close {
                        overflowed: s.overflowed,
                    };
                }
                if !s.control.is_empty()
                    || s.frames
                        .values()
                        .any(|f| f.key.is_some() || !f.deltas.is_empty())
                {
                    let mut out = take_control(&mut s);
                    for slot in s.frames.values_mut() {
                        out.extend(slot.key.take().map(|f| f.message));
                        out.extend(slot.deltas.drain(..).map(|f| f.message));
                    }
                    return Next::Send(out);
                }
            }
            notified.await;
        }
    }
}

/// Outboxes below which [`flush_all`] writes on the calling thread alone.
const FLUSH_SHARD: usize = 64;

/// Flushes `outboxes` ([`Outbox::flush`]): the fan-out's writes of one tick. A few are
/// written on the calling thread; more are cut into one share per worker thread of the
/// runtime, each written by a task of its own, so the writes run on every core and the tick
/// does not wait for them. A tick that comes before a share is done finds its frames replacing
/// the ones still waiting, as a late writer's outbox does. Each outbox's bytes stay in order:
/// whoever flushes it writes under its lock.
///
/// A share runs to its end without yielding: a task that yields between slices goes behind
/// the runtime's local queue, and the ticker, woken from the global queue, waited up to
/// 85 ms on a busy host. (Shares on the blocking pool's threads instead oversubscribed the
/// cores: the ticks slowed to 38–48 a second.)
pub fn flush_all(mut outboxes: Vec<Arc<Outbox>>) {
    match tokio::runtime::Handle::try_current() {
        Ok(handle) if outboxes.len() >= 2 * FLUSH_SHARD => {
            let workers = match handle.runtime_flavor() {
                tokio::runtime::RuntimeFlavor::MultiThread => handle.metrics().num_workers(),
                _ => 1,
            };
            let share = outboxes.len().div_ceil(workers.max(1));
            while !outboxes.is_empty() {
                let rest = outboxes.split_off(outboxes.len().saturating_sub(share));
                handle.spawn(async move {
                    for o in rest {
                        o.flush();
                    }
                });
            }
        }
        _ => {
            for o in outboxes {
                o.flush();
            }
        }
    }
}

/// A queued message, borrowed where it sits.
enum Item<'a> {
    Raw(&'a Bytes),
    Msg(&'a Message),
}

/// A queued message taken from where it sat.
enum Taken {
    Raw(Bytes),
    Msg(Message),
}

/// What an outbox with its own socket writes next, in order: the rest of a message the
/// socket took part of, control messages, then each scene's keyframe and deltas (not when
/// `frames` is false: a closing outbox sends its control messages only).
fn pending(s: &State, frames: bool) -> impl Iterator<Item = (Src, Item<'_>)> {
    let unsent = s.direct.iter().flat_map(|d| d.unsent.iter());
    let frames = s
        .frames
        .iter()
        .filter(move |_| frames)
        .flat_map(|(&n, slot)| {
            slot.key
                .iter()
                .map(move |f| (Src::Key(n), Item::Msg(&f.message)))
                .chain(
                    slot.deltas
                        .iter()
                        .map(move |f| (Src::Delta(n), Item::Msg(&f.message))),
                )
        });
    unsent
        .map(|b| (Src::Unsent, Item::Raw(b)))
        .chain(
            s.control
                .iter()
                .map(|q| (Src::Control, Item::Msg(&q.message))),
        )
        .chain(frames)
}

/// Takes the first message of `src` (the one [`pending`] gave for it).
fn take(s: &mut State, src: Src) -> Option<Taken> {
    match src {
        Src::Unsent => s
            .direct
            .as_mut()
            .and_then(|d| d.unsent.pop_front())
            .map(Taken::Raw),
        Src::Control => {
            let q = s.control.pop_front()?;
            if q.snapshot.is_some() {
                s.snapshot_bytes -= q.bytes;
            } else {
                s.control_bytes -= q.bytes;
            }
            Some(Taken::Msg(q.message))
        }
        Src::Key(n) => s
            .frames
            .get_mut(&n)
            .and_then(|slot| slot.key.take())
            .map(|f| Taken::Msg(f.message)),
        Src::Delta(n) => s
            .frames
            .get_mut(&n)
            .and_then(|slot| slot.deltas.pop_front())
            .map(|f| Taken::Msg(f.message)),
    }
}

fn take_control(s: &mut State) -> Vec<Message> {
    s.control_bytes = 0;
    s.snapshot_bytes = 0;
    s.control.drain(..).map(|q| q.message).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use bytes::Bytes;

    /// A keyframe sent whole is held once acknowledged; one cut by avatar once every avatar
    /// of it is (by names, or by a whole acknowledgement), not before; a part acknowledged
    /// again after a resend stays acknowledged; an old split keyframe forgotten is not taken
    /// as whole; a late acknowledgement of an older keyframe changes nothing.
    #[test]
    fn a_split_keyframe_is_held_once_every_avatar_of_it_is_acknowledged() {
        let o = Outbox::for_datagrams();
        assert_eq!(o.key_acked(1), None);
        o.ack_key(1, 10, &[]);
        assert_eq!(o.key_acked(1), Some(10));
        o.sent_split_key(1, 20, &[1, 2, 3]);
        o.ack_key(1, 20, &[1, 3]);
        assert_eq!(
            o.key_acked(1),
            Some(10),
            "avatar 2's part was not acknowledged"
        );
        // Sent again: the parts acknowledged stay so.
        o.sent_split_key(1, 20, &[1, 2, 3]);
        o.ack_key(1, 20, &[2]);
        assert_eq!(o.key_acked(1), Some(20));
        o.ack_key(1, 15, &[]);
        assert_eq!(o.key_acked(1), Some(20));
        // Another scene is apart; a whole acknowledgement covers every part.
        o.sent_split_key(2, 5, &[1, 2]);
        assert_eq!(o.key_acked(2), None);
        o.ack_key(2, 5, &[]);
        assert_eq!(o.key_acked(2), Some(5));
        // Split keyframes past the ones followed are forgotten, and their parts never count.
        for seq in 30..30 + SPLIT_KEYS_KEPT as u64 + 1 {
            o.sent_split_key(1, seq, &[1, 2]);
        }
        o.ack_key(1, 30, &[1]);
        assert_eq!(o.key_acked(1), Some(20));
        o.ack_key(1, 31, &[1, 2]);
        assert_eq!(o.key_acked(1), Some(31));
        // A flood of made-up scene numbers is held to a bound; known scenes still count.
        for scene in 100..100 + 2 * ACKED_SCENES_KEPT as u32 {
            o.ack_key(scene, 1, &[]);
        }
        assert_eq!(o.key_acks().len(), ACKED_SCENES_KEPT);
        o.ack_key(1, 40, &[]);
        assert_eq!(o.key_acked(1), Some(40));
    }

    /// Protocol version 8: any acknowledgement of a frame sent — of one part of a split
    /// frame too — is a round trip; one of a frame never sent is not.
    #[test]
    fn a_part_acknowledged_is_a_round_trip() {
        let o = Outbox::for_datagrams();
        o.datagram_frame_sent(1, 10, true, Some(&[1, 2]));
        o.ack_frame(1, 99, &[]);
        assert_eq!(
            o.take_frame_rtt_floor(),
            None,
            "an acknowledgement of nothing sent"
        );
        assert_eq!(o.frame_rtt(), None);
        o.ack_frame(1, 10, &[2]);
        assert!(
            o.take_frame_rtt_floor().is_some(),
            "a part's acknowledgement"
        );
        assert!(
            o.datagram_refs(1, 11).is_empty(),
            "part of a frame is not a reference"
        );
        assert!(o.frames_in_flight());
    }

    /// Protocol version 8: a delta names only frames acknowledged for every avatar they went
    /// with, of the last [`frame2::DATAGRAM_REFERENCE_TICKS`] ticks; a keyframe on its way is
    /// not doubled; an acknowledgement of a frame never sent changes nothing; a cleared scene
    /// starts over.
    #[test]
    fn datagram_deltas_name_only_frames_acknowledged_whole_and_recent() {
        let o = Outbox::for_datagrams();
        o.datagram_frame_sent(1, 10, true, None);
        assert!(!o.datagram_key_due(1), "a keyframe on its way");
        assert!(o.datagram_refs(1, 11).is_empty());
        assert!(o.frames_in_flight());
        o.ack_frame(1, 10, &[]);
        assert_eq!(o.datagram_refs(1, 11), vec![10]);
        assert!(o.datagram_key_due(1) && !o.frames_in_flight());
        assert!(o.frame_rtt().is_some() && o.take_frame_rtt_floor().is_some());
        assert_eq!(o.take_frame_rtt_floor(), None, "taken");
        // Cut in two parts: held once both are acknowledged; one naming no avatar says
        // nothing of which part came.
        o.datagram_frame_sent(1, 11, false, Some(&[1, 2]));
        o.ack_frame(1, 11, &[1]);
        o.ack_frame(1, 11, &[]);
        assert_eq!(o.datagram_refs(1, 12), vec![10]);
        o.ack_frame(1, 11, &[2]);
        assert_eq!(o.datagram_refs(1, 12), vec![11, 10]);
        // Made up, or of another scene: nothing.
        o.ack_frame(1, 99, &[]);
        o.ack_frame(2, 12, &[]);
        assert_eq!(o.datagram_refs(1, 100), Vec::<u64>::new());
        assert_eq!(o.datagram_refs(1, 12), vec![11, 10]);
        // Only the last 48 ticks.
        let window = frame2::DATAGRAM_REFERENCE_TICKS;
        assert_eq!(o.datagram_refs(1, 10 + window), vec![11]);
        assert!(o.datagram_refs(1, 11 + window).is_empty());
        o.clear_scene(1);
        assert!(o.datagram_refs(1, 12).is_empty());
    }

    fn frame(byte: u8, key: bool) -> OutFrame {
        OutFrame {
            message: Message::Binary(Bytes::from(vec![byte])),
            key,
        }
    }

    fn text(len: usize) -> Message {
        Message::Text("x".repeat(len).into())
    }

    fn bytes(next: Next) -> Vec<u8> {
        match next {
            Next::Send(m) => m
                .into_iter()
                .map(|m| match m {
                    Message::Binary(b) => b[0],
                    Message::Text(_) => b'T',
                    _ => b'?',
                })
                .collect(),
            Next::Close { .. } => vec![b'C'],
        }
    }

    #[tokio::test]
    async fn newest_frame_wins_but_the_keyframe_a_delta_needs_is_kept() {
        let o = Outbox::new();
        o.push_frame(1, frame(1, true));
        o.push_frame(1, frame(2, false));
        o.push_frame(1, frame(3, false));
        assert!(o.push_control(Message::Text("d".into())));
        // Control first, then the keyframe, then the deltas: two fit behind it.
        assert_eq!(bytes(o.next().await), vec![b'T', 1, 2, 3]);
        assert_eq!(o.dropped_frames(), 0);
        // A keyframe replaces whatever is pending.
        o.push_frame(1, frame(4, false));
        o.push_frame(1, frame(5, true));
        o.push_frame(1, frame(6, false));
        assert_eq!(bytes(o.next().await), vec![5, 6]);
        assert_eq!(o.dropped_frames(), 1);
        // A third delta pushes out the oldest: the newest two are kept, with their keyframe.
        o.push_frame(1, frame(7, true));
        for d in 8..=10 {
            o.push_frame(1, frame(d, false));
        }
        assert_eq!(bytes(o.next().await), vec![7, 9, 10]);
        assert_eq!(o.dropped_frames(), 2);
    }

    #[tokio::test]
    async fn control_is_bounded_in_bytes_not_messages() {
        let o = Outbox::new();
        // Many small messages are fine while their bytes stay under the bound (the old bound
        // was 256 messages)...
        for _ in 0..10_000 {
            assert!(o.push_control(text(100)));
        }
        assert_eq!(o.control_bytes(), 1_000_000);
        // ...and the writer taking them resets the count.
        assert!(matches!(o.next().await, Next::Send(m) if m.len() == 10_000));
        assert_eq!(o.control_bytes(), 0);
        // Up to exactly the bound, then one byte more overflows.
        let chunk = 64 << 10;
        for _ in 0..MAX_CONTROL_BYTES / chunk {
            assert!(o.push_control(text(chunk)));
        }
        assert_eq!(o.control_bytes(), MAX_CONTROL_BYTES);
        assert!(!o.overflowed());
        assert!(!o.push_control(text(1)));
        assert!(o.overflowed());
        // Overflow frees what was queued and tells the writer to close, nothing else.
        assert_eq!(o.control_bytes(), 0);
        assert!(matches!(o.next().await, Next::Close { overflowed: true }));
        assert!(!o.push_control(text(1)));
    }

    #[tokio::test]
    async fn one_message_larger_than_the_bound_still_goes_to_a_reading_client() {
        let o = Outbox::new();
        assert!(o.push_control(text(MAX_CONTROL_BYTES + 1)));
        assert!(matches!(o.next().await, Next::Send(m) if m.len() == 1));
        assert!(o.push_control(text(MAX_CONTROL_BYTES + 1)));
        assert!(
            !o.push_control(text(1)),
            "a second one while it waits overflows"
        );
    }

    #[tokio::test]
    async fn a_snapshot_is_exempt_but_one_per_scene_and_a_stalled_client_still_overflows() {
        let o = Outbox::new();
        let big = MAX_CONTROL_BYTES / 4;
        // A subscription's descriptions far past the bound: not a stall.
        assert!(o.push_snapshot(7, (0..10).map(|_| text(big))));
        assert_eq!(o.snapshot_bytes(), 10 * big);
        assert_eq!(o.control_bytes(), 0);
        // Subscribing to the scene again replaces the unsent snapshot instead of adding to it.
        assert!(o.push_snapshot(7, (0..10).map(|_| text(big))));
        assert_eq!(o.snapshot_bytes(), 10 * big);
        // Another scene has its own.
        assert!(o.push_snapshot(8, [text(5)]));
        assert_eq!(o.snapshot_bytes(), 10 * big + 5);
        // Leaving a scene drops its unsent descriptions.
        o.clear_scene(7);
        assert_eq!(o.snapshot_bytes(), 5);
        // Counted messages still overflow at the bound, snapshot or not.
        assert!(o.push_snapshot(7, (0..10).map(|_| text(big))));
        for _ in 0..4 {
            assert!(o.push_control(text(big)));
        }
        assert!(!o.push_control(text(1)));
        assert!(matches!(o.next().await, Next::Close { overflowed: true }));
        o.close_with(1001, "late");
        assert_eq!(
            o.close_frame(),
            None,
            "an overflow keeps its own close code"
        );
    }

    #[tokio::test]
    async fn close_with_delivers_what_was_queued_then_the_first_requested_frame() {
        let o = Outbox::new();
        assert!(o.push_control(Message::Text("e".into())));
        o.close_with(1009, "too big");
        o.close_with(1001, "shutdown");
        o.close();
        assert!(!o.push_control(Message::Text("late".into())));
        assert_eq!(bytes(o.next().await), vec![b'T']);
        assert!(matches!(o.next().await, Next::Close { overflowed: false }));
        let frame = o.close_frame().unwrap();
        assert_eq!((frame.code, frame.reason.as_str()), (1009, "too big"));
    }

    #[tokio::test]
    async fn snapshots_keep_their_place_in_the_control_order() {
        let o = Outbox::new();
        assert!(o.push_control(Message::Text("subscribed".into())));
        assert!(o.push_snapshot(1, [Message::Text("d1".into()), Message::Text("d2".into())]));
        assert!(o.push_control(Message::Text("ack".into())));
        o.push_frame(1, frame(9, true));
        let Next::Send(m) = o.next().await else {
            panic!("expected messages")
        };
        let order: Vec<String> = m
            .iter()
            .map(|m| match m {
                Message::Text(t) => t.to_string(),
                Message::Binary(b) => format!("frame {}", b[0]),
                _ => String::new(),
            })
            .collect();
        assert_eq!(order, ["subscribed", "d1", "d2", "ack", "frame 9"]);
        assert_eq!(o.snapshot_bytes(), 0);
    }
}
