//! Counters of the WebTransport endpoint (`crate::service::quic`): sessions, frames sent as
//! datagrams and on the stream, keyframe acknowledgements. Kept apart (`Metrics::quic`) like
//! the cluster and VMC counters; all zero without `--quic-listen`.

use crate::metrics::{GaugeU64, counter, gauge, labelled_counters};
use prometheus_client::metrics::counter::Counter;
use prometheus_client::registry::Registry;

/// The WebTransport counters. Relaxed atomics: exact totals, no ordering.
#[derive(Debug)]
pub struct QuicCounters {
    sessions: Counter,
    /// Frames sent, by how: `datagram`, `stream` (larger than a datagram), and those not sent
    /// (`superseded`: QUIC's congestion control held frames already).
    frames: [Counter; 3],
    datagram_bytes: Counter,
    /// Frames too large for one datagram, cut by avatar into several.
    split: Counter,
    key_acks: Counter,
    /// Frame acknowledgements (protocol versions 8 and 9).
    frame_acks: Counter,
    /// Datagrams from clients that are not acknowledgements.
    junk: Counter,
    refused: Counter,
    open: GaugeU64,
    /// Unproven, anonymous.
    evicted: [Counter; 2],
    retries: Counter,
}

impl QuicCounters {
    /// All zero, registered in `registry`.
    pub(crate) fn new(registry: &mut Registry) -> Self {
        let r = registry;
        Self {
            sessions: counter(r, "quic_sessions", "WebTransport sessions established"),
            frames: labelled_counters(
                r,
                "quic_frames",
                "Frames over WebTransport: sent as datagrams, on the stream (too large for one), or superseded (QUIC's congestion control held frames already)",
                "via",
                ["datagram", "stream", "superseded"],
            ),
            datagram_bytes: counter(
                r,
                "quic_datagram_bytes",
                "Bytes of frames sent as datagrams",
            ),
            split: counter(
                r,
                "quic_split_frames",
                "Frames too large for one datagram, sent cut by avatar into several (each part counts as a datagram frame)",
            ),
            key_acks: counter(
                r,
                "quic_key_acks",
                "Keyframe acknowledgements received from WebTransport clients",
            ),
            frame_acks: counter(
                r,
                "quic_frame_acks",
                "Frame acknowledgements received from WebTransport clients of protocol version 8 or later (one per frame, or part of a frame, decoded)",
            ),
            junk: counter(
                r,
                "quic_datagrams_ignored",
                "Datagrams from WebTransport clients that are not acknowledgements",
            ),
            refused: counter(
                r,
                "quic_refused",
                "WebTransport sessions refused over a connection cap (429), or an anonymous hello past the authenticated clients' headroom",
            ),
            open: gauge(
                r,
                "quic_sessions_open",
                "WebTransport sessions holding a place under the connection caps",
            ),
            evicted: labelled_counters(
                r,
                "quic_sessions_evicted",
                "WebTransport sessions closed at the global cap to admit a newcomer (stage: no hello yet, or an idle anonymous session)",
                "stage",
                ["unproven", "anonymous"],
            ),
            retries: counter(
                r,
                "quic_retries",
                "New WebTransport clients answered with a QUIC Retry (their address proven before the handshake: --quic-retry)",
            ),
        }
    }

    /// A session established.
    pub fn session(&self) {
        self.sessions.inc();
    }

    /// A frame of `bytes` sent as a datagram.
    pub fn datagram(&self, bytes: usize) {
        self.frames[0].inc();
        self.datagram_bytes.inc_by(bytes as u64);
    }

    /// A frame cut by avatar into several datagrams.
    pub fn split(&self) {
        self.split.inc();
    }

    /// A frame not sent: QUIC held frames already.
    pub fn superseded(&self) {
        self.frames[2].inc();
    }

    /// A frame sent on the stream.
    pub fn on_stream(&self) {
        self.frames[1].inc();
    }

    /// A keyframe acknowledgement received.
    pub fn key_ack(&self) {
        self.key_acks.inc();
    }

    /// A frame acknowledgement received (protocol versions 8 and 9).
    pub fn frame_ack(&self) {
        self.frame_acks.inc();
    }

    /// A session refused over a cap.
    pub fn refused(&self) {
        self.refused.inc();
    }

    /// A session took a place under the caps.
    pub fn admitted(&self) {
        self.open.inc();
    }

    /// A session gave its place back.
    pub fn released(&self) {
        self.open.dec();
    }

    /// A session was evicted at the global cap; `stage` is `"unproven"` or `"anonymous"`.
    pub fn evicted(&self, stage: &str) {
        if let Some(c) = self.evicted.get(usize::from(stage == "anonymous")) {
            c.inc();
        }
    }

    /// A new client was answered with a Retry.
    pub fn retried(&self) {
        self.retries.inc();
    }

    /// A datagram that is not one.
    pub fn ignored(&self) {
        self.junk.inc();
    }
}
