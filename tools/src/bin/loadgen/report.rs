//! The figures of a run, from every client's statistics and the server's counters.

use crate::Args;
use crate::client::ClientStats;
use std::collections::HashMap;

/// A run's results.
#[derive(Debug)]
pub struct Summary {
    clients: usize,
    avatars: Option<usize>,
    scene: String,
    /// The protocol version the clients spoke.
    protocol: u32,
    tick_rate: f64,
    wall: f64,
    connect_s: f64,
    frames: u64,
    bytes: u64,
    keys: u64,
    per_client_fps: (f64, f64, f64),
    latency_ms: [f64; 5],
    /// Frames without a latency (packed deltas whose base frame a client lacked).
    untimed: u64,
    missed: u64,
    out_of_order: u64,
    failures: usize,
    closed_early: usize,
    first_failure: Option<String>,
    server_cpu: Option<f64>,
    self_cpu: Option<f64>,
    server: Option<ServerCounters>,
}

/// Server counters over the measurement.
#[derive(Debug)]
struct ServerCounters {
    ticks: f64,
    tick_mean_ms: f64,
    ticks_missed: f64,
    offered: f64,
    sent: f64,
    late_max_ms: f64,
    /// The adaptive rate's pings, and its cuts by cause (those that happened).
    pings: f64,
    cuts: Vec<(String, f64)>,
}

type Metrics = HashMap<String, f64>;

impl ServerCounters {
    fn new(before: &Metrics, after: &Metrics) -> Self {
        let d =
            |k: &str| after.get(k).copied().unwrap_or(0.0) - before.get(k).copied().unwrap_or(0.0);
        let ticks = d("posecast_tick_seconds_count");
        Self {
            ticks,
            tick_mean_ms: if ticks > 0.0 {
                1e3 * d("posecast_tick_seconds_sum") / ticks
            } else {
                0.0
            },
            ticks_missed: d("posecast_ticks_missed_total"),
            offered: d("posecast_frames_offered_total"),
            sent: d("posecast_messages_sent_total"),
            pings: d("posecast_probe_pings_total"),
            cuts: {
                let mut cuts: Vec<(String, f64)> = after
                    .keys()
                    .filter_map(|k| {
                        let cause = k
                            .strip_prefix("posecast_rate_cuts_total{cause=\"")?
                            .strip_suffix("\"}")?;
                        Some((cause.to_owned(), d(k)))
                    })
                    .filter(|(_, n)| *n > 0.0)
                    .collect();
                cuts.sort_by(|a, b| a.0.cmp(&b.0));
                cuts
            },
            late_max_ms: after
                .get("posecast_tick_late_seconds_max_micros")
                .copied()
                .unwrap_or(0.0)
                / 1e3,
        }
    }
}

/// The `q` quantile of sorted values (nearest rank).
fn quantile(sorted: &[u32], q: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    let rank = ((q * sorted.len() as f64).ceil() as usize).clamp(1, sorted.len());
    f64::from(sorted[rank - 1])
}

