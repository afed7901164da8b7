//! The client library behind a delayed, jittery, lossy link (issue 22, item 3): its jitter
//! buffer plays out between received frames, and its clock offset holds on one machine.
//!
//! Through the emulating proxy at 25 ms ± 10 ms one way (both ways), a library client renders
//! at 60 Hz what `client/src/net/jitter.rs` gives for now: at 1 % loss (a lost segment stalls
//! its connection for TCP's 200 ms retransmission timeout) ≥ 99 % of the displayed poses are
//! interpolated between two received frames and none is older than the playout point by more
//! than a frame interval; at 5 % loss at most 5 % repeat a received pose (held). The server
//! and the client share the clock, so the true offset is 0: the estimate is within 2 ms.
//!
//! Over WebTransport (issue 31), through the emulator's UDP path at the same delays and
//! losses, each way: at 1 % loss every shown pose is interpolated or extrapolated, none lags its
//! playout point (no displayed freeze) and frames are at most 60 ms old at the 99th
//! percentile; at 5 % loss the client gets at least 55 frames a second and never shows one
//! pose for more than 50 ms. (Fifty viewers at once are `loadgen --link-suite`'s.)

#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use posecast_client::net::jitter::Sampled;
use posecast_client::net::{Client, ClientOptions, Transport, TransportChoice};
use posecast_linkemu::{Link, Proxy, UdpProxy};
use posecast_proto::msg::AvatarId;
use std::time::Duration;

/// What 60 Hz rendering of the default avatar showed.
#[derive(Debug, Default)]
struct Shown {
    /// Frames decoded a second while rendering (the client's count).
    fps: f64,
    /// Frame age (arrival − server time) at the 99th percentile of the frames seen, µs.
    age_p99_us: u64,
    /// The most held samples in a row (one pose shown that many render intervals).
    longest_hold: usize,
    interpolated: usize,
    extrapolated: usize,
    held: usize,
    /// How far the shown pose lagged its playout point, worst, µs (0 when interpolated).
    worst_lag_us: f64,
    /// The server's frame interval seen (µs), for the lag bound.
    frame_interval_us: f64,
}

impl Shown {
    fn total(&self) -> usize {
        self.interpolated + self.extrapolated + self.held
    }
}

/// A client through a link of `link`, warmed up, then rendering for `seconds`: on a
/// websocket through the emulator's TCP proxy.
async fn render(link: &str, seconds: f64) -> (Shown, Client) {
    let server = common::server(60.0).await;
    let proxy = Proxy::start(server.addr, Link::new(link.parse().unwrap()))
        .await
        .unwrap();
    let mut options = ClientOptions::new(format!("ws://{}/ws", proxy.addr()), "default");
    options.reconnect = false;
    options.ping_interval = Duration::from_millis(250);
    let client = Client::connect(options).await.unwrap();
    let shown = watch(&client, seconds).await;
    drop(proxy);
    server.stop().await;
    (shown, client)
}

