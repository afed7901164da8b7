//! When a websocket has to prove it is alive: its `hello` within `hello_timeout` of the
//! upgrade; after that, something (a message, a pong) within `ws_idle_timeout`, with a ping
//! from the server every `ws_ping_interval` so a live but quiet client (a viewer only reads)
//! always has something to answer. Browsers and websocket libraries answer pings on their own.

use crate::config::NetLimits;
use std::time::Duration;
use tokio::time::{Instant, sleep_until};

/// What is due on a connection.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Due {
    /// No hello in time: refuse the connection.
    HelloTimeout,
    /// Time to ping.
    Ping,
    /// Nothing heard for the idle timeout: close.
    Idle,
}

/// A connection's deadlines.
#[derive(Debug)]
pub(super) struct Liveness {
    hello_deadline: Instant,
    ping_interval: Duration,
    idle_timeout: Duration,
    last_heard: Instant,
    next_ping: Instant,
}

impl Liveness {
    /// Deadlines from now (the upgrade).
    pub(super) fn new(limits: &NetLimits) -> Self {
        let now = Instant::now();
        Self {
            hello_deadline: now + limits.hello_timeout,
            // A zero interval would ping in a busy loop.
            ping_interval: limits.ws_ping_interval.max(Duration::from_millis(10)),
            idle_timeout: limits.ws_idle_timeout,
            last_heard: now,
            next_ping: now + limits.ws_ping_interval,
        }
    }

    /// The client sent something (any message, pongs included).
    pub(super) fn heard(&mut self) {
        self.last_heard = Instant::now();
    }

    /// Waits until something is due; `greeted` says whether the hello came.
    pub(super) async fn due(&mut self, greeted: bool) -> Due {
        if !greeted {
            sleep_until(self.hello_deadline).await;
            return Due::HelloTimeout;
        }
        loop {
            let idle_at = self.last_heard + self.idle_timeout;
            sleep_until(idle_at.min(self.next_ping)).await;
            let now = Instant::now();
            if now >= idle_at {
                return Due::Idle;
            }
            if now >= self.next_ping {
                self.next_ping = now + self.ping_interval;
                return Due::Ping;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn limits(hello: u64, ping: u64, idle: u64) -> NetLimits {
        NetLimits {
            hello_timeout: Duration::from_secs(hello),
            ws_ping_interval: Duration::from_secs(ping),
            ws_idle_timeout: Duration::from_secs(idle),
            ..NetLimits::default()
        }
    }

    #[tokio::test(start_paused = true)]
    async fn hello_is_due_at_its_deadline_only_before_the_hello() {
        let start = Instant::now();
        let mut l = Liveness::new(&limits(5, 15, 45));
        assert_eq!(l.due(false).await, Due::HelloTimeout);
        assert_eq!(start.elapsed(), Duration::from_secs(5));
    }

    #[tokio::test(start_paused = true)]
    async fn pings_every_interval_and_idles_out_a_silent_client() {
        let start = Instant::now();
        let mut l = Liveness::new(&limits(5, 15, 45));
        for k in 1..=2 {
            assert_eq!(l.due(true).await, Due::Ping);
            assert_eq!(start.elapsed(), Duration::from_secs(15 * k));
        }
        // The third ping and the idle deadline coincide at 45 s: idle wins.
        assert_eq!(l.due(true).await, Due::Idle);
        assert_eq!(start.elapsed(), Duration::from_secs(45));
    }

    #[tokio::test(start_paused = true)]
    async fn anything_heard_pushes_the_idle_deadline_back() {
        let start = Instant::now();
        let mut l = Liveness::new(&limits(5, 15, 45));
        for _ in 0..10 {
            assert_eq!(l.due(true).await, Due::Ping);
            l.heard();
        }
        assert_eq!(start.elapsed(), Duration::from_secs(150));
        assert_eq!(l.due(true).await, Due::Ping);
        assert_eq!(l.due(true).await, Due::Ping);
        assert_eq!(l.due(true).await, Due::Idle);
        assert_eq!(start.elapsed(), Duration::from_secs(150 + 45));
    }
}
