//! Counters of the network bounds (`limits`): connections held and refused, accept
//! failures, timeouts. Kept apart from the other counters (`Metrics::net`) and registered after
//! them for `/metrics`.

use crate::metrics::{GaugeU64, counter, gauge, labelled_counters};
use prometheus_client::metrics::counter::Counter;
use prometheus_client::registry::Registry;

/// Which bound closed a connection.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Timeout {
    /// No websocket `hello` within `hello_timeout`.
    Hello,
    /// No complete request head within `header_read_timeout` (also idle keep-alive).
    Header,
    /// A request body not read within `body_read_timeout`.
    Body,
    /// A websocket silent for `ws_idle_timeout`.
    Idle,
}

impl Timeout {
    const ALL: [Self; 4] = [Self::Hello, Self::Header, Self::Body, Self::Idle];

    fn label(self) -> &'static str {
        match self {
            Self::Hello => "hello",
            Self::Header => "header",
            Self::Body => "body",
            Self::Idle => "idle",
        }
    }
}

/// The network counters. Relaxed atomics: exact totals, no ordering.
#[derive(Debug)]
pub struct NetCounters {
    open: GaugeU64,
    accepted: Counter,
    refused_global: Counter,
    refused_per_address: Counter,
    unanswered: Counter,
    /// Unproven, anonymous.
    evicted: [Counter; 2],
    accept_errors: Counter,
    /// In the order of [`Timeout::ALL`].
    timeouts: [Counter; Timeout::ALL.len()],
}

impl NetCounters {
    /// All zero, registered in `registry`.
    pub(crate) fn new(registry: &mut Registry) -> Self {
        let r = registry;
        let open = gauge(
            r,
            "tcp_connections_open",
            "TCP connections held (HTTP and websocket)",
        );
        let accepted = counter(r, "tcp_connections_accepted", "TCP connections admitted");
        let [refused_global, refused_per_address] = labelled_counters(
            r,
            "connections_refused",
            "Connections refused for a full cap (503 or close 1013)",
            "cap",
            [Refusal::Global.label(), Refusal::PerAddress.label()],
        );
        let unanswered = counter(
            r,
            "connections_unanswered",
            "Refused connections closed without an answer (too many refusals at once)",
        );
        let evicted = labelled_counters(
            r,
            "connections_evicted",
            "Connections closed at the global cap to admit a newcomer (stage: no hello yet, or an idle anonymous websocket)",
            "stage",
            ["unproven", "anonymous"],
        );
        let accept_errors = counter(
            r,
            "accept_errors",
            "Failed accepts (e.g. out of descriptors)",
        );
        let timeouts = labelled_counters(
            r,
            "timeouts",
            "Connections closed (bodies refused) by a network timeout",
            "kind",
            Timeout::ALL.map(Timeout::label),
        );
        Self {
            open,
            accepted,
            refused_global,
            refused_per_address,
            unanswered,
            evicted,
            accept_errors,
            timeouts,
        }
    }

    /// A connection was admitted (it holds a slot until [`Self::released`]).
    pub fn admitted(&self) {
        self.open.inc();
        self.accepted.inc();
    }

    /// An admitted connection closed.
    pub fn released(&self) {
        self.open.dec();
    }

    /// A connection was evicted at the global cap; `stage` is `"unproven"` or `"anonymous"`.
    pub fn evicted(&self, stage: &str) {
        let i = usize::from(stage == "anonymous");
        if let Some(c) = self.evicted.get(i) {
            c.inc();
        }
    }

    /// Connections evicted so far at `stage` (`"unproven"` or `"anonymous"`).
    #[must_use]
    pub fn evicted_total(&self, stage: &str) -> u64 {
        self.evicted
            .get(usize::from(stage == "anonymous"))
            .map_or(0, Counter::get)
    }

    /// A connection was refused for a full cap.
    pub fn refused(&self, why: Refusal) {
        self.refusals(why).inc();
    }

    /// A refused connection was closed without an answer (too many refusals under way).
    pub fn unanswered(&self) {
        self.unanswered.inc();
    }

    /// `accept` failed (e.g. out of descriptors).
    pub fn accept_error(&self) {
        self.accept_errors.inc();
    }

    /// A bound closed a connection (or refused a body).
    pub fn timed_out(&self, which: Timeout) {
        let i = Timeout::ALL.iter().position(|&t| t == which);
        if let Some(counter) = i.and_then(|i| self.timeouts.get(i)) {
            counter.inc();
        }
    }

    /// Connections held now.
    #[must_use]
    pub fn open(&self) -> u64 {
        self.open.get()
    }

    /// Connections refused so far, for `why`.
    #[must_use]
    pub fn refused_total(&self, why: Refusal) -> u64 {
        self.refusals(why).get()
    }

    fn refusals(&self, why: Refusal) -> &Counter {
        match why {
            Refusal::Global => &self.refused_global,
            Refusal::PerAddress => &self.refused_per_address,
        }
    }
}

/// Why a connection was not admitted.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Refusal {
    /// The server holds its maximum number of connections.
    Global,
    /// This client address holds its maximum.
    PerAddress,
}

impl Refusal {
    /// The label used in `/metrics` and logs.
    #[must_use]
    pub fn label(self) -> &'static str {
        match self {
            Self::Global => "global",
            Self::PerAddress => "per_address",
        }
    }
}
