//! Clock offset and round-trip time from ping/pong, NTP-style: for a ping sent at client time
//! `t0`, answered at server time `ts` and received at `t1`, `rtt = t1 − t0` and
//! `offset = ts − (t0 + t1) / 2` (server = client + offset). The estimate uses the sample with
//! the smallest round trip among the last [`WINDOW`], whose error is bounded by `rtt / 2`.

use std::collections::VecDeque;

/// Samples kept.
pub const WINDOW: usize = 16;

/// Offset and round-trip estimator.
#[derive(Debug, Default, Clone)]
pub struct ClockEstimator {
    samples: VecDeque<(f64, f64)>,
}

impl ClockEstimator {
    /// No samples yet: offset 0.
    #[must_use]
    pub fn new() -> Self {
        Self::default()
    }

    /// Adds one ping/pong exchange (all in microseconds).
    pub fn add(&mut self, t0: u64, server: u64, t1: u64) {
        if t1 < t0 {
            return;
        }
        let rtt = (t1 - t0) as f64;
        let offset = server as f64 - (t0 as f64 + t1 as f64) / 2.0;
        if self.samples.len() == WINDOW {
            self.samples.pop_front();
        }
        self.samples.push_back((rtt, offset));
    }

    fn best(&self) -> Option<(f64, f64)> {
        self.samples
            .iter()
            .copied()
            .min_by(|a, b| a.0.total_cmp(&b.0))
    }

    /// Estimated `server − client` clock offset, microseconds (0 before any sample).
    #[must_use]
    pub fn offset_us(&self) -> f64 {
        self.best().map_or(0.0, |b| b.1)
    }

    /// The smallest recent round-trip time, microseconds.
    #[must_use]
    pub fn rtt_us(&self) -> Option<f64> {
        self.best().map(|b| b.0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn picks_the_fastest_exchange() {
        let mut c = ClockEstimator::new();
        // Server is 5 000 µs ahead. A slow exchange with asymmetric delay is misleading; the
        // fast one is close to the truth.
        c.add(1_000, 1_000 + 5_000 + 9_000, 10_000);
        c.add(20_000, 20_000 + 5_000 + 100, 20_200);
        assert_eq!(c.rtt_us(), Some(200.0));
        assert!((c.offset_us() - 5_000.0).abs() <= 100.0);
    }
}
