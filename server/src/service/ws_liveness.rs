//! When a websocket has to prove it is alive: its `hello` within `hello_timeout` of the
//! upgrade; after that, something (a message, a pong) within `ws_idle_timeout`, with a ping
//! from the server every `ws_ping_interval` so a live but quiet client (a viewer only reads)
//! always has something to answer. Browsers and websocket libraries answer pings on their own.
//!
//! One timer per connection, armed for its earliest deadline and never re-armed for what is
//! heard: `heard` only notes the time, and when the timer fires the deadlines are worked out
//! again (a client heard meanwhile is not idle; the timer moves on). A connection's select
//! loop runs for every message and pong, and a fresh timer per turn was tens of thousands of
//! timer insertions and removals a second at 2,000 viewers (issue 38's profile: 19 % in tokio's
//! timers).

use crate::config::NetLimits;
use std::pin::Pin;
use std::time::Duration;
use tokio::time::{Instant, Sleep, sleep_until};

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

/// A connection's deadlines, and the one timer that watches them.
#[derive(Debug)]
pub(super) struct Liveness {
    ping_interval: Duration,
    idle_timeout: Duration,
    last_heard: Instant,
    next_ping: Instant,
    /// Armed for the deadline `armed_for` says (the hello's until greeted, then the earlier of
    /// the next ping and the idle deadline as of when it was armed).
    timer: Pin<Box<Sleep>>,
    /// Whether `timer` is armed for the greeted deadlines (it starts armed for the hello's).
    armed_greeted: bool,
}

impl Liveness {
    /// Deadlines from now (the upgrade).
    pub(super) fn new(limits: &NetLimits) -> Self {
        let now = Instant::now();
        Self {
            // A zero interval would ping in a busy loop.
            ping_interval: limits.ws_ping_interval.max(Duration::from_millis(10)),
            idle_timeout: limits.ws_idle_timeout,
            last_heard: now,
            next_ping: now + limits.ws_ping_interval,
            timer: Box::pin(sleep_until(now + limits.hello_timeout)),
            armed_greeted: false,
        }
    }

    /// Something came from the client: the idle deadline moves (no timer is touched).
    pub(super) fn heard(&mut self) {
        self.last_heard = Instant::now();
    }

    /// The earlier of the next ping and the idle deadline.
    fn greeted_deadline(&self) -> Instant {
        (self.last_heard + self.idle_timeout).min(self.next_ping)
    }

    /// Resolves when something is due: the hello's deadline while not `greeted`, then a ping
    /// every ping interval and the idle deadline. Cancel-safe: dropped unfinished (another
    /// branch of the select won), the timer stays armed for the next call.
    pub(super) async fn due(&mut self, greeted: bool) -> Due {
        if !greeted {
            self.timer.as_mut().await;
            return Due::HelloTimeout;
        }
        if !self.armed_greeted {
            self.armed_greeted = true;
            let at = self.greeted_deadline();
            self.timer.as_mut().reset(at);
        }
        loop {
            self.timer.as_mut().await;
            let now = Instant::now();
            if now >= self.last_heard + self.idle_timeout {
                return Due::Idle;
            }
            let ping = now >= self.next_ping;
            if ping {
                self.next_ping = now + self.ping_interval;
            }
            // Heard since it was armed, or pinged now: armed again for what is due next.
            let at = self.greeted_deadline();
            self.timer.as_mut().reset(at);
            if ping {
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
