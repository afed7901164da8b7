//! Server counters and their Prometheus text exposition (`GET /metrics`).

use std::fmt::Write as _;
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::time::Duration;

pub mod net;

use net::NetCounters;

/// Upper bounds (seconds) of the tick duration histogram buckets.
const TICK_BUCKETS: [f64; 10] = [
    0.0001, 0.00025, 0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1,
];

/// Every counter the server keeps. All updates are relaxed atomics: exact totals, no ordering.
#[derive(Debug, Default)]
pub struct Metrics {
    connections_open: AtomicU64,
    connections_total: AtomicU64,
    frames_offered: AtomicU64,
    frame_bytes_offered: AtomicU64,
    json_poses: AtomicU64,
    messages_sent: AtomicU64,
    bytes_sent: AtomicU64,
    frames_dropped: AtomicU64,
    ticks: AtomicU64,
    ticks_missed: AtomicU64,
    tick_buckets: [AtomicU64; TICK_BUCKETS.len()],
    tick_seconds_micros: AtomicU64,
    tick_late_micros_max: AtomicU64,
    commands: AtomicU64,
    command_errors: AtomicU64,
    protocol_errors: AtomicU64,
    unauthorized: AtomicU64,
    forbidden: AtomicU64,
    quota_refused: [AtomicU64; crate::quota::Quota::ALL.len()],
    rate_limited: AtomicU64,
    // --- network bounds (issue 13): connections held and refused, timeouts ---
    /// Connections held and refused, accept failures, timeouts ([`NetCounters`]).
    pub net: NetCounters,
}

impl Metrics {
    /// All zero.
    #[must_use]
    pub fn new() -> Self {
        Self::default()
    }

    /// A websocket connection opened.
    pub fn connection_opened(&self) {
        self.connections_open.fetch_add(1, Relaxed);
        self.connections_total.fetch_add(1, Relaxed);
    }

    /// A websocket connection closed; `dropped` frames were replaced before it read them.
    pub fn connection_closed(&self, dropped: u64) {
        self.connections_open.fetch_sub(1, Relaxed);
        self.frames_dropped.fetch_add(dropped, Relaxed);
    }

    /// A tick offered `frames` frames of `bytes` bytes in all to subscribers.
    pub fn frames_offered(&self, frames: u64, bytes: u64) {
        self.frames_offered.fetch_add(frames, Relaxed);
        self.frame_bytes_offered.fetch_add(bytes, Relaxed);
    }

    /// A tick (or a JSON late joiner) serialised `poses` avatar poses to JSON.
    pub fn json_encoded(&self, poses: u64) {
        self.json_poses.fetch_add(poses, Relaxed);
    }

    /// Avatar poses serialised to JSON so far.
    #[must_use]
    pub fn json_poses_encoded(&self) -> u64 {
        self.json_poses.load(Relaxed)
    }

    /// A writer sent `messages` websocket messages of `bytes` bytes.
    pub fn sent(&self, messages: u64, bytes: u64) {
        self.messages_sent.fetch_add(messages, Relaxed);
        self.bytes_sent.fetch_add(bytes, Relaxed);
    }

    /// `n` ticks were skipped because the tick task ran late.
    pub fn ticks_missed(&self, n: u64) {
        self.ticks_missed.fetch_add(n, Relaxed);
    }

    /// A tick took `took` and started `late` after its deadline.
    pub fn tick_done(&self, took: Duration, late: Duration) {
        self.ticks.fetch_add(1, Relaxed);
        let secs = took.as_secs_f64();
        if let Some(i) = TICK_BUCKETS.iter().position(|&b| secs <= b) {
            self.tick_buckets[i].fetch_add(1, Relaxed);
        }
        self.tick_seconds_micros
            .fetch_add(took.as_micros() as u64, Relaxed);
        self.tick_late_micros_max
            .fetch_max(late.as_micros() as u64, Relaxed);
    }

    /// A command was handled; `ok` says whether it succeeded.
    pub fn command(&self, ok: bool) {
        self.commands.fetch_add(1, Relaxed);
        if !ok {
            self.command_errors.fetch_add(1, Relaxed);
        }
    }

    /// A request or message was refused for its token: `forbidden` (a valid token without
    /// the right) or unauthorized (missing or unknown token).
    pub fn refused(&self, forbidden: bool) {
        if forbidden {
            self.forbidden.fetch_add(1, Relaxed);
        } else {
            self.unauthorized.fetch_add(1, Relaxed);
        }
    }

    /// A request was refused by a quota.
    pub fn quota_refused(&self, quota: crate::quota::Quota) {
        self.quota_refused[quota.index()].fetch_add(1, Relaxed);
    }

    /// Counts a refusal by `quota` and returns its typed error ([`crate::quota::Quota::exceeded`]).
    #[must_use]
    pub fn refuse_quota(
        &self,
        quota: crate::quota::Quota,
        what: impl std::fmt::Display,
        limit: impl std::fmt::Display,
    ) -> crate::error::Error {
        self.quota_refused(quota);
        quota.exceeded(what, limit)
    }

    /// A command was refused by a connection's rate limit.
    pub fn rate_limited(&self) {
        self.rate_limited.fetch_add(1, Relaxed);
    }

    /// A client sent something invalid.
    pub fn protocol_error(&self) {
        self.protocol_errors.fetch_add(1, Relaxed);
    }

    /// Ticks run so far.
    #[must_use]
    pub fn ticks(&self) -> u64 {
        self.ticks.load(Relaxed)
    }

