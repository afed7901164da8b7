//! How long the server waits for a peer and how many connections it holds: every bound that
//! keeps an anonymous client, an idle socket or a slow sender from taking the server down
//! (issue 13). The limits themselves are [`crate::config::NetLimits`] (`Config::net`).

use std::time::Duration;

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
