//! Server counters and their Prometheus text exposition (`GET /metrics`, format 0.0.4), kept
//! and encoded by `prometheus-client`. Every metric is registered once, in [`Metrics::new`];
//! only the per-scene subscriber gauges, which depend on who asks, are built per request.

use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::time::Duration;

use prometheus_client::encoding::prometheus_text;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::metrics::histogram::Histogram;
use prometheus_client::registry::Registry;

use posecast_core::quota::Quota;
pub mod cluster;
pub mod net;
pub mod pace;
pub mod quic;
pub mod takes;
pub mod vmc;

use cluster::ClusterCounters;
use net::NetCounters;
use pace::PaceCounters;
use quic::QuicCounters;
use takes::TakeCounters;
use vmc::VmcCounters;

/// The `Content-Type` of [`Metrics::render`]'s text.
pub const CONTENT_TYPE: &str = prometheus_text::CONTENT_TYPE;

/// Every exposed name is `posecast_` and the registered name (counters also get `_total`).
const PREFIX: &str = "posecast";

/// Upper bounds (seconds) of the tick duration histogram buckets.
const TICK_BUCKETS: [f64; 10] = [
    0.0001, 0.00025, 0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1,
];

/// A gauge of unsigned values (prometheus-client's default gauge is `i64`).
pub(crate) type GaugeU64 = Gauge<u64, AtomicU64>;

/// Every counter the server keeps. Counters and gauges are relaxed atomics: exact totals, no
/// ordering.
#[derive(Debug)]
pub struct Metrics {
    /// Every metric but the per-request subscriber gauges; the fields below are handles to the
    /// same values.
    registry: Registry,
    connections_open: GaugeU64,
    connections_total: Counter,
    frames_offered: Counter,
    frame_bytes_offered: Counter,
    json_poses: Counter,
    messages_sent: Counter,
    bytes_sent: Counter,
    writer_wakes: Counter,
    frames_dropped: Counter,
    ticks_missed: Counter,
    tick_seconds: Histogram,
    scene_lock_seconds: Histogram,
    /// The histogram's count, for [`Self::ticks`] (prometheus-client reads it only in tests).
    ticks: AtomicU64,
    tick_late_micros_max: GaugeU64,
    commands: Counter,
    command_errors: Counter,
    protocol_errors: Counter,
    unauthorized: Counter,
    forbidden: Counter,
    /// By [`Quota::index`].
    quota_refused: [Counter; Quota::ALL.len()],
    rate_limited: Counter,
    // --- network bounds (issue 13): connections held and refused, timeouts ---
    /// Connections held and refused, accept failures, timeouts ([`NetCounters`]).
    pub net: NetCounters,
    // --- the VMC gateway (issue 17) ---
    /// VMC datagrams in, refusals, poses applied, bundles out ([`VmcCounters`]).
    pub vmc: VmcCounters,
    // --- the adaptive frame rate (issue 22) ---
    /// Connections per adaptive rate step, rate changes ([`PaceCounters`]).
    pub pace: PaceCounters,
    // --- scale-out (issue 15) ---
    /// Scenes owned and relayed, NATS bytes ([`ClusterCounters`]).
    pub cluster: ClusterCounters,
    /// Takes of whole scenes ([`TakeCounters`]).
    pub takes: TakeCounters,
    /// The WebTransport endpoint ([`QuicCounters`]).
    pub quic: QuicCounters,
}

impl Default for Metrics {
    fn default() -> Self {
        Self::new()
    }
}

