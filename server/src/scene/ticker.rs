//! The tick task of a scene: a drift-free schedule of absolute deadlines.
//!
//! Tick `n` is due at `start + n / rate`. The task sleeps until the next deadline (tokio's
//! `Interval`, which keeps absolute deadlines); when it wakes late past one or more deadlines,
//! those ticks are counted as missed and skipped — the scene jumps to the current tick with
//! `dt` covering the gap, so playback time stays right and no burst of catch-up frames is sent.

use super::Scene;
use crate::metrics::Metrics;
use std::sync::Arc;
use std::time::{Duration, SystemTime, UNIX_EPOCH};
use tokio::time::{Instant, MissedTickBehavior};

/// Microseconds since the Unix epoch (0 if the clock is before it).
#[must_use]
pub fn unix_micros() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_micros() as u64)
}

/// Runs `scene`'s ticks at `rate` Hz until the scene is shut.
pub async fn run(scene: Arc<Scene>, rate: f32, metrics: Arc<Metrics>) {
    let rate = if rate.is_finite() && rate > 0.0 {
        rate
    } else {
        60.0
    };
    let period = Duration::from_secs_f64(1.0 / f64::from(rate));
    let start = Instant::now();
    let mut interval = tokio::time::interval_at(start, period);
    interval.set_missed_tick_behavior(MissedTickBehavior::Skip);
    // A keyframe at least once a second.
    let key_interval = (rate.ceil() as u64).max(1);
    let mut last: Option<u64> = None;
    let mut generation = scene.ticker_generation();
    generation.borrow_and_update();
    loop {
        let due = tokio::select! {
            due = interval.tick() => due,
            () = scene.stopped() => return,
            _ = generation.changed() => return,
        };
        let late = Instant::now().saturating_duration_since(due);
        // The tick number of the deadline that just passed, from absolute time.
        let seq = (due.duration_since(start).as_secs_f64() / period.as_secs_f64()).round() as u64;
        let elapsed_ticks = last.map_or(1, |l| seq.saturating_sub(l).max(1));
        if elapsed_ticks > 1 {
            metrics.ticks_missed(elapsed_ticks - 1);
        }
        last = Some(seq);
        let began = std::time::Instant::now();
        // The scene clock comes from the tick number, so playback never accumulates rounding.
        scene.tick(
            seq,
            seq as f64 / f64::from(rate),
            unix_micros(),
            key_interval,
        );
        metrics.tick_done(began.elapsed(), late);
    }
}
