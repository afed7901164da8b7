//! How long the server waits for a peer and how many connections it holds: every bound that
//! keeps an anonymous client, an idle socket or a slow sender from taking the server down
//! (issue 13). One struct, [`NetLimits`], so the whole set travels as `Config::net`.

use std::time::Duration;

/// Network timeouts and connection caps (`Config::net`; flags in `posecast --help`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct NetLimits {
    /// A websocket must send its `hello` this soon after the upgrade, or it gets a `timeout`
    /// error and close 1008. A viewer says hello at once; a socket that says nothing is
    /// anonymous and must not hold a connection slot for long.
    pub hello_timeout: Duration,
    /// An HTTP request head (request line and headers) must arrive within this, counted from
    /// the connection's accept or from the previous response on a kept-alive connection; so
    /// this is also the keep-alive idle time. Silent TCP connections and half-sent headers
    /// (slowloris) are closed after it.
    pub header_read_timeout: Duration,
    /// A request body must be read completely within this, counted from its head (`408
    /// timeout`). Long enough for a [`crate::state::Config::max_upload_bytes`] upload over a
    /// slow link, short enough that a client trickling a byte a second cannot keep a
    /// request open for hours.
    pub body_read_timeout: Duration,
    /// How often the server pings a websocket that said hello.
    pub ws_ping_interval: Duration,
    /// A websocket from which nothing (not even a pong) arrived for this long is closed
    /// (1008 `idle timeout`). Should span a few ping intervals so one lost pong is not fatal.
    pub ws_idle_timeout: Duration,
    /// Open TCP connections (HTTP and websocket) the server holds at most; more are refused
    /// with 503 (websocket upgrades: close 1013). Lowered at start to what the descriptor
    /// limit allows ([`effective_max_connections`]).
    pub max_connections: usize,
    /// Open connections from one client address at most (IPv6: one /64, which one host
    /// usually holds whole); more are refused like over [`Self::max_connections`]. Keeps one
    /// client from taking every slot.
    pub max_connections_per_address: usize,
}

/// Default [`NetLimits::hello_timeout`]: 5 s.
pub const DEFAULT_HELLO_TIMEOUT: Duration = Duration::from_secs(5);
/// Default [`NetLimits::header_read_timeout`]: 10 s.
pub const DEFAULT_HEADER_READ_TIMEOUT: Duration = Duration::from_secs(10);
/// Default [`NetLimits::body_read_timeout`]: 120 s (32 MiB at ~280 KB/s).
pub const DEFAULT_BODY_READ_TIMEOUT: Duration = Duration::from_secs(120);
/// Default [`NetLimits::ws_ping_interval`]: 15 s.
pub const DEFAULT_WS_PING_INTERVAL: Duration = Duration::from_secs(15);
/// Default [`NetLimits::ws_idle_timeout`]: 45 s (three pings).
pub const DEFAULT_WS_IDLE_TIMEOUT: Duration = Duration::from_secs(45);
/// Default [`NetLimits::max_connections`]: 10,000.
pub const DEFAULT_MAX_CONNECTIONS: usize = 10_000;
/// Default [`NetLimits::max_connections_per_address`]: 256.
pub const DEFAULT_MAX_CONNECTIONS_PER_ADDRESS: usize = 256;

/// Descriptors kept free of connections: the listener, epoll, the data folder's files, asset
/// loading, log output, and the short-lived sockets that carry a 503 to refused clients
/// ([`REFUSING_MAX`]). Without them a server at its connection cap could not even refuse.
pub const RESERVED_DESCRIPTORS: usize = 128;

/// Refused connections being answered (503 or close 1013) at once, at most; beyond that a
/// refused connection is closed without an answer. Each takes a descriptor for at most
/// [`REFUSAL_TIMEOUT`].
pub const REFUSING_MAX: usize = 64;

/// How long a refused connection may take to send its request head before it is closed
/// unanswered: refusing must stay cheap whatever the peer does.
pub const REFUSAL_TIMEOUT: Duration = Duration::from_secs(2);

impl Default for NetLimits {
    fn default() -> Self {
        Self {
            hello_timeout: DEFAULT_HELLO_TIMEOUT,
            header_read_timeout: DEFAULT_HEADER_READ_TIMEOUT,
            body_read_timeout: DEFAULT_BODY_READ_TIMEOUT,
            ws_ping_interval: DEFAULT_WS_PING_INTERVAL,
            ws_idle_timeout: DEFAULT_WS_IDLE_TIMEOUT,
            max_connections: DEFAULT_MAX_CONNECTIONS,
            max_connections_per_address: DEFAULT_MAX_CONNECTIONS_PER_ADDRESS,
        }
    }
}

/// The connection cap that fits under a soft descriptor limit of `nofile`: `configured`, or
/// `nofile` less [`RESERVED_DESCRIPTORS`] when that is lower (at least 1). A cap above the
/// descriptor limit would make `accept` fail with EMFILE before any 503 could be sent.
#[must_use]
pub fn effective_max_connections(configured: usize, nofile: u64) -> usize {
    let fits = usize::try_from(nofile)
        .unwrap_or(usize::MAX)
        .saturating_sub(RESERVED_DESCRIPTORS)
        .max(1);
    configured.min(fits)
}

/// The soft and hard `RLIMIT_NOFILE` after raising the soft limit to the hard one, and the
/// soft limit before: `(before, soft, hard)`. The usual soft limit of 1,024 is a historical
/// default for `select()`; tokio uses epoll, so there is no reason to keep it.
///
/// # Errors
/// `getrlimit`/`setrlimit` failed.
pub fn raise_nofile_limit() -> std::io::Result<(u64, u64, u64)> {
    let (before, hard) = rlimit::Resource::NOFILE.get()?;
    if before < hard {
        rlimit::Resource::NOFILE.set(hard, hard)?;
    }
    let (soft, hard) = rlimit::Resource::NOFILE.get()?;
    Ok((before, soft, hard))
}

/// The current soft `RLIMIT_NOFILE` (`u64::MAX` when it cannot be read: no cap from it).
#[must_use]
pub fn nofile_soft_limit() -> u64 {
    rlimit::Resource::NOFILE
        .get()
        .map_or(u64::MAX, |(soft, _)| soft)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_cap_leaves_the_reserve_free_under_the_descriptor_limit() {
        assert_eq!(effective_max_connections(10_000, 1024), 1024 - 128);
        assert_eq!(effective_max_connections(500, 1024), 500);
        assert_eq!(effective_max_connections(10_000, 20), 1);
        assert_eq!(effective_max_connections(10_000, u64::MAX), 10_000);
    }
}
