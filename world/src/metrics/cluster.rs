//! Counters of scale-out through NATS (`crate::cluster`): scenes this server ticks for the
//! cluster and scenes it relays, and the bytes it publishes to and receives from NATS. Kept
//! apart (`Metrics::cluster`) like the network and VMC counters; all zero on a server that is
//! not part of a cluster.

use crate::metrics::{GaugeU64, counter, gauge, labelled_counters};
use prometheus_client::metrics::counter::Counter;
use prometheus_client::registry::Registry;

/// The cluster counters. Relaxed atomics: exact totals, no ordering.
#[derive(Debug)]
pub struct ClusterCounters {
    owned: GaugeU64,
    relayed: GaugeU64,
    published: Counter,
    published_bytes: Counter,
    received: Counter,
    received_bytes: Counter,
    publish_dropped: Counter,
    takeovers: Counter,
    /// Relay messages not believed, by reason (`crate::cluster::RelayRefused::ALL`).
    relay_refused: [Counter; 4],
}

impl ClusterCounters {
    /// All zero, registered in `registry`.
    pub(crate) fn new(registry: &mut Registry) -> Self {
        let r = registry;
        Self {
            owned: gauge(
                r,
                "cluster_scenes_owned",
                "Scenes this server ticks for the cluster",
            ),
            relayed: gauge(
                r,
                "cluster_scenes_relayed",
                "Scenes ticked by another server whose frames this server relays",
            ),
            published: counter(r, "nats_published", "Messages published to NATS"),
            published_bytes: counter(r, "nats_published_bytes", "Payload bytes published to NATS"),
            received: counter(r, "nats_received", "Messages received from NATS"),
            received_bytes: counter(r, "nats_received_bytes", "Payload bytes received from NATS"),
            publish_dropped: counter(
                r,
                "nats_publish_dropped",
                "Frames not published because the queue to NATS was full",
            ),
            takeovers: counter(
                r,
                "cluster_takeovers",
                "Scenes this server took over after their owner's lease lapsed",
            ),
            relay_refused: labelled_counters(
                r,
                "cluster_relay_refused",
                "Relay messages dropped: a bad signature, not from the lease holder, an epoch the lease cannot have made, or deleted while the scene exists",
                "reason",
                ["signature", "not_owner", "epoch", "not_deleted"],
            ),
        }
    }

    /// Scenes owned and relayed now.
    pub fn scenes(&self, owned: u64, relayed: u64) {
        self.owned.set(owned);
        self.relayed.set(relayed);
    }

    /// A message of `bytes` published.
    pub fn published(&self, bytes: usize) {
        self.published.inc();
        self.published_bytes.inc_by(bytes as u64);
    }

    /// A relay message was dropped; `reason` is one of `signature`, `not_owner`, `epoch`,
    /// `not_deleted`.
    pub fn relay_refused(&self, reason: &str) {
        if let Some(c) = self.relay_refused_counter(reason) {
            c.inc();
        }
    }

    /// Relay messages dropped so far for `reason`.
    #[must_use]
    pub fn relay_refused_total(&self, reason: &str) -> u64 {
        self.relay_refused_counter(reason).map_or(0, Counter::get)
    }

    fn relay_refused_counter(&self, reason: &str) -> Option<&Counter> {
        let i = ["signature", "not_owner", "epoch", "not_deleted"]
            .iter()
            .position(|r| *r == reason)?;
        self.relay_refused.get(i)
    }

    /// A message of `bytes` received.
    pub fn received(&self, bytes: usize) {
        self.received.inc();
        self.received_bytes.inc_by(bytes as u64);
    }

    /// A frame dropped before publication (the queue to NATS was full).
    pub fn publish_dropped(&self) {
        self.publish_dropped.inc();
    }

    /// A scene taken over.
    pub fn takeover(&self) {
        self.takeovers.inc();
    }

    /// (published bytes, received bytes) so far.
    #[must_use]
    pub fn bytes(&self) -> (u64, u64) {
        (self.published_bytes.get(), self.received_bytes.get())
    }
}
