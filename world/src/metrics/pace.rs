//! Counters of the adaptive frame rate (`posecast_stream::pace`): how many connections send at
//! each step, and how often rates went down and up. Kept apart (`Metrics::pace`) like the
//! network counters.

use crate::metrics::{GaugeU64, labelled_counters};
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::registry::Registry;

/// The adaptive rate's steps, frames per 60 ticks (the stream layer's, one list).
pub use posecast_stream::pace::STEPS;
use posecast_stream::pace::{Cause, Change};

/// Labels of [`STEPS`].
const RATES: [&str; STEPS.len()] = [
    "60", "45", "30", "24", "20", "15", "12", "10", "8", "6", "5", "4", "3", "2", "1",
];

/// Connections per step and rate changes. Relaxed atomics: exact totals, no ordering.
#[derive(Debug)]
pub struct PaceCounters {
    /// By step (index into [`STEPS`]).
    at: [GaugeU64; STEPS.len()],
    lowered: Counter,
    raised: Counter,
    /// Cuts by cause (in the order of [`Cause::ALL`]).
    cuts: [Counter; Cause::ALL.len()],
    /// Round-trip pings sent.
    pings: Counter,
}

impl PaceCounters {
    /// All zero, registered in `registry`.
    pub(crate) fn new(registry: &mut Registry) -> Self {
        let family = Family::<[(&'static str, &'static str); 1], GaugeU64>::default();
        let at = RATES.map(|r| family.get_or_create(&[("per_60_ticks", r)]).clone());
        registry.register(
            "connection_rate",
            "Websocket connections by their adaptive frame rate (frames per 60 ticks)",
            family,
        );
        let [lowered, raised] = labelled_counters(
            registry,
            "rate_changes",
            "Adaptive frame rate changes of websocket connections",
            "way",
            ["down", "up"],
        );
        let cuts = labelled_counters(
            registry,
            "rate_cuts",
            "Adaptive frame rate cuts by what they answered: round_trips (a queue past the socket), socket (the kernel's figures), unanswered (a late ping), superseded (frames replaced while the socket held the writer), path (a cut shared by the client address's connections)",
            "cause",
            Cause::ALL.map(Cause::label),
        );
        let pings = Counter::default();
        registry.register(
            "probe_pings",
            "Round-trip pings sent to subscribed websocket connections (the adaptive rate's probes; a settled connection pings once a second)",
            pings.clone(),
        );
        Self {
            at,
            lowered,
            raised,
            cuts,
            pings,
        }
    }

    /// A connection started at the first step.
    pub fn opened(&self) {
        self.at[0].inc();
    }

    /// A connection at step `level` closed.
    pub fn closed(&self, level: usize) {
        if let Some(g) = self.at.get(level) {
            g.dec();
        }
    }

    /// A connection's rate changed.
    pub fn changed(&self, change: Change) {
        let Change { from, to, cause } = change;
        if let Some(cause) = cause
            && let Some(i) = Cause::ALL.iter().position(|c| *c == cause)
        {
            self.cuts[i].inc();
        }
        if let (Some(a), Some(b)) = (self.at.get(from), self.at.get(to)) {
            a.dec();
            b.inc();
        }
        if to > from {
            self.lowered.inc();
        } else {
            self.raised.inc();
        }
    }

    /// A probe's ping went out.
    pub fn pinged(&self) {
        self.pings.inc();
    }

    /// Connections at step `level` now.
    #[must_use]
    pub fn at(&self, level: usize) -> u64 {
        self.at.get(level).map_or(0, GaugeU64::get)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn labels_are_the_steps() {
        for (label, step) in RATES.iter().zip(STEPS) {
            assert_eq!(label.parse::<u32>().unwrap(), step);
        }
    }
}