impl Metrics {
    /// All zero. (prometheus-client ends every help text with a full stop.)
    #[must_use]
    pub fn new() -> Self {
        let mut registry = Registry::with_prefix(PREFIX);
        let r = &mut registry;
        let connections_open = gauge(r, "connections_open", "Open websocket connections");
        let connections_total = counter(r, "connections", "Websocket connections accepted");
        let frames_offered = counter(
            r,
            "frames_offered",
            "Pose frames handed to subscriber outboxes",
        );
        let frame_bytes_offered = counter(
            r,
            "frame_bytes_offered",
            "Bytes of pose frames handed to outboxes",
        );
        let json_poses = counter(
            r,
            "json_poses_encoded",
            "Avatar poses serialised to JSON (only while a JSON subscriber needs them)",
        );
        let messages_sent = counter(r, "messages_sent", "Websocket messages written");
        let bytes_sent = counter(r, "bytes_sent", "Websocket payload bytes written");
        let writer_wakes = counter(
            r,
            "writer_wakes",
            "Times a connection's writer task woke to write: a websocket's when its socket was full or it closed (a socket with room is written by whatever queued the message), a WebTransport session's for each batch",
        );
        let frames_dropped = counter(
            r,
            "frames_dropped",
            "Frames replaced by newer ones before a slow client read them (closed connections)",
        );
        let ticks_missed = counter(
            r,
            "ticks_missed",
            "Ticks skipped because the tick task ran late",
        );
        let tick_late_micros_max = gauge(
            r,
            "tick_late_seconds_max_micros",
            "Largest delay of a tick after its deadline, microseconds",
        );
        let commands = counter(r, "commands", "Commands handled");
        let command_errors = counter(r, "command_errors", "Commands that failed");
        let protocol_errors = counter(r, "protocol_errors", "Invalid client messages");
        let rate_limited = counter(
            r,
            "rate_limited",
            "Commands refused by a connection's rate limit",
        );
        let [unauthorized, forbidden] = labelled_counters(
            r,
            "refused",
            "Requests and messages refused for their token",
            "code",
            ["unauthorized", "forbidden"],
        );
        let quota_refused = labelled_counters(
            r,
            "quota_refused",
            "Requests refused by a quota",
            "quota",
            Quota::ALL.map(Quota::name),
        );
        let tick_seconds = Histogram::new(TICK_BUCKETS);
        r.register(
            "tick_seconds",
            "Time to run one scene tick",
            tick_seconds.clone(),
        );
        let scene_lock_seconds = Histogram::new(TICK_BUCKETS);
        r.register(
            "scene_lock_seconds",
            "Time a tick holds its scene's lock (moving the avatars and copying their poses; the frame is encoded and fanned out after)",
            scene_lock_seconds.clone(),
        );
        let net = NetCounters::new(r);
        let vmc = VmcCounters::new(r);
        let pace = PaceCounters::new(r);
        let cluster = ClusterCounters::new(r);
        let takes = TakeCounters::new(r);
        let quic = QuicCounters::new(r);
        Self {
            registry,
            connections_open,
            connections_total,
            frames_offered,
            frame_bytes_offered,
            json_poses,
            messages_sent,
            bytes_sent,
            writer_wakes,
            frames_dropped,
            ticks_missed,
            tick_seconds,
            scene_lock_seconds,
            ticks: AtomicU64::new(0),
            tick_late_micros_max,
            commands,
            command_errors,
            protocol_errors,
            unauthorized,
            forbidden,
            quota_refused,
            rate_limited,
            net,
            vmc,
            pace,
            cluster,
            takes,
            quic,
        }
    }

    /// A websocket connection opened.
    pub fn connection_opened(&self) {
        self.connections_open.inc();
        self.connections_total.inc();
    }

    /// A websocket connection closed; `dropped` frames were replaced before it read them.
    pub fn connection_closed(&self, dropped: u64) {
        self.connections_open.dec();
        self.frames_dropped.inc_by(dropped);
    }

    /// A tick offered `frames` frames of `bytes` bytes in all to subscribers.
    pub fn frames_offered(&self, frames: u64, bytes: u64) {
        self.frames_offered.inc_by(frames);
        self.frame_bytes_offered.inc_by(bytes);
    }

    /// A tick (or a JSON late joiner) serialised `poses` avatar poses to JSON.
    pub fn json_encoded(&self, poses: u64) {
        self.json_poses.inc_by(poses);
    }

    /// Avatar poses serialised to JSON so far.
    #[must_use]
    pub fn json_poses_encoded(&self) -> u64 {
        self.json_poses.get()
    }

    /// A writer sent `messages` websocket messages of `bytes` bytes.
    pub fn sent(&self, messages: u64, bytes: u64) {
        self.messages_sent.inc_by(messages);
        self.bytes_sent.inc_by(bytes);
    }

    /// A websocket's writer task woke (its socket was full, or the connection closed).
    pub fn writer_woke(&self) {
        self.writer_wakes.inc();
    }

    /// Wake-ups of websocket writer tasks so far.
    #[must_use]
    pub fn writer_wakes(&self) -> u64 {
        self.writer_wakes.get()
    }