/// [`render`] over WebTransport (protocol version 9: frames as datagrams) through the
/// emulator's UDP proxy, `link` each way.
async fn render_over_webtransport(link: &str, seconds: f64) -> (Shown, Client) {
    let server = common::kit_builder(60.0)
        .configure(|c| c.quic_listen = Some("127.0.0.1:0".parse().unwrap()))
        .start()
        .await
        .unwrap()
        .into_server();
    let port = server.state.quic.get().unwrap().port;
    let proxy = UdpProxy::start(
        std::net::SocketAddr::from(([127, 0, 0, 1], port)),
        link.parse().unwrap(),
    )
    .await
    .unwrap();
    let mut options = ClientOptions::new(format!("ws://{}/ws", server.addr), "default");
    options.reconnect = false;
    options.quic_timeout = common::watch::PATIENCE;
    options.webtransport_url = Some(format!("https://127.0.0.1:{}/", proxy.addr.port()));
    // WebTransport only, a few tries: at 5 % loss a handshake can fail (wtransport then
    // closes the session), and the client would fall back to the websocket — right for a
    // viewer, not what this test measures. The frames' behaviour is the subject here.
    options.transport = TransportChoice::WebTransport;
    let mut client = None;
    for attempt in 1..=5 {
        match Client::connect(options.clone()).await {
            Ok(c) => {
                client = Some(c);
                break;
            }
            Err(e) => eprintln!("WebTransport session {attempt} of 5 failed: {e}"),
        }
    }
    let client = client.expect("no WebTransport session in 5 tries");
    assert_eq!(client.transport(), Some(Transport::WebTransport));
    let shown = watch(&client, seconds).await;
    let (down, up) = (proxy.down(), proxy.up());
    eprintln!(
        "link down {} delivered {} lost, up {} delivered {} lost",
        down.delivered, down.lost, up.delivered, up.lost
    );
    drop(proxy);
    server.stop().await;
    (shown, client)
}

/// Renders `client`'s default avatar at 60 Hz for `seconds` (after a few seconds for its
/// jitter buffer to learn the link): what it showed.
async fn watch(client: &Client, seconds: f64) -> Shown {
    let id = AvatarId("avatar".into());
    // The buffer's delay follows the last 10 s of transits: let it see a few seconds.
    assert!(
        common::wait_for(10.0, || client.latest(&id).is_some()).await,
        "no frame"
    );
    tokio::time::sleep(Duration::from_secs(5)).await;
    let mut shown = Shown::default();
    let mut ticker = tokio::time::interval(Duration::from_micros(16_667));
    let began = tokio::time::Instant::now();
    let decoded = client.stats().frames;
    let mut seqs = Vec::new();
    let mut holding = 0;
    while began.elapsed().as_secs_f64() < seconds {
        ticker.tick().await;
        let view = client.avatar(&id).unwrap();
        let now = posecast_client::net::client::unix_micros();
        let t = view.jitter.playout_time(now);
        let (_, kind) = view.jitter.sample_with_kind(t).unwrap();
        holding = if kind == Sampled::Held {
            holding + 1
        } else {
            0
        };
        shown.longest_hold = shown.longest_hold.max(holding);
        match kind {
            Sampled::Interpolated => shown.interpolated += 1,
            Sampled::Extrapolated => shown.extrapolated += 1,
            Sampled::Held => {
                shown.held += 1;
                // A held pose is the newest frame (or the oldest, before it): its lag.
                if let Some((stamp, _)) = view.jitter.latest() {
                    shown.worst_lag_us = shown.worst_lag_us.max(t - stamp as f64);
                }
            }
        }
        if let Some(l) = view.latest {
            seqs.push((
                l.seq,
                l.server_time_us,
                now.saturating_sub(l.server_time_us),
            ));
        }
    }
    seqs.dedup_by_key(|s| s.0);
    if let (Some(a), Some(b)) = (seqs.first(), seqs.last())
        && b.0 > a.0
    {
        shown.frame_interval_us = (b.1 - a.1) as f64 / (seqs.len() - 1).max(1) as f64;
    }
    shown.fps = (client.stats().frames - decoded) as f64 / began.elapsed().as_secs_f64();
    // A frame's age when first seen: at most a render interval after it came.
    let mut ages: Vec<u64> = seqs.iter().map(|s| s.2).collect();
    ages.sort_unstable();
    if !ages.is_empty() {
        shown.age_p99_us = ages[(ages.len() * 99).div_ceil(100) - 1];
    }
    shown
}

