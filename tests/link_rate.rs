//! A thin link shared by many viewers (issue 22, items 2 and 4): 2 Mbit/s through the
//! emulating proxy for 50 binary viewers of 10 avatars — about ten times what the link carries
//! at 60 Hz. Each connection's adaptive rate (`stream/src/pace.rs`) brings its frames
//! down to what the link delivers: every viewer keeps getting fresh frames (p99 age ≤ 300 ms;
//! before, frames were 5–11 s stale and most viewers got under one a second) and a newcomer
//! joins at once (before: no welcome at all). Whether the slowest get a fair share of what the
//! fastest get is an ignored test (issue 35, see `MIN_FAIR_SHARE`): not reliably yet. One JSON
//! viewer alone on 2 Mbit/s (a JSON frame is ~10 KB: the link carries 24 a second) gets fresh
//! frames too (before: p99 355 ms and rising).

#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use common::link::{Viewer, quantile, scene_server, unix_micros};
use posecast_linkemu::{Link, LinkConfig, Proxy};
use posecast_proto::msg::Encoding;
use posecast_server::startup::Server;
use std::time::Duration;

/// Frames each viewer got per second and the ages (µs) of all frames, over `[from, to)`.
fn figures(viewers: &[Viewer], from: u64, to: u64) -> (Vec<f64>, Vec<f64>) {
    let seconds = (to - from) as f64 / 1e6;
    let mut rates = Vec::new();
    let mut ages = Vec::new();
    for v in viewers {
        let seen = v.seen();
        assert!(
            seen.failure.is_none(),
            "a viewer failed: {:?}",
            seen.failure
        );
        let frames: Vec<_> = seen.frames_between(from, to).copied().collect();
        rates.push(frames.len() as f64 / seconds);
        ages.extend(frames.iter().map(|(a, s)| a.saturating_sub(*s) as f64));
    }
    (rates, ages)
}

/// Jain's fairness index of `rates`, `(Σx)² / (n·Σx²)`: 1 when all are equal, `k/n` when `k`
/// of `n` share everything and the others get nothing.
fn jain(rates: &[f64]) -> f64 {
    let sum: f64 = rates.iter().sum();
    let squares: f64 = rates.iter().map(|r| r * r).sum();
    if squares == 0.0 {
        return 0.0;
    }
    sum * sum / (rates.len() as f64 * squares)
}

/// The least share of the fastest tenth's frame rate the slowest tenth of 50 viewers sharing a
/// bottleneck should get, over 12 s (issue 35: fairness, the slowest against the fastest, not
/// a floor). The path's shared cuts (`Path::judge` in `stream/src/pace.rs`) give every
/// connection behind the link one equal share — the cut's factor times their mean rate — so
/// the faster give up more and the slower catch up; without them each cuts on its own queue
/// samples.
///
/// Measured (`cargo test --test link_rate fair_shares -- --test-threads=1 --nocapture`), the
/// tenths' ratio over 12 s: 0.76–0.82 with equal shares (7 runs, 3 of them beside a release
/// build: 0.80, 0.79, 0.76, 0.80, 0.81, 0.76, 0.82). The cuts before, each connection by the
/// same factor of its own rate: 0.46–0.61 (14 runs at stop 42) and 0.52, 0.42 now; no shared
/// cuts at all: 0.32–0.48 (9 runs) and 0.52 now. Tenths, not the single slowest and fastest:
/// a viewer at 2–4 frames/s shows 24–50 frames in 12 s, and the extremes of 50 such counts are
/// noise as much as rate (single slowest / fastest: 0.67–0.78 with equal shares, 0.37–0.41
/// with the cuts before). Not Jain's index `(Σx)²/(n·Σx²)`: the middle 40 dominate it
/// (0.994–0.997 with equal shares, 0.951–0.970 with the cuts before).
const MIN_FAIR_SHARE: f64 = 0.65;

/// A scene of 10 avatars behind 2 Mbit/s and 50 binary viewers arriving one every 150 ms
/// (each join is 52 KB of descriptions, a fifth of a second of the whole link).
async fn fifty_on_two_megabits() -> (Server, Proxy, Vec<Viewer>) {
    let server = scene_server(10).await;
    let link: LinkConfig = "rate=2mbit".parse().unwrap();
    let proxy = Proxy::start(server.addr, Link::new(link)).await.unwrap();
    let mut viewers = Vec::new();
    for _ in 0..50 {
        viewers.push(Viewer::spawn(proxy.addr(), Encoding::Binary));
        tokio::time::sleep(Duration::from_millis(150)).await;
    }
    (server, proxy, viewers)
}

