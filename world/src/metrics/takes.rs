//! Counters of takes of whole scenes (`crate::takes`): how many scenes are being recorded and
//! replayed, the bytes takes hold of the data quota and the bytes written, takes that ended by
//! themselves, and (in a cluster) takes put into and read from the cluster's store. Kept
//! apart (`Metrics::takes`) like the cluster and VMC counters.

use crate::metrics::{GaugeU64, counter, gauge};
use prometheus_client::metrics::counter::Counter;
use prometheus_client::registry::Registry;

/// The take counters. Relaxed atomics: exact totals, no ordering.
#[derive(Debug)]
pub struct TakeCounters {
    recording: GaugeU64,
    replays: GaugeU64,
    held_bytes: GaugeU64,
    written: Counter,
    ended: Counter,
    shared: Counter,
    fetched: Counter,
}

impl TakeCounters {
    /// All zero, registered in `registry`.
    pub(crate) fn new(registry: &mut Registry) -> Self {
        let r = registry;
        Self {
            recording: gauge(
                r,
                "takes_recording",
                "Scenes being recorded into a take now",
            ),
            replays: gauge(r, "replays", "Scenes replaying a take now"),
            held_bytes: gauge(
                r,
                "takes_held_bytes",
                "Bytes the takes hold (stored, in memory, queued): part of the data quota",
            ),
            written: counter(
                r,
                "take_bytes_written",
                "Bytes written to takes (frames, avatar lists, events)",
            ),
            ended: counter(
                r,
                "takes_ended_by_themselves",
                "Takes that ended without stop_recording_scene: a limit, the data quota, a failed write, a disk that could not keep up",
            ),
            shared: counter(
                r,
                "cluster_takes_shared",
                "Takes this server put into the cluster's store",
            ),
            fetched: counter(
                r,
                "cluster_takes_fetched",
                "Takes (or newer versions) this server read from the cluster's store",
            ),
        }
    }

    /// What is recorded, replayed and held now (set when the metrics are read).
    pub fn now(&self, recording: u64, replays: u64, held_bytes: u64) {
        self.recording.set(recording);
        self.replays.set(replays);
        self.held_bytes.set(held_bytes);
    }

    /// The counter of bytes written, for the takes' writers to add to.
    #[must_use]
    pub fn written(&self) -> Counter {
        self.written.clone()
    }

    /// The counter of takes that ended by themselves, for the takes' sinks.
    #[must_use]
    pub fn ended(&self) -> Counter {
        self.ended.clone()
    }

    /// A take put into the cluster's store.
    pub fn shared(&self) {
        self.shared.inc();
    }

    /// A take read from the cluster's store.
    pub fn fetched(&self) {
        self.fetched.inc();
    }
}
