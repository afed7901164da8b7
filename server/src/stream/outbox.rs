//! A connection's outbox: what the writer task sends next, bounded whatever the client does.
//!
//! Control messages (welcome, descriptions, acks, errors, pongs) queue in order up to
//! [`MAX_CONTROL`]; a client that lets that many pile up is not reading and is disconnected.
//! Pose frames do not queue: each subscribed scene has one slot holding at most the newest
//! keyframe not yet sent and the newest frame after it, so a slow reader gets the newest pose,
//! never a growing backlog, and never a delta whose keyframe it lacks. Everything sits behind one
//! lock so the writer takes control messages and frames together in publication order (a
//! description always reaches the client before the first frame that needs it).

use axum::extract::ws::{CloseFrame, Message};
use std::collections::{BTreeMap, VecDeque};
use std::sync::Mutex;
use std::sync::atomic::{AtomicU64, Ordering};
use tokio::sync::Notify;

/// Control messages a connection may have waiting before it counts as stalled.
pub const MAX_CONTROL: usize = 256;

/// A frame handed to a subscriber.
#[derive(Debug, Clone)]
pub struct OutFrame {
    /// The websocket message (shared bytes: cloning is a reference count).
    pub message: Message,
    /// Whether deltas after it refer to it.
    pub key: bool,
}

#[derive(Debug, Default)]
struct Slot {
    key: Option<OutFrame>,
    latest: Option<OutFrame>,
}

#[derive(Debug, Default)]
struct State {
    control: VecDeque<Message>,
    frames: BTreeMap<u32, Slot>,
    closed: bool,
    overflowed: bool,
    /// The close frame asked for by [`Outbox::close_with`], if any.
    close_frame: Option<CloseFrame>,
}

/// One connection's pending output.
#[derive(Debug, Default)]
pub struct Outbox {
    state: Mutex<State>,
    notify: Notify,
    dropped: AtomicU64,
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

impl Outbox {
    /// An empty outbox.
    #[must_use]
    pub fn new() -> Self {
        Self::default()
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, State> {
        // A panic while holding this lock cannot leave the state inconsistent (every update is
        // a single push or replace), so a poisoned lock is still usable.
        self.state
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// Queues a control message. Returns `false` (and marks the outbox overflowed, which makes
    /// the writer close the connection) when [`MAX_CONTROL`] are already waiting.
    pub fn push_control(&self, message: Message) -> bool {
        let mut s = self.lock();
        if s.closed {
            return false;
        }
        if s.control.len() >= MAX_CONTROL {
            s.overflowed = true;
            s.closed = true;
            drop(s);
            self.notify.notify_one();
            return false;
        }
        s.control.push_back(message);
        drop(s);
        self.notify.notify_one();
        true
    }

    /// Offers scene `scene_num`'s newest frame. A keyframe replaces everything pending for the
    /// scene; a delta replaces only a pending delta (the keyframe it needs stays).
    pub fn push_frame(&self, scene_num: u32, frame: OutFrame) {
        let mut s = self.lock();
        if s.closed {
            return;
        }
        let slot = s.frames.entry(scene_num).or_default();
        let mut replaced = 0;
        if frame.key {
            replaced += u64::from(slot.key.take().is_some());
            replaced += u64::from(slot.latest.take().is_some());
            slot.key = Some(frame);
        } else {
            replaced += u64::from(slot.latest.replace(frame).is_some());
        }
        drop(s);
        if replaced > 0 {
            self.dropped.fetch_add(replaced, Ordering::Relaxed);
        }
        self.notify.notify_one();
    }

    /// Forgets pending frames of a scene (on unsubscribe).
    pub fn clear_scene(&self, scene_num: u32) {
        self.lock().frames.remove(&scene_num);
    }

    /// Frames waiting to be sent (at most two per subscribed scene, whatever the client does).
    #[must_use]
    pub fn pending_frames(&self) -> usize {
        self.lock()
            .frames
            .values()
            .map(|f| usize::from(f.key.is_some()) + usize::from(f.latest.is_some()))
            .sum()
    }

    /// Frames replaced before the writer could send them (the client read too slowly).
    #[must_use]
    pub fn dropped_frames(&self) -> u64 {
        self.dropped.load(Ordering::Relaxed)
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
                        return Next::Send(s.control.drain(..).collect());
                    }
                    return Next::Close {
                        overflowed: s.overflowed,
                    };
                }
                if !s.control.is_empty()
                    || s.frames
                        .values()
                        .any(|f| f.key.is_some() || f.latest.is_some())
                {
                    let mut out: Vec<Message> = s.control.drain(..).collect();
                    for slot in s.frames.values_mut() {
                        out.extend(slot.key.take().map(|f| f.message));
                        out.extend(slot.latest.take().map(|f| f.message));
                    }
                    return Next::Send(out);
                }
            }
            notified.await;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use bytes::Bytes;

    fn frame(byte: u8, key: bool) -> OutFrame {
        OutFrame {
            message: Message::Binary(Bytes::from(vec![byte])),
            key,
        }
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
        // Control first, then the keyframe, then only the newest delta.
        assert_eq!(bytes(o.next().await), vec![b'T', 1, 3]);
        assert_eq!(o.dropped_frames(), 1);
        o.push_frame(1, frame(4, false));
        o.push_frame(1, frame(5, true));
        o.push_frame(1, frame(6, false));
        assert_eq!(bytes(o.next().await), vec![5, 6]);
        assert_eq!(o.dropped_frames(), 2);
    }

    #[tokio::test]
    async fn control_overflow_closes() {
        let o = Outbox::new();
        for _ in 0..MAX_CONTROL {
            assert!(o.push_control(Message::Text("x".into())));
        }
        assert!(!o.push_control(Message::Text("x".into())));
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
}