    /// `n` ticks were skipped because the tick task ran late.
    pub fn ticks_missed(&self, n: u64) {
        self.ticks_missed.inc_by(n);
    }

    /// A tick took `took`, started `late` after its deadline and held its scene's lock for
    /// `held` of that.
    pub fn tick_done(&self, took: Duration, late: Duration, held: Duration) {
        self.ticks.fetch_add(1, Relaxed);
        self.tick_seconds.observe(took.as_secs_f64());
        self.scene_lock_seconds.observe(held.as_secs_f64());
        self.tick_late_micros_max
            .inner()
            .fetch_max(late.as_micros() as u64, Relaxed);
    }

    /// A command was handled; `ok` says whether it succeeded.
    pub fn command(&self, ok: bool) {
        self.commands.inc();
        if !ok {
            self.command_errors.inc();
        }
    }

    /// A request or message was refused for its token: `forbidden` (a valid token without
    /// the right) or unauthorized (missing or unknown token).
    pub fn refused(&self, forbidden: bool) {
        if forbidden {
            self.forbidden.inc();
        } else {
            self.unauthorized.inc();
        }
    }

    /// A request was refused by a quota.
    pub fn quota_refused(&self, quota: Quota) {
        if let Some(counter) = self.quota_refused.get(quota.index()) {
            counter.inc();
        }
    }

    /// Counts a refusal by `quota` and returns its typed error ([`Quota::exceeded`]).
    #[must_use]
    pub fn refuse_quota(
        &self,
        quota: Quota,
        what: impl std::fmt::Display,
        limit: impl std::fmt::Display,
    ) -> posecast_core::error::Error {
        self.quota_refused(quota);
        quota.exceeded(what, limit)
    }

    /// A command was refused by a connection's rate limit.
    pub fn rate_limited(&self) {
        self.rate_limited.inc();
    }

    /// A client sent something invalid.
    pub fn protocol_error(&self) {
        self.protocol_errors.inc();
    }

    /// Pose frames handed to subscriber outboxes so far.
    #[must_use]
    pub fn frames_offered_total(&self) -> u64 {
        self.frames_offered.get()
    }

    /// Bytes of those frames.
    #[must_use]
    pub fn frame_bytes_offered_total(&self) -> u64 {
        self.frame_bytes_offered.get()
    }

    /// Ticks run so far.
    #[must_use]
    pub fn ticks(&self) -> u64 {
        self.ticks.load(Relaxed)
    }

    /// Ticks skipped so far.
    #[must_use]
    pub fn missed(&self) -> u64 {
        self.ticks_missed.get()
    }