impl Summary {
    /// Gathers the figures. CPU figures are percent of one core over `wall` seconds.
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        args: &Args,
        scene: &str,
        wall: f64,
        connect_s: f64,
        stats: &[ClientStats],
        server_cpu: Option<f64>,
        self_cpu: Option<f64>,
        metrics: Option<(&Metrics, &Metrics)>,
    ) -> Self {
        let mut latencies: Vec<u32> = stats
            .iter()
            .flat_map(|s| s.latencies_us.iter().copied())
            .collect();
        latencies.sort_unstable();
        let ms = |q: f64| quantile(&latencies, q) / 1e3;
        let fps: Vec<f64> = stats
            .iter()
            .filter(|s| s.failure.is_none())
            .map(|s| s.frames as f64 / wall)
            .collect();
        let (lo, hi) = fps.iter().fold((f64::INFINITY, 0.0f64), |(lo, hi), &f| {
            (lo.min(f), hi.max(f))
        });
        let mean = if fps.is_empty() {
            0.0
        } else {
            fps.iter().sum::<f64>() / fps.len() as f64
        };
        Self {
            clients: args.clients,
            protocol: args.protocol,
            avatars: args.spawn_server.then_some(args.avatars),
            scene: scene.to_owned(),
            // The frames each client should get: every tick, or every n-th at a lower rate.
            tick_rate: match args.rate {
                Some(rate) if rate > 0.0 && rate < args.tick_rate => {
                    f64::from(args.tick_rate)
                        / (f64::from(args.tick_rate) / f64::from(rate)).round()
                }
                _ => f64::from(args.tick_rate),
            },
            wall,
            connect_s,
            frames: stats.iter().map(|s| s.frames).sum(),
            bytes: stats.iter().map(|s| s.bytes).sum(),
            keys: stats.iter().map(|s| s.keys).sum(),
            per_client_fps: (if fps.is_empty() { 0.0 } else { lo }, mean, hi),
            latency_ms: [ms(0.5), ms(0.9), ms(0.99), ms(0.999), ms(1.0)],
            untimed: stats.iter().map(|s| s.untimed).sum(),
            missed: stats.iter().map(|s| s.missed).sum(),
            out_of_order: stats.iter().map(|s| s.out_of_order).sum(),
            failures: stats.iter().filter(|s| s.failure.is_some()).count(),
            closed_early: stats.iter().filter(|s| s.closed_early).count(),
            first_failure: stats.iter().find_map(|s| s.failure.clone()),
            server_cpu,
            self_cpu,
            server: metrics.map(|(a, b)| ServerCounters::new(a, b)),
        }
    }

    /// Prints the figures, then one Markdown table row.
    pub fn print(&self) {
        let expected = self.clients as f64 * self.tick_rate;
        let fps = self.frames as f64 / self.wall;
        let [p50, p90, p99, p999, max] = self.latency_ms;
        let pct = |v: Option<f64>| v.map_or_else(|| "n/a".into(), |v| format!("{v:.0} %"));
        println!(
            "\nscene {} · {} clients · {}{} · {:.1} s measured (connect {:.1} s)",
            self.scene,
            self.clients,
            wire_name(self.protocol),
            self.avatars
                .map_or_else(String::new, |m| format!(" · {m} avatars")),
            self.wall,
            self.connect_s
        );
        println!(
            "frames delivered  {fps:.0}/s of {expected:.0}/s expected ({:.1} %), {:.1} MB/s, {:.1} % keyframes",
            100.0 * fps / expected,
            self.bytes as f64 / self.wall / 1e6,
            100.0 * self.keys as f64 / (self.frames.max(1) as f64),
        );
        let (lo, mean, hi) = self.per_client_fps;
        println!("per client        min {lo:.1} · mean {mean:.1} · max {hi:.1} frames/s");
        println!(
            "tick→receive      p50 {p50:.2} · p90 {p90:.2} · p99 {p99:.2} · p99.9 {p999:.2} · max {max:.2} ms"
        );
        if self.untimed > 0 {
            println!(
                "                  ({} frames untimed: packed deltas whose base frame their client lacked)",
                self.untimed
            );
        }
        println!(
            "frames missed     {} ({:.2} % of expected; {} out of order)",
            self.missed,
            100.0 * self.missed as f64 / (expected * self.wall),
            self.out_of_order
        );
        println!(
            "failures          {} clients ({} closed early){}",
            self.failures,
            self.closed_early,
            self.first_failure
                .as_ref()
                .map_or_else(String::new, |f| format!("; first: {f}"))
        );
        println!(
            "cpu (of one core) server {} · loadgen {}",
            pct(self.server_cpu),
            pct(self.self_cpu)
        );
        // Other work on the machine competes with both processes for the same cores.
        if let Ok(load) = std::fs::read_to_string("/proc/loadavg") {
            println!(
                "machine           load average {} on {} cores",
                load.split_whitespace()
                    .take(3)
                    .collect::<Vec<_>>()
                    .join(" "),
                std::thread::available_parallelism().map_or(0, usize::from)
            );
        }
        if let Some(s) = &self.server {
            println!(
                "server counters   {:.1} ticks/s ({:.0} missed), mean tick {:.3} ms, max tick lateness {:.1} ms (whole run), \
                 frames offered {:.0}/s, messages written {:.0}/s",
                s.ticks / self.wall,
                s.ticks_missed,
                s.tick_mean_ms,
                s.late_max_ms,
                s.offered / self.wall,
                s.sent / self.wall,
            );
            let cuts: Vec<String> = s.cuts.iter().map(|(c, n)| format!("{c} {n:.0}")).collect();
            println!(
                "adaptive rate     {:.0} pings/s; cuts by cause: {}",
                s.pings / self.wall,
                if cuts.is_empty() {
                    "none".to_owned()
                } else {
                    cuts.join(", ")
                }
            );
        }
        println!(
            "\n| clients N | wire | avatars M | frames/s delivered (expected) | B/frame | per client | p50 ms | p99 ms | max ms | missed | failures | server CPU | loadgen CPU |"
        );
        println!(
            "| {} | {} | {} | {fps:.0} ({expected:.0}) | {:.1} | {mean:.1} | {p50:.2} | {p99:.2} | {max:.1} | {:.2} % | {} | {} | {} |",
            self.clients,
            wire_name(self.protocol),
            self.avatars.map_or_else(|| "?".into(), |m| m.to_string()),
            self.bytes as f64 / self.frames.max(1) as f64,
            100.0 * self.missed as f64 / (expected * self.wall),
            self.failures,
            pct(self.server_cpu),
            pct(self.self_cpu),
        );
    }
}

/// The frames a protocol version's binary subscribers get.
pub fn wire_name(protocol: u32) -> String {
    match protocol {
        1 => "wire v1 (protocol 1)".into(),
        p => format!("wire v2 (protocol {p})"),
    }
}

/// Prints posecast's figures as ratios of the reference server's from the same run:
/// delivered frames (higher is better) and server CPU per delivered frame (lower is better).
pub fn compare(posecast: &Summary, reference: &Summary) {
    let fps = |s: &Summary| s.frames as f64 / s.wall;
    let cpu_per_frame_us =
        |s: &Summary| s.server_cpu.map(|cpu| cpu / 100.0 * 1e6 / fps(s).max(1.0));
    println!(
        "\nposecast / reference: delivered {:.2}× ({:.0} vs {:.0} frames/s)",
        fps(posecast) / fps(reference).max(1.0),
        fps(posecast),
        fps(reference)
    );
    if let (Some(p), Some(r)) = (cpu_per_frame_us(posecast), cpu_per_frame_us(reference)) {
        println!(
            "                      server CPU per frame {:.2}× ({p:.2} vs {r:.2} µs)",
            p / r.max(1e-9)
        );
    }
    println!(
        "                      p99 tick→receive {:.2} vs {:.2} ms",
        posecast.latency_ms[2], reference.latency_ms[2]
    );
}
