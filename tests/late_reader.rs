//! Issue 28 goal 5: the adaptive rate takes what a reader can read. A reader starved of CPU
//! (a client on a loaded machine) answers pings late without any queue (here 0–300 ms) — it reads everything
//! each time it runs — and keeps its rate; a reader that cannot take the rate is cut to what
//! it takes, and its frames stay fresh. Loopback, 10 built-in avatars at 60 Hz.

#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use common::link::{Reading, Viewer, one_at_a_time, quantile, scene_server, unix_micros};
use posecast_proto::msg::Encoding;
use std::time::Duration;

/// Frames per second over `[from, to)` µs, and every frame's age (arrival − server time, ms).
fn rate_and_ages(viewer: &Viewer, from: u64, to: u64) -> (f64, Vec<f64>) {
    let seen = viewer.seen();
    assert!(seen.failure.is_none(), "{:?}", seen.failure);
    let frames: Vec<_> = seen.frames_between(from, to).collect();
    let rate = frames.len() as f64 / ((to - from) as f64 / 1e6);
    let ages = frames
        .iter()
        .map(|(arrival, stamp)| (*arrival as f64 - *stamp as f64) / 1e3)
        .collect();
    (rate, ages)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_reader_late_by_its_scheduling_keeps_its_rate_and_a_slow_one_is_cut_to_what_it_reads() {
    let _turn = one_at_a_time().await;
    let server = scene_server(10).await;
    // Runs for about a millisecond every 300 ms: its pongs come 0–300 ms late, with no queue
    // anywhere (it reads all that came each time it runs).
    let late = Viewer::spawn_reading(
        server.addr,
        Encoding::Binary,
        Reading::InBursts(Duration::from_millis(300)),
    );
    // Takes at most 20 messages a second: at 60 frames a second its backlog would grow by
    // 40 frames a second.
    let slow = Viewer::spawn_reading(server.addr, Encoding::Binary, Reading::AtMost(20));
    let prompt = Viewer::spawn(server.addr, Encoding::Binary);
    // Settle: the slow reader's rate comes down (a cut every half second at most).
    tokio::time::sleep(Duration::from_secs(10)).await;
    let from = unix_micros();
    tokio::time::sleep(Duration::from_secs(8)).await;
    let to = unix_micros();
    let (prompt_rate, _) = rate_and_ages(&prompt, from, to);
    let (late_rate, mut late_ages) = rate_and_ages(&late, from, to);
    let (slow_rate, mut slow_ages) = rate_and_ages(&slow, from, to);
    let p99 = |ages: &mut Vec<f64>| quantile(ages, 0.99);
    eprintln!(
        "frames/s: prompt {prompt_rate:.1}, late by 0–300 ms {late_rate:.1} (age p99 {:.0} ms), \
         at most 20 messages/s {slow_rate:.1} (age p50 {:.0} ms, p99 {:.0} ms)",
        p99(&mut late_ages),
        quantile(&mut slow_ages, 0.5),
        p99(&mut slow_ages)
    );
    // What the adaptive rate did, for a failure's reading.
    let metrics = server.state.metrics.render(&[], 0).unwrap();
    eprintln!(
        "{}",
        metrics
            .lines()
            .filter(
                |l| l.starts_with("posecast_rate_") || l.starts_with("posecast_probe_pings_total")
            )
            .collect::<Vec<_>>()
            .join("; ")
    );
    assert!(prompt_rate >= 55.0, "{prompt_rate}");
    // The late reader keeps (nearly) the full rate: its lateness is not a queue.
    assert!(
        late_rate >= 0.9 * prompt_rate,
        "late {late_rate} against prompt {prompt_rate}"
    );
    // The slow one is cut to what it reads (pings and frames within its 20 messages), not
    // below a third of it, and its frames are not seconds old.
    assert!(
        (5.0..=20.0).contains(&slow_rate),
        "slow reader at {slow_rate} frames/s"
    );
    assert!(p99(&mut slow_ages) <= 1_000.0, "{slow_ages:?}");
    drop((late, slow, prompt));
    server.stop().await;
}