    /// Ticks skipped so far.
    #[must_use]
    pub fn missed(&self) -> u64 {
        self.ticks_missed.load(Relaxed)
    }

    /// The Prometheus text format (version 0.0.4). `subscribers` is per scene (only the scenes
    /// the caller may see by name), `total_subscribers` over every scene.
    #[must_use]
    pub fn render(&self, subscribers: &[(String, usize)], total_subscribers: usize) -> String {
        let mut out = String::new();
        let mut counter = |name: &str, help: &str, kind: &str, v: u64| {
            let _ = writeln!(
                out,
                "# HELP posecast_{name} {help}\n# TYPE posecast_{name} {kind}\nposecast_{name} {v}"
            );
        };
        counter(
            "connections_open",
            "Open websocket connections.",
            "gauge",
            self.connections_open.load(Relaxed),
        );
        counter(
            "connections_total",
            "Websocket connections accepted.",
            "counter",
            self.connections_total.load(Relaxed),
        );
        counter(
            "frames_offered_total",
            "Pose frames handed to subscriber outboxes.",
            "counter",
            self.frames_offered.load(Relaxed),
        );
        counter(
            "frame_bytes_offered_total",
            "Bytes of pose frames handed to outboxes.",
            "counter",
            self.frame_bytes_offered.load(Relaxed),
        );
        counter(
            "json_poses_encoded_total",
            "Avatar poses serialised to JSON (only while a JSON subscriber needs them).",
            "counter",
            self.json_poses.load(Relaxed),
        );
        counter(
            "messages_sent_total",
            "Websocket messages written.",
            "counter",
            self.messages_sent.load(Relaxed),
        );
        counter(
            "bytes_sent_total",
            "Websocket payload bytes written.",
            "counter",
            self.bytes_sent.load(Relaxed),
        );
        counter(
            "frames_dropped_total",
            "Frames replaced by newer ones before a slow client read them (closed connections).",
            "counter",
            self.frames_dropped.load(Relaxed),
        );
        counter(
            "ticks_missed_total",
            "Ticks skipped because the tick task ran late.",
            "counter",
            self.ticks_missed.load(Relaxed),
        );
        counter(
            "tick_late_seconds_max_micros",
            "Largest delay of a tick after its deadline, microseconds.",
            "gauge",
            self.tick_late_micros_max.load(Relaxed),
        );
        counter(
            "commands_total",
            "Commands handled.",
            "counter",
            self.commands.load(Relaxed),
        );
        counter(
            "command_errors_total",
            "Commands that failed.",
            "counter",
            self.command_errors.load(Relaxed),
        );
        counter(
            "protocol_errors_total",
            "Invalid client messages.",
            "counter",
            self.protocol_errors.load(Relaxed),
        );
        counter(
            "rate_limited_total",
            "Commands refused by a connection's rate limit.",
            "counter",
            self.rate_limited.load(Relaxed),
        );
        let _ = writeln!(
            out,
            "# HELP posecast_refused_total Requests and messages refused for their token.\n\
             # TYPE posecast_refused_total counter\n\
             posecast_refused_total{{code=\"unauthorized\"}} {}\n\
             posecast_refused_total{{code=\"forbidden\"}} {}",
            self.unauthorized.load(Relaxed),
            self.forbidden.load(Relaxed)
        );
        let _ = writeln!(
            out,
            "# HELP posecast_quota_refused_total Requests refused by a quota.\n\
             # TYPE posecast_quota_refused_total counter"
        );
        for q in crate::quota::Quota::ALL {
            let _ = writeln!(
                out,
                "posecast_quota_refused_total{{quota=\"{}\"}} {}",
                q.name(),
                self.quota_refused[q.index()].load(Relaxed)
            );
        }
        let _ = writeln!(
            out,
            "# HELP posecast_subscribers_total_open Subscriptions open, over every scene.\n\
             # TYPE posecast_subscribers_total_open gauge\n\
             posecast_subscribers_total_open {total_subscribers}"
        );
        let _ = writeln!(
            out,
            "# HELP posecast_subscribers Subscribers per scene.\n# TYPE posecast_subscribers gauge"
        );
        for (scene, n) in subscribers {
            let _ = writeln!(
                out,
                "posecast_subscribers{{scene=\"{}\"}} {n}",
                escape_label(scene)
            );
        }
        let _ = writeln!(
            out,
            "# HELP posecast_tick_seconds Time to run one scene tick.\n# TYPE posecast_tick_seconds histogram"
        );
        let mut cumulative = 0;
        for (b, c) in TICK_BUCKETS.iter().zip(&self.tick_buckets) {
            cumulative += c.load(Relaxed);
            let _ = writeln!(
                out,
                "posecast_tick_seconds_bucket{{le=\"{b}\"}} {cumulative}"
            );
        }
        let count = self.ticks.load(Relaxed);
        let _ = writeln!(out, "posecast_tick_seconds_bucket{{le=\"+Inf\"}} {count}");
        let _ = writeln!(
            out,
            "posecast_tick_seconds_sum {}",
            self.tick_seconds_micros.load(Relaxed) as f64 / 1e6
        );
        let _ = writeln!(out, "posecast_tick_seconds_count {count}");
        self.net.render(&mut out);
        out
    }
}

fn escape_label(s: &str) -> String {
    s.replace('\\', "\\\\")
        .replace('"', "\\\"")
        .replace('\n', "\\n")
}
