//! One clock for every connection's round-trip probes ([`crate::pace`]).
//!
//! A subscribed connection probes its link every [`PROBE_INTERVAL`]. With a timer of its own
//! per connection, 2,000 viewers were 10,000 timer firings and re-armings a second in tokio's
//! timer wheel; here one task ticks [`PHASES`] channels in turn, each every
//! [`PROBE_INTERVAL`], and a connection waits on its phase's channel (no timer of its own).
//! The phases spread the probes over the interval, so 2,000 pings do not leave at one instant
//! and come back as one burst that would read as queueing.

use crate::pace::PROBE_INTERVAL;
use std::sync::{Arc, OnceLock, Weak};
use tokio::sync::watch;

/// How many groups the connections' probes are spread over, one every
/// `PROBE_INTERVAL / PHASES`.
pub const PHASES: usize = 8;

/// The probe clock a server's connections share.
#[derive(Debug)]
pub struct ProbeClock {
    phases: Vec<watch::Sender<u64>>,
    started: OnceLock<()>,
}

impl Default for ProbeClock {
    fn default() -> Self {
        Self {
            phases: (0..PHASES).map(|_| watch::Sender::new(0)).collect(),
            started: OnceLock::new(),
        }
    }
}

impl ProbeClock {
    /// A clock whose task starts with its first subscriber.
    #[must_use]
    pub fn new() -> Arc<Self> {
        Arc::new(Self::default())
    }

    /// The channel connection `conn` probes on: it changes every [`PROBE_INTERVAL`], in the
    /// connection's phase. Starts the clock's task on first use (in the calling runtime); the
    /// task ends once the clock is dropped.
    #[must_use]
    pub fn subscribe(self: &Arc<Self>, conn: u64) -> watch::Receiver<u64> {
        self.started.get_or_init(|| {
            tokio::spawn(run(Arc::downgrade(self)));
        });
        self.phases[(conn % PHASES as u64) as usize].subscribe()
    }
}

async fn run(clock: Weak<ProbeClock>) {
    let mut ticks = tokio::time::interval(PROBE_INTERVAL / PHASES as u32);
    ticks.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let mut phase = 0;
    loop {
        ticks.tick().await;
        let Some(clock) = clock.upgrade() else {
            return;
        };
        clock.phases[phase].send_modify(|n| *n = n.wrapping_add(1));
        phase = (phase + 1) % PHASES;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    /// Under tokio's paused clock: each phase's channel changes once per probe interval, the
    /// phases a `PROBE_INTERVAL / PHASES` apart, and the task ends with the clock.
    #[tokio::test(start_paused = true)]
    async fn each_phase_ticks_once_per_interval_spread_over_it() {
        let clock = ProbeClock::new();
        let mut first = clock.subscribe(0);
        let mut second = clock.subscribe(1);
        let start = tokio::time::Instant::now();
        first.changed().await.unwrap();
        assert_eq!(start.elapsed(), Duration::ZERO);
        second.changed().await.unwrap();
        assert_eq!(start.elapsed(), PROBE_INTERVAL / PHASES as u32);
        for k in 1..=3u32 {
            first.changed().await.unwrap();
            assert_eq!(start.elapsed(), PROBE_INTERVAL * k);
        }
        // Phase 0 changed 4 times; nothing else ticks it in between.
        assert_eq!(*first.borrow(), 4);
        let weak = Arc::downgrade(&clock);
        drop(clock);
        // The task notices at its next tick and drops the senders: the channel closes.
        assert!(first.changed().await.is_err());
        assert!(weak.upgrade().is_none());
    }
}
