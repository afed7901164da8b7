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
        let now = Instant::now();
        let late = now.saturating_duration_since(due);
        // The tick number of the latest deadline passed, from absolute time. Not `due`'s: after
        // a stall the interval hands back the oldest missed deadline first, which would run
        // one tick a whole stall behind before jumping.
        let seq =
            (now.duration_since(start).as_secs_f64() / period.as_secs_f64() + 1e-9).floor() as u64;
        let elapsed_ticks = last.map_or(1, |l| seq.saturating_sub(l).max(1));
        if elapsed_ticks > 1 {
            metrics.ticks_missed(elapsed_ticks - 1);
        }
        last = Some(seq);
        let began = std::time::Instant::now();
        // The scene clock comes from the tick number, so playback never accumulates rounding.
        let held = scene.tick(
            seq,
            seq as f64 / f64::from(rate),
            unix_micros(),
            key_interval,
        );
        metrics.tick_done(began.elapsed(), late, held);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use posecast_proto::msg::SceneId;

    /// Under tokio's paused clock (time moves only when the test says): tick `n` runs at
    /// `start + n / rate`, its scene clock is exactly `n / rate`, and a stall of several
    /// periods is one tick that skips to the current number, the gap counted as missed.
    #[tokio::test(start_paused = true)]
    async fn ticks_follow_absolute_deadlines_and_skip_after_a_stall() {
        let rate = 60.0f32;
        let metrics = Arc::new(Metrics::new());
        let scene = Arc::new(Scene::new(SceneId("t".into()), 1, metrics.clone(), rate));
        let mut ticks = scene.ticks();
        let task = tokio::spawn(run(scene.clone(), rate, metrics.clone()));
        let period = Duration::from_secs_f64(1.0 / f64::from(rate));

        // The first deadline is the start itself; then one tick per period.
        for n in 0..=120u64 {
            if n > 0 {
                tokio::time::advance(period).await;
            }
            ticks.changed().await.unwrap();
            let seq = *ticks.borrow_and_update();
            assert_eq!(seq, n, "tick number after {n} periods");
            let s = scene.lock();
            assert_eq!(s.last_seq(), n);
            assert_eq!(s.clock(), n as f64 / f64::from(rate), "clock == seq / rate");
        }
        assert_eq!(metrics.missed(), 0);

        // A stall of 10 periods (the task could not run): the next tick is number 130,
        // not 121, and the 9 deadlines in between are counted missed, not run.
        tokio::time::advance(period * 10).await;
        ticks.changed().await.unwrap();
        assert_eq!(*ticks.borrow_and_update(), 130);
        assert_eq!(metrics.missed(), 9);
        assert_eq!(scene.lock().clock(), 130.0 / f64::from(rate));

        scene.shut();
        task.await.unwrap();
    }
}
