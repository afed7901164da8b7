//! `watch`: one line of stream statistics per second.

use super::Connection;
use clap::Args;
use posecast_client::net::{Client, Stats};
use posecast_proto::msg::ErrorCode;
use std::time::{Duration, Instant};

#[derive(Debug, Args)]
pub struct WatchArgs {
    #[command(flatten)]
    connection: Connection,
    /// Print one JSON object per line instead of text.
    #[arg(long, env = "POSECAST_WATCH_JSON")]
    json: bool,
    /// Stop after this many seconds (default: run until interrupted).
    #[arg(long, env = "POSECAST_WATCH_SECONDS")]
    seconds: Option<u64>,
}

pub async fn run(args: WatchArgs) -> anyhow::Result<()> {
    let client = args.connection.connect(true).await?;
    let mut events = client.events();
    let start = Instant::now();
    let mut ticker = tokio::time::interval(Duration::from_secs(1));
    ticker.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    ticker.tick().await;
    let mut before = (Instant::now(), client.stats());
    loop {
        tokio::select! {
            _ = ticker.tick() => {}
            _ = tokio::signal::ctrl_c() => return Ok(()),
            event = events.recv() => {
                // A subscription the server refused (no such scene, not allowed) would
                // otherwise show 0 frames/s for ever: say so and stop.
                if let Ok(posecast_client::net::Event::Error(e)) = event
                    && matches!(e.code, ErrorCode::UnknownScene | ErrorCode::Unauthorized | ErrorCode::Forbidden)
                {
                    anyhow::bail!("the server refused the subscription: {e}");
                }
                continue;
            }
        }
        let now = Instant::now();
        let stats = client.stats();
        // An error that came before the events were listened to.
        if let Some(e) = &stats.last_error
            && matches!(
                e.code,
                ErrorCode::UnknownScene | ErrorCode::Unauthorized | ErrorCode::Forbidden
            )
        {
            anyhow::bail!("the server refused the subscription: {e}");
        }
        let line = Line::new(&client, &before.1, &stats, now.duration_since(before.0));
        if args.json {
            println!("{}", line.json(start.elapsed()));
        } else {
            println!("{}", line.text());
        }
        before = (now, stats);
        if args
            .seconds
            .is_some_and(|s| start.elapsed() >= Duration::from_secs(s))
        {
            return Ok(());
        }
    }
}

/// One interval's figures.
struct Line {
    frames_per_s: f64,
    keyframes: u64,
    bytes_per_s: f64,
    /// Mean tick→receive latency over the interval, ms (offset-corrected).
    latency_mean_ms: Option<f64>,
    /// Largest tick→receive latency since connecting, ms (join keyframes left out).
    latency_max_ms: f64,
    /// Age of the newest join keyframe when it arrived, ms.
    join_age_ms: Option<f64>,
    rtt_ms: Option<f64>,
    offset_ms: f64,
    avatars: usize,
    connected: bool,
    transport: Option<posecast_client::net::Transport>,
}

impl Line {
    fn new(client: &Client, before: &Stats, now: &Stats, elapsed: Duration) -> Self {
        let seconds = elapsed.as_secs_f64().max(1e-3);
        let count = now.latency_count.saturating_sub(before.latency_count);
        let (offset, rtt) = client.clock();
        Self {
            frames_per_s: now.frames.saturating_sub(before.frames) as f64 / seconds,
            keyframes: now.keyframes.saturating_sub(before.keyframes),
            bytes_per_s: now.frame_bytes.saturating_sub(before.frame_bytes) as f64 / seconds,
            latency_mean_ms: (count > 0)
                .then(|| (now.latency_sum_us - before.latency_sum_us) / count as f64 / 1000.0),
            latency_max_ms: now.latency_max_us / 1000.0,
            join_age_ms: now.join_age_us.map(|a| a / 1000.0),
            rtt_ms: rtt.map(|r| r / 1000.0),
            offset_ms: offset / 1000.0,
            avatars: client.avatars().len(),
            connected: client.is_connected(),
            transport: now.transport,
        }
    }

    fn text(&self) -> String {
        let ms = |v: Option<f64>| v.map_or("-".to_owned(), |v| format!("{v:.2} ms"));
        format!(
            "{:5.1} frames/s  {} keyframes  {:8.0} B/s  latency mean {} max {:.2} ms  join age {}  \
             rtt {}  offset {:+.2} ms  {} avatars  {}{}",
            self.frames_per_s,
            self.keyframes,
            self.bytes_per_s,
            ms(self.latency_mean_ms),
            self.latency_max_ms,
            ms(self.join_age_ms),
            ms(self.rtt_ms),
            self.offset_ms,
            self.avatars,
            self.transport.map_or("-".to_owned(), |t| t.to_string()),
            if self.connected {
                ""
            } else {
                "  (disconnected)"
            },
        )
    }

    fn json(&self, t: Duration) -> serde_json::Value {
        serde_json::json!({
            "t_s": t.as_secs_f64(),
            "frames_per_s": self.frames_per_s,
            "keyframes": self.keyframes,
            "bytes_per_s": self.bytes_per_s,
            "latency_mean_ms": self.latency_mean_ms,
            "latency_max_ms": self.latency_max_ms,
            "join_age_ms": self.join_age_ms,
            "rtt_ms": self.rtt_ms,
            "clock_offset_ms": self.offset_ms,
            "avatars": self.avatars,
            "connected": self.connected,
            "transport": self.transport.map(|t| t.to_string()),
        })
    }
}