    /// The Prometheus text format (version 0.0.4, [`CONTENT_TYPE`]). `subscribers` is per scene
    /// (only the scenes the caller may see by name), `total_subscribers` over every scene.
    ///
    /// # Errors
    /// Only if a metric fails to encode, which writing to a `String` does not.
    pub fn render(
        &self,
        subscribers: &[(String, usize)],
        total_subscribers: usize,
    ) -> Result<String, std::fmt::Error> {
        let mut per_request = Registry::with_prefix(PREFIX);
        gauge(
            &mut per_request,
            "subscribers_total_open",
            "Subscriptions open, over every scene",
        )
        .set(total_subscribers as u64);
        let per_scene = Family::<[(&'static str, String); 1], GaugeU64>::default();
        for (scene, n) in subscribers {
            per_scene
                .get_or_create(&[("scene", scene.clone())])
                .set(*n as u64);
        }
        per_request.register("subscribers", "Subscribers per scene", per_scene);
        let mut out = String::new();
        prometheus_text::encode(&mut out, &self.registry)?;
        prometheus_text::encode(&mut out, &per_request)?;
        Ok(out)
    }
}

/// Registers and returns a counter, exposed as `posecast_{name}_total`.
pub(crate) fn counter(registry: &mut Registry, name: &str, help: &str) -> Counter {
    let counter = Counter::default();
    registry.register(name, help, counter.clone());
    counter
}

/// Registers and returns a gauge, exposed as `posecast_{name}`.
pub(crate) fn gauge(registry: &mut Registry, name: &str, help: &str) -> GaugeU64 {
    let gauge = GaugeU64::default();
    registry.register(name, help, gauge.clone());
    gauge
}

/// Registers `name` as a family with one counter per value of label `key`, each created here
/// so that every value is exposed from zero, and returns the counters in the order of `values`.
pub(crate) fn labelled_counters<const N: usize>(
    registry: &mut Registry,
    name: &str,
    help: &str,
    key: &'static str,
    values: [&'static str; N],
) -> [Counter; N] {
    let family = Family::<[(&'static str, &'static str); 1], Counter>::default();
    let counters = values.map(|value| family.get_or_create(&[(key, value)]).clone());
    registry.register(name, help, family);
    counters
}

/// The stream layer counts into the server's metrics.
impl posecast_stream::Counters for Metrics {
    fn frames_offered(&self, frames: u64, bytes: u64) {
        Metrics::frames_offered(self, frames, bytes);
    }

    fn json_encoded(&self, poses: u64) {
        Metrics::json_encoded(self, poses);
    }

    fn sent(&self, messages: u64, bytes: u64) {
        Metrics::sent(self, messages, bytes);
    }

    fn writer_woke(&self) {
        Metrics::writer_woke(self);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::BTreeSet;

    /// The sample lines of a fresh server, as the hand-written exposition this encoder replaced
    /// printed them (names, labels and zero values; the histogram's sum was printed as `0`).
    const BEFORE: &str = r#"posecast_connections_open 0
posecast_connections_total 0
posecast_frames_offered_total 0
posecast_frame_bytes_offered_total 0
posecast_json_poses_encoded_total 0
posecast_messages_sent_total 0
posecast_bytes_sent_total 0
posecast_writer_wakes_total 0
posecast_frames_dropped_total 0
posecast_ticks_missed_total 0
posecast_tick_late_seconds_max_micros 0
posecast_commands_total 0
posecast_command_errors_total 0
posecast_protocol_errors_total 0
posecast_rate_limited_total 0
posecast_refused_total{code="unauthorized"} 0
posecast_refused_total{code="forbidden"} 0
posecast_quota_refused_total{quota="scenes"} 0
posecast_quota_refused_total{quota="avatars_per_scene"} 0
posecast_quota_refused_total{quota="joints"} 0
posecast_quota_refused_total{quota="limited_joints"} 0
posecast_quota_refused_total{quota="clip_joint_seconds"} 0
posecast_quota_refused_total{quota="asset_bytes"} 0
posecast_quota_refused_total{quota="upload_total_bytes"} 0
posecast_quota_refused_total{quota="retarget_bytes"} 0
posecast_quota_refused_total{quota="token_bytes"} 0
posecast_quota_refused_total{quota="token_objects"} 0
posecast_subscribers_total_open 0
posecast_subscribers{scene="default"} 0
posecast_tick_seconds_bucket{le="0.0001"} 0
posecast_tick_seconds_bucket{le="0.00025"} 0
posecast_tick_seconds_bucket{le="0.0005"} 0
posecast_tick_seconds_bucket{le="0.001"} 0
posecast_tick_seconds_bucket{le="0.0025"} 0
posecast_tick_seconds_bucket{le="0.005"} 0
posecast_tick_seconds_bucket{le="0.01"} 0
posecast_tick_seconds_bucket{le="0.025"} 0
posecast_tick_seconds_bucket{le="0.05"} 0
posecast_tick_seconds_bucket{le="0.1"} 0
posecast_tick_seconds_bucket{le="+Inf"} 0
posecast_tick_seconds_sum 0
posecast_tick_seconds_count 0
posecast_scene_lock_seconds_bucket{le="0.0001"} 0
posecast_scene_lock_seconds_bucket{le="0.00025"} 0
posecast_scene_lock_seconds_bucket{le="0.0005"} 0
posecast_scene_lock_seconds_bucket{le="0.001"} 0
posecast_scene_lock_seconds_bucket{le="0.0025"} 0
posecast_scene_lock_seconds_bucket{le="0.005"} 0
posecast_scene_lock_seconds_bucket{le="0.01"} 0
posecast_scene_lock_seconds_bucket{le="0.025"} 0
posecast_scene_lock_seconds_bucket{le="0.05"} 0
posecast_scene_lock_seconds_bucket{le="0.1"} 0
posecast_scene_lock_seconds_bucket{le="+Inf"} 0
posecast_scene_lock_seconds_sum 0
posecast_scene_lock_seconds_count 0
posecast_tcp_connections_open 0
posecast_tcp_connections_accepted_total 0
posecast_connections_refused_total{cap="global"} 0
posecast_connections_refused_total{cap="per_address"} 0
posecast_connections_unanswered_total 0
posecast_connections_evicted_total{stage="unproven"} 0
posecast_connections_evicted_total{stage="anonymous"} 0
posecast_accept_errors_total 0
posecast_timeouts_total{kind="hello"} 0
posecast_timeouts_total{kind="header"} 0
posecast_timeouts_total{kind="body"} 0
posecast_timeouts_total{kind="idle"} 0
posecast_vmc_packets_total 0
posecast_vmc_packet_bytes_total 0
posecast_vmc_packets_dropped_total{reason="malformed"} 0
posecast_vmc_packets_dropped_total{reason="too_deep"} 0
posecast_vmc_packets_dropped_total{reason="flood"} 0
posecast_vmc_packets_dropped_total{reason="sender"} 0
posecast_vmc_messages_rejected_total{reason="unknown_address"} 0
posecast_vmc_messages_rejected_total{reason="bad_arguments"} 0
posecast_vmc_messages_rejected_total{reason="invalid_value"} 0
posecast_vmc_messages_rejected_total{reason="unknown_bone"} 0
posecast_vmc_messages_rejected_total{reason="blend_shape_limit"} 0
posecast_vmc_messages_rejected_total{reason="device_limit"} 0
posecast_vmc_poses_total 0
posecast_vmc_poses_refused_total{reason="busy"} 0
posecast_vmc_poses_refused_total{reason="no_avatar"} 0
posecast_vmc_poses_refused_total{reason="not_humanoid"} 0
posecast_vmc_bundles_sent_total 0
posecast_vmc_bytes_sent_total 0
posecast_vmc_send_errors_total 0
posecast_connection_rate{per_60_ticks="60"} 0
posecast_connection_rate{per_60_ticks="45"} 0
posecast_connection_rate{per_60_ticks="30"} 0
posecast_connection_rate{per_60_ticks="24"} 0
posecast_connection_rate{per_60_ticks="20"} 0
posecast_connection_rate{per_60_ticks="15"} 0
posecast_connection_rate{per_60_ticks="12"} 0
posecast_connection_rate{per_60_ticks="10"} 0
posecast_connection_rate{per_60_ticks="8"} 0
posecast_connection_rate{per_60_ticks="6"} 0
posecast_connection_rate{per_60_ticks="5"} 0
posecast_connection_rate{per_60_ticks="4"} 0
posecast_connection_rate{per_60_ticks="3"} 0
posecast_connection_rate{per_60_ticks="2"} 0
posecast_connection_rate{per_60_ticks="1"} 0
posecast_rate_changes_total{way="down"} 0
posecast_rate_changes_total{way="up"} 0
posecast_rate_cuts_total{cause="round_trips"} 0
posecast_rate_cuts_total{cause="socket"} 0
posecast_rate_cuts_total{cause="unanswered"} 0
posecast_rate_cuts_total{cause="superseded"} 0
posecast_rate_cuts_total{cause="path"} 0
posecast_probe_pings_total 0
posecast_cluster_scenes_owned 0
posecast_cluster_scenes_relayed 0
posecast_nats_published_total 0
posecast_nats_published_bytes_total 0
posecast_nats_received_total 0
posecast_nats_received_bytes_total 0
posecast_nats_publish_dropped_total 0
posecast_cluster_takeovers_total 0
posecast_cluster_relay_refused_total{reason="signature"} 0
posecast_cluster_relay_refused_total{reason="not_owner"} 0
posecast_cluster_relay_refused_total{reason="epoch"} 0
posecast_cluster_relay_refused_total{reason="not_deleted"} 0
posecast_takes_recording 0
posecast_replays 0
posecast_takes_held_bytes 0
posecast_take_bytes_written_total 0
posecast_takes_ended_by_themselves_total 0
posecast_cluster_takes_shared_total 0
posecast_cluster_takes_fetched_total 0
posecast_quic_sessions_total 0
posecast_quic_frames_total{via="datagram"} 0
posecast_quic_frames_total{via="stream"} 0
posecast_quic_frames_total{via="superseded"} 0
posecast_quic_datagram_bytes_total 0
posecast_quic_split_frames_total 0
posecast_quic_key_acks_total 0
posecast_quic_frame_acks_total 0
posecast_quic_datagrams_ignored_total 0
posecast_quic_refused_total 0
posecast_quic_sessions_open 0
posecast_quic_sessions_evicted_total{stage="unproven"} 0
posecast_quic_sessions_evicted_total{stage="anonymous"} 0
posecast_quic_retries_total 0"#;

    /// Sample lines with their values parsed, so `0` and `0.0` compare equal.
    fn samples(text: &str) -> BTreeSet<(String, u64)> {
        text.lines()
            .filter(|l| !l.starts_with('#') && !l.is_empty())
            .map(|l| {
                let (name, value) = l.rsplit_once(' ').unwrap();
                let value: f64 = value.parse().unwrap();
                (name.to_owned(), value.to_bits())
            })
            .collect()
    }

    #[test]
    fn a_fresh_server_exposes_the_same_samples_as_before() {
        let text = Metrics::new().render(&[("default".into(), 0)], 0).unwrap();
        assert_eq!(samples(&text), samples(BEFORE), "{text}");
    }

    #[test]
    fn every_family_has_help_and_type_under_its_sample_name() {
        let text = Metrics::new().render(&[("default".into(), 0)], 0).unwrap();
        for (name, kind) in [
            ("posecast_connections_total", "counter"),
            ("posecast_connections_open", "gauge"),
            ("posecast_refused_total", "counter"),
            ("posecast_tick_seconds", "histogram"),
            ("posecast_timeouts_total", "counter"),
            ("posecast_subscribers", "gauge"),
        ] {
            assert!(
                text.contains(&format!("# TYPE {name} {kind}\n")),
                "{name}: {text}"
            );
            assert!(text.contains(&format!("# HELP {name} ")), "{name}: {text}");
        }
        assert!(text.contains("# HELP posecast_commands_total Commands handled.\n"));
    }

    #[test]
    fn counts_land_in_their_samples() {
        let m = Metrics::new();
        m.connection_opened();
        m.connection_opened();
        m.connection_closed(3);
        m.refused(true);
        m.quota_refused(Quota::Joints);
        m.net.timed_out(net::Timeout::Idle);
        // 0.3 ms: above the 0.25 ms bucket, inside the 0.5 ms one; 0.2 s: only in +Inf.
        m.tick_done(
            Duration::from_micros(300),
            Duration::from_micros(40),
            Duration::from_micros(60),
        );
        m.tick_done(
            Duration::from_millis(200),
            Duration::from_micros(7),
            Duration::from_micros(90),
        );
        let text = m.render(&[("a\"b\\c\nd".into(), 2)], 5).unwrap();
        for line in [
            "posecast_connections_open 1",
            "posecast_connections_total 2",
            "posecast_frames_dropped_total 3",
            "posecast_refused_total{code=\"forbidden\"} 1",
            "posecast_refused_total{code=\"unauthorized\"} 0",
            "posecast_quota_refused_total{quota=\"joints\"} 1",
            "posecast_timeouts_total{kind=\"idle\"} 1",
            "posecast_tick_seconds_bucket{le=\"0.00025\"} 0",
            "posecast_tick_seconds_bucket{le=\"0.0005\"} 1",
            "posecast_tick_seconds_bucket{le=\"0.1\"} 1",
            "posecast_tick_seconds_bucket{le=\"+Inf\"} 2",
            "posecast_tick_seconds_sum 0.2003",
            "posecast_tick_seconds_count 2",
            "posecast_tick_late_seconds_max_micros 40",
            // 60 µs and 90 µs: both under the 0.1 ms bucket.
            "posecast_scene_lock_seconds_bucket{le=\"0.0001\"} 2",
            "posecast_scene_lock_seconds_count 2",
            "posecast_subscribers_total_open 5",
            // The label value escaped as the text format requires: \" \\ \n.
            "posecast_subscribers{scene=\"a\\\"b\\\\c\\nd\"} 2",
        ] {
            assert!(text.lines().any(|l| l == line), "no {line:?} in\n{text}");
        }
        assert_eq!(m.ticks(), 2);
    }
}