/// The mean frames/s of the slowest and of the fastest tenth of `viewers` over `[from, to)`,
/// and every viewer's, sorted.
fn tenths(viewers: &[Viewer], from: u64, to: u64) -> (f64, f64, Vec<f64>) {
    let (mut shares, _) = figures(viewers, from, to);
    shares.sort_by(f64::total_cmp);
    let tenth = (shares.len() / 10).max(1);
    let slowest = shares[..tenth].iter().sum::<f64>() / tenth as f64;
    let fastest = shares[shares.len() - tenth..].iter().sum::<f64>() / tenth as f64;
    (slowest, fastest, shares)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn fifty_viewers_share_two_megabits_fairly_and_a_newcomer_joins() {
    let _turn = common::link::one_at_a_time().await;
    let (server, proxy, viewers) = fifty_on_two_megabits().await;
    // Then the rates settle.
    tokio::time::sleep(Duration::from_secs(20)).await;
    let from = unix_micros();
    tokio::time::sleep(Duration::from_secs(6)).await;
    let to = unix_micros();
    let (rates, mut ages) = figures(&viewers, from, to);
    let min_rate = rates.iter().copied().fold(f64::INFINITY, f64::min);
    let mean_rate = rates.iter().sum::<f64>() / rates.len() as f64;
    let p50 = quantile(&mut ages, 0.5) / 1e3;
    let p99 = quantile(&mut ages, 0.99) / 1e3;
    let down = proxy.link().stats(posecast_linkemu::Way::Down);
    eprintln!(
        "50 viewers on 2 Mbit/s: frames/s min {min_rate:.1} mean {mean_rate:.1}; age p50 \
         {p50:.0} ms p99 {p99:.0} ms; link carried {} bytes",
        down.bytes
    );
    // A newcomer on the saturated link.
    let newcomer = Viewer::spawn(proxy.addr(), Encoding::Binary);
    common::wait_for(5.0, || newcomer.seen().joined_after.is_some()).await;
    let joined = newcomer.seen().joined_after;
    eprintln!(
        "a newcomer: welcome after {:?}, first frame after {joined:?}",
        newcomer.seen().welcome_after
    );
    // The rates are in /metrics: every connection is counted at one step.
    let metrics = server.state.metrics.render(&[], 0).unwrap();
    let counted: u64 = metrics
        .lines()
        .filter(|l| l.starts_with("posecast_connection_rate{"))
        .map(|l| l.rsplit_once(' ').unwrap().1.parse::<u64>().unwrap())
        .sum();
    assert_eq!(counted, 51, "{metrics}");
    // Every cut is counted under what it answered, and the probes' pings are counted.
    let sum = |prefix: &str| -> f64 {
        metrics
            .lines()
            .filter(|l| l.starts_with(prefix))
            .map(|l| l.rsplit_once(' ').unwrap().1.parse::<f64>().unwrap())
            .sum()
    };
    let cuts = sum("posecast_rate_cuts_total{");
    let down = sum(r#"posecast_rate_changes_total{way="down"}"#);
    eprintln!(
        "cuts by cause: {:?}",
        metrics
            .lines()
            .filter(|l| l.starts_with("posecast_rate_cuts_total{"))
            .collect::<Vec<_>>()
    );
    assert!(
        cuts > 0.0 && cuts == down,
        "{cuts} cuts by cause, {down} down"
    );
    assert!(sum("posecast_probe_pings_total") >= 51.0, "{metrics}");
    // No viewer starves: each keeps at least the lowest step (1 frame/s). (5 frames/s each
    // does not fit: a frame of these 10 avatars is 872 bytes, the keyframe a paced viewer
    // needs once a second 1,712 — 5 × 872 + 1,712 = 6.1 KB/s a viewer, 303 KB/s for 50,
    // more than the link's 250 KB/s.)
    assert!(
        min_rate >= 0.65,
        "every viewer ≥ 1 frame/s (give or take one): {rates:?}"
    );
    assert!(mean_rate >= 1.5, "{rates:?}");
    assert!(p99 <= 300.0, "p99 frame age {p99:.0} ms");
    let welcome = newcomer.seen().welcome_after;
    assert!(
        welcome.is_some_and(|w| w <= Duration::from_secs(1)),
        "the newcomer's welcome came after {welcome:?}"
    );
    // Its first frame comes after its 52 KB of descriptions.
    assert!(
        joined.is_some_and(|j| j <= Duration::from_secs(2)),
        "the newcomer's first frame came after {joined:?}"
    );
    drop(viewers);
    server.stop().await;
}

/// Issue 35: viewers sharing a bottleneck get fair shares — the slowest tenth at least
/// `MIN_FAIR_SHARE` of the fastest tenth's frame rate over 12 s. Red with the path's shared
/// cuts switched off, and with the cuts by one factor of each connection's own rate that came
/// before equal shares (see `MIN_FAIR_SHARE`).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn fifty_viewers_behind_one_bottleneck_get_fair_shares() {
    let _turn = common::link::one_at_a_time().await;
    let (server, _proxy, viewers) = fifty_on_two_megabits().await;
    // Judged over 12 s after 14 s of settling, the same 26 s as the test above.
    tokio::time::sleep(Duration::from_secs(14)).await;
    let from = unix_micros();
    tokio::time::sleep(Duration::from_secs(12)).await;
    let to = unix_micros();
    let (slowest, fastest, shares) = tenths(&viewers, from, to);
    eprintln!(
        "50 viewers on 2 Mbit/s over 12 s: slowest tenth {slowest:.2}, fastest tenth \
         {fastest:.2} frames/s (ratio {:.2}; single slowest / fastest {:.2}, Jain's index \
         {:.3})",
        slowest / fastest,
        shares[0] / shares[shares.len() - 1],
        jain(&shares)
    );
    assert!(
        slowest / fastest >= MIN_FAIR_SHARE,
        "slowest tenth {slowest:.2} against fastest tenth {fastest:.2} frames/s: {shares:.2?}"
    );
    drop(viewers);
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn one_json_viewer_on_two_megabits_gets_fresh_frames() {
    let _turn = common::link::one_at_a_time().await;
    let server = scene_server(10).await;
    let proxy = Proxy::start(server.addr, Link::new("rate=2mbit".parse().unwrap()))
        .await
        .unwrap();
    let viewer = Viewer::spawn(proxy.addr(), Encoding::Json);
    // It starts at 60 Hz (600 KB/s): a few seconds to come down and settle.
    tokio::time::sleep(Duration::from_secs(10)).await;
    let from = unix_micros();
    tokio::time::sleep(Duration::from_secs(6)).await;
    let to = unix_micros();
    let viewers = [viewer];
    let (rates, mut ages) = figures(&viewers, from, to);
    let p50 = quantile(&mut ages, 0.5) / 1e3;
    let p99 = quantile(&mut ages, 0.99) / 1e3;
    eprintln!(
        "one JSON viewer on 2 Mbit/s: {:.1} frames/s; age p50 {p50:.0} ms p99 {p99:.0} ms",
        rates[0]
    );
    assert!(rates[0] >= 5.0, "{} frames/s", rates[0]);
    assert!(p99 <= 300.0, "p99 frame age {p99:.0} ms");
    // A 10 KB frame takes 42 ms to cross: at a rate the link keeps up with, frames do not
    // wait for each other. (Sent at every tick, the newest-frame-wins outbox alone keeps the
    // p99 near 270 ms, but every frame waits behind the last: p50 ~200 ms.)
    assert!(p50 <= 120.0, "p50 frame age {p50:.0} ms");
    server.stop().await;
}

/// Frames/s of each of `n` binary viewers of 10 avatars behind one address on `link`, over 6 s
/// after `settle`; and the link's spurious retransmissions (down) meanwhile.
async fn viewers_on(link: &str, n: usize, settle: Duration) -> (Vec<f64>, u64) {
    let server = scene_server(10).await;
    let proxy = Proxy::start(server.addr, Link::new(link.parse().unwrap()))
        .await
        .unwrap();
    let mut viewers = Vec::new();
    for _ in 0..n {
        viewers.push(Viewer::spawn(proxy.addr(), Encoding::Binary));
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    tokio::time::sleep(settle).await;
    let before = proxy.link().stats(posecast_linkemu::Way::Down).spurious;
    let from = unix_micros();
    tokio::time::sleep(Duration::from_secs(6)).await;
    let to = unix_micros();
    let spurious = proxy.link().stats(posecast_linkemu::Way::Down).spurious - before;
    let (rates, _) = figures(&viewers, from, to);
    drop(viewers);
    server.stop().await;
    (rates, spurious)
}

/// Issue 37, goal 5: 50 viewers from one address on a path that reorders (25 ± 10 ms each
/// way; a segment overtaken by three later ones costs a spurious retransmission's stall) each
/// keep ≥ 50 frames/s, and together no less than 85 % of what one alone gets there. (Before:
/// any two connections cutting within a second made the whole address cut, and jitter made
/// some two always do: 50 such viewers fell to 3–4 frames/s behind a kernel link emulator.)
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn fifty_viewers_behind_one_address_keep_their_rate_on_a_reordering_link() {
    let _turn = common::link::one_at_a_time().await;
    let link = "delay=25ms,jitter=10ms,reorder=3,seed=37";
    let (alone, _) = viewers_on(link, 1, Duration::from_secs(8)).await;
    let (rates, spurious) = viewers_on(link, 50, Duration::from_secs(15)).await;
    let min = rates.iter().copied().fold(f64::INFINITY, f64::min);
    let mean = rates.iter().sum::<f64>() / rates.len() as f64;
    eprintln!(
        "{link}: one viewer alone {:.1} frames/s; 50 viewers min {min:.1} mean {mean:.1} \
         frames/s ({spurious} spurious retransmissions in 6 s)",
        alone[0]
    );
    assert!(min >= 50.0, "every viewer ≥ 50 frames/s: {rates:?}");
    assert!(
        mean >= 0.85 * alone[0],
        "one address's viewers together below what one alone gets: mean {mean:.1}, alone {:.1}",
        alone[0]
    );
}
