//! Counters of the network bounds (`limits`): connections held and refused, accept
//! failures, timeouts. Kept apart from the other counters (`Metrics::net`) and rendered after
//! them in `/metrics`.

use std::fmt::Write as _;
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};

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
#[derive(Debug, Default)]
pub struct NetCounters {
    open: AtomicU64,
    accepted: AtomicU64,
    refused_global: AtomicU64,
    refused_per_address: AtomicU64,
    unanswered: AtomicU64,
    accept_errors: AtomicU64,
    timeouts: [AtomicU64; Timeout::ALL.len()],
}

impl NetCounters {
    /// A connection was admitted (it holds a slot until [`Self::released`]).
    pub fn admitted(&self) {
        self.open.fetch_add(1, Relaxed);
        self.accepted.fetch_add(1, Relaxed);
    }

    /// An admitted connection closed.
    pub fn released(&self) {
        self.open.fetch_sub(1, Relaxed);
    }

    /// A connection was refused for a full cap.
    pub fn refused(&self, why: Refusal) {
        match why {
            Refusal::Global => &self.refused_global,
            Refusal::PerAddress => &self.refused_per_address,
        }
        .fetch_add(1, Relaxed);
    }

    /// A refused connection was closed without an answer (too many refusals under way).
    pub fn unanswered(&self) {
        self.unanswered.fetch_add(1, Relaxed);
    }

    /// `accept` failed (e.g. out of descriptors).
    pub fn accept_error(&self) {
        self.accept_errors.fetch_add(1, Relaxed);
    }

    /// A bound closed a connection (or refused a body).
    pub fn timed_out(&self, which: Timeout) {
        if let Some(i) = Timeout::ALL.iter().position(|&t| t == which) {
            self.timeouts[i].fetch_add(1, Relaxed);
        }
    }

    /// Connections held now.
    #[must_use]
    pub fn open(&self) -> u64 {
        self.open.load(Relaxed)
    }

    /// Connections refused so far, for `why`.
    #[must_use]
    pub fn refused_total(&self, why: Refusal) -> u64 {
        match why {
            Refusal::Global => &self.refused_global,
            Refusal::PerAddress => &self.refused_per_address,
        }
        .load(Relaxed)
    }

    /// Appends the Prometheus text of these counters.
    pub fn render(&self, out: &mut String) {
        let _ = writeln!(
            out,
            "# HELP posecast_tcp_connections_open TCP connections held (HTTP and websocket).\n\
             # TYPE posecast_tcp_connections_open gauge\n\
             posecast_tcp_connections_open {}\n\
             # HELP posecast_tcp_connections_accepted_total TCP connections admitted.\n\
             # TYPE posecast_tcp_connections_accepted_total counter\n\
             posecast_tcp_connections_accepted_total {}\n\
             # HELP posecast_connections_refused_total Connections refused for a full cap (503 or close 1013).\n\
             # TYPE posecast_connections_refused_total counter\n\
             posecast_connections_refused_total{{cap=\"global\"}} {}\n\
             posecast_connections_refused_total{{cap=\"per_address\"}} {}\n\
             # HELP posecast_connections_unanswered_total Refused connections closed without an answer (too many refusals at once).\n\
             # TYPE posecast_connections_unanswered_total counter\n\
             posecast_connections_unanswered_total {}\n\
             # HELP posecast_accept_errors_total Failed accepts (e.g. out of descriptors).\n\
             # TYPE posecast_accept_errors_total counter\n\
             posecast_accept_errors_total {}\n\
             # HELP posecast_timeouts_total Connections closed (bodies refused) by a network timeout.\n\
             # TYPE posecast_timeouts_total counter",
            self.open.load(Relaxed),
            self.accepted.load(Relaxed),
            self.refused_global.load(Relaxed),
            self.refused_per_address.load(Relaxed),
            self.unanswered.load(Relaxed),
            self.accept_errors.load(Relaxed),
        );
        for (t, n) in Timeout::ALL.iter().zip(&self.timeouts) {
            let _ = writeln!(
                out,
                "posecast_timeouts_total{{kind=\"{}\"}} {}",
                t.label(),
                n.load(Relaxed)
            );
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
