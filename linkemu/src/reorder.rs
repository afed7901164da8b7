//! What TCP makes of reordered segments for the application on top of it, per connection and
//! direction.
//!
//! A path that delays each packet independently (a jittery radio link, `netem delay 25ms
//! 10ms`, parallel paths) reorders them whenever the jitter is wider than the gap between two
//! segments of a connection. TCP hides the reordering from the application but not its cost:
//!
//! - **head-of-line holds**: the receiver hands bytes over in order, so a segment that arrives
//!   early waits for every segment ahead of it (`Order::place` never delivers a segment before
//!   the one ahead);
//! - **spurious retransmissions**: when a segment is overtaken by [`LinkConfig::reorder`] later
//!   segments of its connection (3 is the classic duplicate-ACK threshold; Linux's RACK can take
//!   a segment for lost after fewer), the sender takes it for lost: it retransmits it and cuts
//!   its congestion window. The retransmission is a duplicate the receiver drops; the cut is
//!   what the application sees. Modelled as a stall: the duplicate ACKs reach the sender
//!   one-way `delay` after the last overtaking segment arrived, and for one round trip
//!   (2 × `delay`) after that the sender sends nothing new — segments the proxy reads in that
//!   round trip leave when it ends. (Linux may undo the cut once the receiver reports the
//!   duplicate, a round trip later; a whole round trip without sending is the pessimistic
//!   end. The retransmitted copy's bytes are not counted against the link's rate.)
//!
//! A lost segment (`loss`) is already late by a retransmission timeout: it is not counted as
//! overtaken a second time.

use crate::LinkConfig;
use std::collections::VecDeque;
use tokio::time::Instant;

/// Segments remembered as possibly still to be overtaken (bounds the work per segment).
const TRACKED: usize = 64;

/// One direction of one connection: when its last segment arrives, the segments later ones
/// may still overtake, and the stall of a spurious retransmission.
#[derive(Debug)]
pub(crate) struct Order {
    /// When the segment ahead arrives (nothing is delivered before it).
    ahead: Instant,
    /// (unheld arrival, times overtaken) of recent segments.
    recent: VecDeque<(Instant, u32)>,
    /// A spurious retransmission's stall: segments leaving in `[from, until)` leave at `until`.
    stall: Option<(Instant, Instant)>,
}

/// Where a segment goes: when it arrives, and whether placing it made the sender retransmit
/// a segment spuriously.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Placed {
    pub arrives: Instant,
    pub spurious: bool,
}

impl Order {
    pub(crate) fn new(now: Instant) -> Self {
        Self {
            ahead: now,
            recent: VecDeque::new(),
            stall: None,
        }
    }

    /// Places a segment that leaves the bottleneck at `departs` and would arrive at `raw`
    /// (`departs` + its jittered delay, or + a retransmission timeout when `lost`): held
    /// behind the segment ahead, and behind a spurious retransmission's stall.
    pub(crate) fn place(
        &mut self,
        config: &LinkConfig,
        departs: Instant,
        raw: Instant,
        lost: bool,
    ) -> Placed {
        let mut raw = raw;
        if let Some((from, until)) = self.stall
            && departs >= from
        {
            if departs < until {
                // The sender was not sending: it leaves when the stall ends.
                raw += until - departs;
            } else {
                self.stall = None;
            }
        }
        let mut spurious = false;
        if let Some(threshold) = config.reorder
            && !lost
        {
            // The earliest a later segment can arrive: entries before it are safe.
            let earliest = departs + config.delay.saturating_sub(config.jitter);
            while self.recent.front().is_some_and(|(r, _)| *r <= earliest)
                || self.recent.len() >= TRACKED
            {
                self.recent.pop_front();
            }
            for (r, overtaken) in &mut self.recent {
                if raw < *r {
                    *overtaken += 1;
                    if *overtaken == threshold {
                        spurious = true;
                    }
                }
            }
            if spurious && self.stall.is_none() {
                // The duplicate ACKs reach the sender a one-way delay after this segment
                // arrived; it then sends nothing new for a round trip.
                let from = raw + config.delay;
                self.stall = Some((from, from + config.delay * 2));
            }
            self.recent.push_back((raw, 0));
        }
        let arrives = raw.max(self.ahead);
        self.ahead = arrives;
        Placed { arrives, spurious }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    const MS: Duration = Duration::from_millis(1);

    fn config(reorder: Option<u32>) -> LinkConfig {
        LinkConfig {
            delay: 25 * MS,
            jitter: 10 * MS,
            reorder,
            ..LinkConfig::default()
        }
    }

    #[test]
    fn a_segment_is_never_delivered_before_the_one_ahead() {
        let c = config(Some(3));
        let t0 = Instant::now();
        let mut o = Order::new(t0);
        // Leaves at 0 with 35 ms of delay; the next at 1 ms with 15 ms: held to 35 ms.
        assert_eq!(o.place(&c, t0, t0 + 35 * MS, false).arrives, t0 + 35 * MS);
        assert_eq!(
            o.place(&c, t0 + MS, t0 + 16 * MS, false).arrives,
            t0 + 35 * MS
        );
        assert_eq!(
            o.place(&c, t0 + 2 * MS, t0 + 40 * MS, false).arrives,
            t0 + 40 * MS
        );
    }

    #[test]
    fn three_overtaking_segments_stall_the_sender_for_a_round_trip() {
        let c = config(Some(3));
        let t0 = Instant::now();
        let mut o = Order::new(t0);
        o.place(&c, t0, t0 + 35 * MS, false);
        // Two overtake it: no retransmission yet.
        assert!(!o.place(&c, t0 + MS, t0 + 16 * MS, false).spurious);
        assert!(!o.place(&c, t0 + 2 * MS, t0 + 17 * MS, false).spurious);
        // The third does: its duplicate ACK reaches the sender at 18 + 25 = 43 ms, and it
        // sends nothing new until 43 + 50 = 93 ms.
        let third = o.place(&c, t0 + 3 * MS, t0 + 18 * MS, false);
        assert!(third.spurious);
        assert_eq!(third.arrives, t0 + 35 * MS);
        // A segment leaving at 50 ms (inside the stall) leaves at 93 ms instead: 43 ms later.
        let held = o.place(&c, t0 + 50 * MS, t0 + 75 * MS, false);
        assert_eq!(held.arrives, t0 + 118 * MS);
        // One leaving after the stall is not held by it.
        let after = o.place(&c, t0 + 100 * MS, t0 + 125 * MS, false);
        assert_eq!(after.arrives, t0 + 125 * MS);
    }

    #[test]
    fn without_the_model_only_the_in_order_hold_remains() {
        let c = config(None);
        let t0 = Instant::now();
        let mut o = Order::new(t0);
        o.place(&c, t0, t0 + 35 * MS, false);
        for i in 1..10 {
            assert!(!o.place(&c, t0 + i * MS, t0 + (15 + i) * MS, false).spurious);
        }
        assert_eq!(
            o.place(&c, t0 + 50 * MS, t0 + 75 * MS, false).arrives,
            t0 + 75 * MS
        );
    }
}
