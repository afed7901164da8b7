//! Clock offset and round-trip time from ping/pong, NTP-style: for a ping sent at client time
//! `t0`, answered at server time `ts` and received at `t1`, `rtt = t1 − t0` and
//! `offset = ts − (t0 + t1) / 2` (server = client + offset). A sample's error is half the
//! difference of its two one-way delays (at most `rtt / 2`).
//!
//! **Estimate.** Each sample bounds the offset: the server's clock read `ts` between the
//! client's `t0` and `t1`, so `ts − t1 ≤ offset ≤ ts − t0`. Intersecting the bounds of the last
//! [`WINDOW`] samples gives `[ts − t1]max ≤ offset ≤ [ts − t0]min`, set by the fastest way
//! *to* the server and the fastest way *back* — from any two samples, not one that was fast
//! both ways — and the estimate is its middle: off by half the difference of the two fastest
//! one-way delays (on a link of 25 ± 10 ms each way the fastest single sample was off by up to
//! 3.5 ms; this by well under 2 ms, `tests/link_playout.rs`). Should the bounds not meet (a
//! clock stepped), the median offset of the quarter of the samples with the smallest round
//! trips is used instead.

use std::collections::VecDeque;

/// Samples kept.
pub const WINDOW: usize = 64;

/// The most samples the fallback estimate takes the median of.
pub const BEST_OF: usize = 16;

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

    /// Estimated `server − client` clock offset, microseconds (0 before any sample): the middle
    /// of the samples' intersected bounds, or, when they do not meet, the median offset of the
    /// quarter of the samples with the smallest round trips (at least one, at most
    /// [`BEST_OF`]).
    #[must_use]
    pub fn offset_us(&self) -> f64 {
        // The bounds: (ts − t1, ts − t0) of each sample is (offset − rtt/2, offset + rtt/2)
        // around its midpoint estimate.
        let lo = self
            .samples
            .iter()
            .map(|(rtt, o)| o - rtt / 2.0)
            .fold(f64::NEG_INFINITY, f64::max);
        let hi = self
            .samples
            .iter()
            .map(|(rtt, o)| o + rtt / 2.0)
            .fold(f64::INFINITY, f64::min);
        if lo <= hi {
            return (lo + hi) / 2.0;
        }
        let mut by_rtt: Vec<(f64, f64)> = self.samples.iter().copied().collect();
        by_rtt.sort_by(|a, b| a.0.total_cmp(&b.0));
        let k = (by_rtt.len() / 4).clamp(1, BEST_OF).min(by_rtt.len());
        let mut offsets: Vec<f64> = by_rtt.iter().take(k).map(|s| s.1).collect();
        if offsets.is_empty() {
            return 0.0;
        }
        offsets.sort_by(f64::total_cmp);
        let mid = offsets.len() / 2;
        if offsets.len() % 2 == 1 {
            offsets[mid]
        } else {
            (offsets[mid - 1] + offsets[mid]) / 2.0
        }
    }

    /// The smallest recent round-trip time, microseconds.
    #[must_use]
    pub fn rtt_us(&self) -> Option<f64> {
        self.samples.iter().map(|s| s.0).min_by(f64::total_cmp)
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

    /// Pings over a link of 25 ms ± 10 ms (uniform) each way; the server 5 ms ahead.
    fn jittery(c: &mut ClockEstimator, n: usize, seed: u64) {
        let mut state = seed;
        let mut random = move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        for i in 0..n {
            let t0 = 1_000_000.0 + i as f64 * 250_000.0;
            let up = 25_000.0 + (random() * 2.0 - 1.0) * 10_000.0;
            let down = 25_000.0 + (random() * 2.0 - 1.0) * 10_000.0;
            c.add(
                t0 as u64,
                (t0 + up + 5_000.0) as u64,
                (t0 + up + down) as u64,
            );
        }
    }

    #[test]
    fn intersected_bounds_cancel_a_jittery_links_asymmetry() {
        // Over many seeds: the filtered estimate's worst error, and the fastest single
        // sample's (what the estimator used before).
        let (mut worst, mut worst_single) = (0.0f64, 0.0f64);
        for seed in 1..200 {
            let mut c = ClockEstimator::new();
            jittery(&mut c, WINDOW, seed);
            worst = worst.max((c.offset_us() - 5_000.0).abs());
            let fastest = c.samples.iter().min_by(|a, b| a.0.total_cmp(&b.0)).unwrap();
            worst_single = worst_single.max((fastest.1 - 5_000.0).abs());
        }
        eprintln!("worst error: bounds {worst:.0} µs, fastest sample {worst_single:.0} µs");
        assert!(worst <= 2_000.0, "{worst}");
        assert!(worst < worst_single, "{worst} vs {worst_single}");
    }

    #[test]
    fn bounds_that_do_not_meet_fall_back_to_the_fastest_quarter() {
        let mut c = ClockEstimator::new();
        // Server 5 ms ahead, 1 ms round trips...
        for i in 0..8u64 {
            let t0 = 1_000_000 + i * 100_000;
            c.add(t0, t0 + 5_500, t0 + 1_000);
        }
        // ...then its clock steps 50 ms ahead: the bounds no longer meet. The quarter with the
        // smallest round trips (these, at 0.8 ms) says 55 ms.
        for i in 0..8u64 {
            let t0 = 3_000_000 + i * 100_000;
            c.add(t0, t0 + 55_400, t0 + 800);
        }
        assert!(
            (c.offset_us() - 55_000.0).abs() <= 100.0,
            "{}",
            c.offset_us()
        );
    }
}