fn report(what: &str, s: &Shown) {
    let total = s.total() as f64;
    eprintln!(
        "{what}: {} poses shown, interpolated {:.2} %, extrapolated {:.2} %, held {:.2} %, \
         worst lag {:.1} ms, longest hold {} renders, frames every {:.1} ms, {:.1} frames/s, \
         age p99 (as seen) {:.1} ms",
        s.total(),
        100.0 * s.interpolated as f64 / total,
        100.0 * s.extrapolated as f64 / total,
        100.0 * s.held as f64 / total,
        s.worst_lag_us / 1e3,
        s.longest_hold,
        s.frame_interval_us / 1e3,
        s.fps,
        s.age_p99_us as f64 / 1e3
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn at_one_percent_loss_nearly_every_pose_is_interpolated() {
    let _turn = common::link::one_at_a_time().await;
    let (s, _) = render("delay=25ms,jitter=10ms,loss=1%,seed=11", 12.0).await;
    report("25 ± 10 ms, 1 % loss", &s);
    assert!(s.total() >= 300, "rendering fell behind: {s:?}");
    let interpolated = s.interpolated as f64 / s.total() as f64;
    assert!(interpolated >= 0.99, "{s:?}");
    // No shown pose lags its playout point by more than a frame interval (an interpolated or
    // extrapolated one does not lag at all).
    assert!(s.worst_lag_us <= s.frame_interval_us.max(16_667.0), "{s:?}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn at_five_percent_loss_few_poses_repeat() {
    let _turn = common::link::one_at_a_time().await;
    let (s, _) = render("delay=25ms,jitter=10ms,loss=5%,seed=12", 12.0).await;
    report("25 ± 10 ms, 5 % loss", &s);
    assert!(s.total() >= 300, "rendering fell behind: {s:?}");
    let held = s.held as f64 / s.total() as f64;
    assert!(held <= 0.05, "{s:?}");
}

/// Issue 31's goal at 1 % loss, over WebTransport: no displayed freeze (every shown pose
/// interpolated or extrapolated: none held, none lagging its playout point), frames at most
/// 60 ms old at the 99th percentile (as the renderer saw them: up to a render interval after
/// they came).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn over_webtransport_at_one_percent_loss_nothing_freezes() {
    let _turn = common::link::one_at_a_time().await;
    let (s, _) = render_over_webtransport("delay=25ms,jitter=10ms,loss=1%,seed=11", 12.0).await;
    report("WebTransport, 25 ± 10 ms, 1 % loss", &s);
    assert!(s.total() >= 300, "rendering fell behind: {s:?}");
    let interpolated = s.interpolated as f64 / s.total() as f64;
    assert!(interpolated >= 0.99, "{s:?}");
    assert_eq!((s.held, s.worst_lag_us), (0, 0.0), "{s:?}");
    assert!(s.age_p99_us <= 60_000, "{s:?}");
}

/// Issue 31's goal at 5 % loss, over WebTransport: at least 55 frames a second, and no pose
/// shown for more than 50 ms (three render intervals).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn over_webtransport_at_five_percent_loss_frames_keep_coming() {
    let _turn = common::link::one_at_a_time().await;
    let (s, _) = render_over_webtransport("delay=25ms,jitter=10ms,loss=5%,seed=12", 12.0).await;
    report("WebTransport, 25 ± 10 ms, 5 % loss", &s);
    assert!(s.total() >= 300, "rendering fell behind: {s:?}");
    assert!(s.fps >= 55.0, "{s:?}");
    assert!(s.longest_hold <= 3, "{s:?}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_clock_offset_is_within_two_milliseconds_on_one_machine() {
    let _turn = common::link::one_at_a_time().await;
    // Directly and through the jittery link: server and client share this machine's clock.
    for link in ["none", "delay=25ms,jitter=10ms"] {
        let (_, client) = render(link, 4.0).await;
        let (offset, rtt) = client.clock();
        eprintln!(
            "{link}: offset {:.3} ms (true 0), round trip {:?} ms",
            offset / 1e3,
            rtt.map(|r| r / 1e3)
        );
        assert!(rtt.is_some(), "no pong");
        assert!(offset.abs() <= 2_000.0, "{link}: offset {offset} µs");
    }
}
