//! Link emulation in the test process: a TCP proxy that impairs the connections through it the
//! way a real network path does to an application on top of TCP, and a UDP proxy ([`udp`])
//! that drops, delays and reorders datagrams for real (QUIC, WebTransport).
//!
//! ```text
//! client ──► Proxy (listens on 127.0.0.1:0) ──► upstream (the server)
//!            one Link, shared by every connection through the proxy:
//!            down (upstream → client) and up (client → upstream), each with
//!            a bounded FIFO queue drained at `rate` → one-way `delay` ± `jitter` → loss stalls
//! ```
//!
//! What each impairment does, per direction, to every segment (a read of at most [`SEGMENT`]
//! bytes, about one TCP segment):
//!
//! - **rate** (a bottleneck link shared by every connection of the [`Link`]): the segment waits
//!   in the link's queue (FIFO across connections, at most `queue` bytes), then takes
//!   `bytes × 8 / rate` to leave it. While the queue is full, readers wait for room and stop
//!   reading from their source socket, so back-pressure reaches the sender's socket (and, in
//!   posecast, its newest-frame-wins outbox) as it does behind a real bottleneck. Bytes counted
//!   are TCP payload (no header overhead).
//! - **delay** and **jitter**: the segment arrives `delay + U(−jitter, +jitter)` (never < 0)
//!   after it left the queue.
//! - **loss**: a TCP proxy cannot drop bytes, so a lost segment is emulated as what TCP makes
//!   of it for the application: the segment is retransmitted after an RTO-like
//!   `max(200 ms, 2 × RTT)` (RTT = 2 × delay) and arrives that much later.
//! - **in order**: TCP delivers bytes in order, so a segment never arrives before the one ahead
//!   of it on its connection (a late or lost segment holds everything behind it: head-of-line
//!   blocking).
//! - **reordering** (`reorder=3`): jitter wider than the gap between two segments of a
//!   connection reorders them on a real path; TCP then holds the early ones (the in-order rule
//!   above) and, when a segment is overtaken by `reorder` later ones, takes it for lost: a
//!   spurious retransmission, modelled as the sender sending nothing new for a round trip
//!   (see [`reorder`] for the model and its limits). Without `reorder`, only
//!   the in-order holds remain.
//! - **window**: at most `window` bytes of a connection are between the proxy's read and its
//!   write (TCP's in-flight bound); past it the proxy stops reading that connection.
//!
//! The proxy's socket to the upstream has a small receive buffer, so what it does not read
//! stays in the sender's socket instead of in loopback's megabyte buffers.

#![warn(missing_docs)]

pub mod udp;
pub use udp::{UdpProxy, UdpStats};

use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use std::fmt;
use std::net::SocketAddr;
use std::str::FromStr;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::tcp::{OwnedReadHalf, OwnedWriteHalf};
use tokio::net::{TcpListener, TcpSocket, TcpStream};
use tokio::sync::{OwnedSemaphorePermit, Semaphore, mpsc};
use tokio::task::JoinHandle;
use tokio::time::Instant;

/// Bytes the proxy reads at a time: about one TCP segment (1448 bytes of payload on Ethernet
/// with timestamps), so losses, queueing and fairness between connections act per segment.
pub const SEGMENT: usize = 1448;

/// The shortest emulated retransmission timeout (Linux's minimum RTO).
pub const MIN_RTO: Duration = Duration::from_millis(200);

/// Receive buffer of the proxy's socket to the upstream (the kernel doubles it): small, so
/// loopback adds little buffering of its own between the sender and the emulated link.
const UPSTREAM_RCVBUF: u32 = 4 << 10;

/// The impairments of a link (both directions alike).
#[derive(Debug, Clone, PartialEq)]
pub struct LinkConfig {
    /// One-way delay.
    pub delay: Duration,
    /// Each segment's delay varies uniformly by up to this much either way.
    pub jitter: Duration,
    /// Probability that a segment is lost (and retransmitted: see the module docs), 0–1.
    pub loss: f64,
    /// Reordering's cost: a segment overtaken by this many later segments of its connection
    /// makes the sender retransmit spuriously and stall for a round trip (3: TCP's
    /// duplicate-ACK threshold); `None`: reordered segments are only held in order.
    pub reorder: Option<u32>,
    /// Bottleneck rate in bits per second, shared by every connection; `None`: unlimited.
    pub rate_bps: Option<u64>,
    /// Bytes the bottleneck queue holds per direction.
    pub queue_bytes: usize,
    /// Bytes of one connection in flight through the proxy per direction: TCP's congestion
    /// window. The default, 16 KiB, is about the bandwidth-delay product of 2 Mbit/s × 64 ms;
    /// a real flow's window at a congested bottleneck shrinks to its share of the queue (the
    /// proxy does not drop, so it does not shrink): past it, bytes wait in the sender's socket.
    pub window_bytes: usize,
    /// Seed of the random delays and losses.
    pub seed: u64,
}

impl Default for LinkConfig {
    /// A perfect link: no delay, no loss, no rate limit; a 32 KiB queue (used with a rate),
    /// a 16 KiB window.
    fn default() -> Self {
        Self {
            delay: Duration::ZERO,
            jitter: Duration::ZERO,
            loss: 0.0,
            reorder: None,
            rate_bps: None,
            queue_bytes: 32 << 10,
            window_bytes: 16 << 10,
            seed: 1,
        }
    }
}

impl LinkConfig {
    /// The emulated retransmission stall of a lost segment: `max(200 ms, 2 × RTT)`.
    #[must_use]
    pub fn rto(&self) -> Duration {
        MIN_RTO.max(self.delay * 4)
    }

    /// Whether the link impairs nothing.
    #[must_use]
    pub fn is_perfect(&self) -> bool {
        self.delay.is_zero() && self.jitter.is_zero() && self.loss == 0.0 && self.rate_bps.is_none()
    }
}

/// A link description that did not parse.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ParseError(String);

impl fmt::Display for ParseError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for ParseError {}

impl FromStr for LinkConfig {
    type Err = ParseError;

    /// `delay=25ms,jitter=10ms,loss=1%,reorder=3,rate=2mbit,queue=32kb,window=64kb,seed=7`, any
    /// subset in
    /// any order (`none` or an empty string: a perfect link). Durations take `us`, `ms` or `s`;
    /// rates `bit`, `kbit`, `mbit`, `gbit` (per second, decimal); sizes `b`, `kb`, `mb`
    /// (binary); loss a percentage or a fraction.
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let mut config = Self::default();
        let s = s.trim();
        if s.is_empty() || s == "none" {
            return Ok(config);
        }
        for part in s.split(',') {
            let (key, value) = part
                .split_once('=')
                .ok_or_else(|| ParseError(format!("`{part}`: expected key=value")))?;
            let (key, value) = (key.trim(), value.trim().to_ascii_lowercase());
            match key {
                "delay" => config.delay = duration(&value)?,
                "jitter" => config.jitter = duration(&value)?,
                "loss" => config.loss = fraction(&value)?,
                "reorder" => {
                    let n: u32 = value.parse().map_err(|_| {
                        ParseError(format!("reorder `{value}`: a number of segments (≥ 1)"))
                    })?;
                    if n == 0 {
                        return Err(ParseError(format!(
                            "reorder `{value}`: a number of segments (≥ 1)"
                        )));
                    }
                    config.reorder = Some(n);
                }
                "rate" => config.rate_bps = Some(rate(&value)?),
                "queue" => config.queue_bytes = size(&value)?,
                "window" => config.window_bytes = size(&value)?,
                "seed" => {
                    config.seed = value
                        .parse()
                        .map_err(|_| ParseError(format!("seed `{value}`: not a number")))?;
                }
                _ => {
                    return Err(ParseError(format!(
                        "unknown link parameter `{key}` (delay, jitter, loss, reorder, rate, queue, window, seed)"
                    )));
                }
            }
        }
        if config.queue_bytes < SEGMENT || config.window_bytes < SEGMENT {
            return Err(ParseError(format!(
                "queue and window must hold at least one segment ({SEGMENT} bytes)"
            )));
        }
        Ok(config)
    }
}

impl fmt::Display for LinkConfig {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let mut parts = Vec::new();
        if !self.delay.is_zero() {
            parts.push(format!("delay={}ms", self.delay.as_secs_f64() * 1e3));
        }
        if !self.jitter.is_zero() {
            parts.push(format!("jitter={}ms", self.jitter.as_secs_f64() * 1e3));
        }
        if self.loss > 0.0 {
            parts.push(format!("loss={}%", self.loss * 100.0));
        }
        if let Some(n) = self.reorder {
            parts.push(format!("reorder={n}"));
        }
        if let Some(r) = self.rate_bps {
            parts.push(format!("rate={}kbit", r as f64 / 1e3));
        }
        if parts.is_empty() {
            f.write_str("none")
        } else {
            f.write_str(&parts.join(","))
        }
    }
}

fn number_with_unit<'a>(value: &'a str, what: &str) -> Result<(f64, &'a str), ParseError> {
    let split = value
        .find(|c: char| !(c.is_ascii_digit() || c == '.'))
        .unwrap_or(value.len());
    let (number, unit) = value.split_at(split);
    let number: f64 = number
        .parse()
        .map_err(|_| ParseError(format!("{what} `{value}`: not a number")))?;
    if !number.is_finite() || number < 0.0 {
        return Err(ParseError(format!("{what} `{value}`: must be ≥ 0")));
    }
    Ok((number, unit))
}

fn duration(value: &str) -> Result<Duration, ParseError> {
    let (n, unit) = number_with_unit(value, "duration")?;
    let seconds = match unit {
        "us" => n / 1e6,
        "ms" => n / 1e3,
        "s" => n,
        _ => {
            return Err(ParseError(format!(
                "duration `{value}`: unit must be us, ms or s"
            )));
        }
    };
    Ok(Duration::from_secs_f64(seconds))
}

fn fraction(value: &str) -> Result<f64, ParseError> {
    let (n, unit) = number_with_unit(value, "loss")?;
    let p = match unit {
        "%" => n / 100.0,
        "" => n,
        _ => return Err(ParseError(format!("loss `{value}`: a percentage or 0–1"))),
    };
    if p > 1.0 {
        return Err(ParseError(format!("loss `{value}`: at most 100 %")));
    }
    Ok(p)
}

fn rate(value: &str) -> Result<u64, ParseError> {
    let (n, unit) = number_with_unit(value, "rate")?;
    let scale = match unit {
        "bit" | "bps" => 1.0,
        "kbit" => 1e3,
        "mbit" => 1e6,
        "gbit" => 1e9,
        _ => {
            return Err(ParseError(format!(
                "rate `{value}`: unit must be bit, kbit, mbit or gbit"
            )));
        }
    };
    let bps = n * scale;
    if bps < 8.0 {
        return Err(ParseError(format!("rate `{value}`: at least 8 bit/s")));
    }
    Ok(bps as u64)
}

fn size(value: &str) -> Result<usize, ParseError> {
    let (n, unit) = number_with_unit(value, "size")?;
    let scale = match unit {
        "b" | "" => 1.0,
        "kb" | "kib" => 1024.0,
        "mb" | "mib" => 1024.0 * 1024.0,
        _ => {
            return Err(ParseError(format!(
                "size `{value}`: unit must be b, kb or mb"
            )));
        }
    };
    Ok((n * scale) as usize)
}

/// Totals of one direction of a link.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct DirectionStats {
    /// Bytes delivered.
    pub bytes: u64,
    /// Segments delivered.
    pub segments: u64,
    /// Segments lost (and delivered a retransmission stall late).
    pub lost: u64,
    /// Segments overtaken by `reorder` later ones: spurious retransmissions (each a stall).
    pub spurious: u64,
}

/// One direction of a link: its bottleneck queue and transmission clock, its dice, its totals.
#[derive(Debug)]
struct Direction {
    /// Room in the bottleneck queue, bytes (FIFO: tokio's semaphore serves waiters in order).
    queue: Arc<Semaphore>,
    /// When the bottleneck finishes sending what is queued.
    busy_until: Mutex<Instant>,
    rng: Mutex<StdRng>,
    bytes: AtomicU64,
    segments: AtomicU64,
    lost: AtomicU64,
    spurious: AtomicU64,
}

impl Direction {
    fn new(config: &LinkConfig, seed: u64) -> Self {
        Self {
            queue: Arc::new(Semaphore::new(config.queue_bytes)),
            busy_until: Mutex::new(Instant::now()),
            rng: Mutex::new(StdRng::seed_from_u64(seed)),
            bytes: AtomicU64::new(0),
            segments: AtomicU64::new(0),
            lost: AtomicU64::new(0),
            spurious: AtomicU64::new(0),
        }
    }

    fn stats(&self) -> DirectionStats {
        DirectionStats {
            bytes: self.bytes.load(Ordering::Relaxed),
            segments: self.segments.load(Ordering::Relaxed),
            lost: self.lost.load(Ordering::Relaxed),
            spurious: self.spurious.load(Ordering::Relaxed),
        }
    }
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    // Every update under these locks is a single assignment: a poisoned lock is still usable.
    m.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}

/// An impaired link, shared by every connection through the proxies that use it.
#[derive(Debug)]
pub struct Link {
    config: LinkConfig,
    /// Upstream → client.
    down: Direction,
    /// Client → upstream.
    up: Direction,
}

/// Which way bytes flow.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Way {
    /// From the upstream (the server) to the client.
    Down,
    /// From the client to the upstream.
    Up,
}

impl Link {
    /// A link with these impairments.
    #[must_use]
    pub fn new(config: LinkConfig) -> Arc<Self> {
        let down = Direction::new(&config, config.seed);
        let up = Direction::new(&config, config.seed ^ 0x9e37_79b9_7f4a_7c15);
        Arc::new(Self { config, down, up })
    }

    /// Its impairments.
    #[must_use]
    pub fn config(&self) -> &LinkConfig {
        &self.config
    }

    /// Totals of one direction.
    #[must_use]
    pub fn stats(&self, way: Way) -> DirectionStats {
        self.direction(way).stats()
    }

    fn direction(&self, way: Way) -> &Direction {
        match way {
            Way::Down => &self.down,
            Way::Up => &self.up,
        }
    }

    /// When a segment of `bytes` that may enter the bottleneck now leaves its queue, when it
    /// would arrive on its own (before the in-order hold of `reorder::Order`), and whether
    /// it was lost.
    fn schedule(&self, way: Way, bytes: usize) -> (Instant, Instant, bool) {
        let d = self.direction(way);
        let now = Instant::now();
        let departs = match self.config.rate_bps {
            Some(rate) => {
                let mut busy = lock(&d.busy_until);
                let start = (*busy).max(now);
                let serialise = Duration::from_secs_f64(bytes as f64 * 8.0 / rate as f64);
                *busy = start + serialise;
                *busy
            }
            None => now,
        };
        let (wobble, lost) = {
            let mut rng = lock(&d.rng);
            let j = self.config.jitter.as_secs_f64();
            let wobble = if j > 0.0 {
                rng.random_range(-j..=j)
            } else {
                0.0
            };
            let lost = self.config.loss > 0.0 && rng.random_bool(self.config.loss);
            (wobble, lost)
        };
        let one_way = (self.config.delay.as_secs_f64() + wobble).max(0.0);
        let mut arrives = departs + Duration::from_secs_f64(one_way);
        if lost {
            arrives += self.config.rto();
        }
        (departs, arrives, lost)
    }
}

/// A running proxy: connections to [`Proxy::addr`] are relayed to the upstream through its
/// [`Link`]. Dropping it stops accepting and ends every relayed connection.
#[derive(Debug)]
pub struct Proxy {
    addr: SocketAddr,
    link: Arc<Link>,
    accept: JoinHandle<()>,
}

impl Drop for Proxy {
    fn drop(&mut self) {
        self.accept.abort();
    }
}

impl Proxy {
    /// Listens on a free loopback port and relays to `upstream` through `link` (which other
    /// proxies may share: one bottleneck for all of them).
    ///
    /// # Errors
    /// When the listening socket cannot be bound.
    pub async fn start(upstream: SocketAddr, link: Arc<Link>) -> std::io::Result<Self> {
        let listener = TcpListener::bind("127.0.0.1:0").await?;
        let addr = listener.local_addr()?;
        let accept = {
            let link = link.clone();
            tokio::spawn(async move {
                let mut connections = tokio::task::JoinSet::new();
                loop {
                    let Ok((client, _)) = listener.accept().await else {
                        // Out of descriptors or the like: try again shortly.
                        tokio::time::sleep(Duration::from_millis(10)).await;
                        continue;
                    };
                    let link = link.clone();
                    connections.spawn(async move { relay(client, upstream, link).await });
                    // Reap finished connections so the set does not grow.
                    while connections.try_join_next().is_some() {}
                }
            })
        };
        Ok(Self { addr, link, accept })
    }

    /// Where clients connect.
    #[must_use]
    pub fn addr(&self) -> SocketAddr {
        self.addr
    }

    /// The link its connections share.
    #[must_use]
    pub fn link(&self) -> &Arc<Link> {
        &self.link
    }
}

async fn relay(client: TcpStream, upstream: SocketAddr, link: Arc<Link>) {
    let server = async {
        let socket = if upstream.is_ipv4() {
            TcpSocket::new_v4()?
        } else {
            TcpSocket::new_v6()?
        };
        // What the proxy does not read stays with the sender, not in loopback's buffers.
        socket.set_recv_buffer_size(UPSTREAM_RCVBUF)?;
        socket.connect(upstream).await
    };
    let Ok(server) = server.await else {
        return;
    };
    client.set_nodelay(true).ok();
    server.set_nodelay(true).ok();
    let (client_read, client_write) = client.into_split();
    let (server_read, server_write) = server.into_split();
    let down = pump(server_read, client_write, link.clone(), Way::Down);
    let up = pump(client_read, server_write, link, Way::Up);
    // Either direction ending ends the connection (a closed websocket closes both ways).
    tokio::select! {
        () = down => {}
        () = up => {}
    }
}

/// A segment on its way: when it may be written, and what holds its place meanwhile.
struct InFlight {
    arrives: Instant,
    data: Vec<u8>,
    _window: OwnedSemaphorePermit,
}

/// Relays one direction of a connection until either side closes.
async fn pump(mut from: OwnedReadHalf, mut to: OwnedWriteHalf, link: Arc<Link>, way: Way) {
    let window = Arc::new(Semaphore::new(link.config.window_bytes));
    let (tx, mut rx) = mpsc::unbounded_channel::<Option<InFlight>>();
    let reader = {
        let link = link.clone();
        async move {
            let mut order = reorder::Order::new(Instant::now());
            let mut buf = vec![0u8; SEGMENT];
            loop {
                let Ok(mut in_window) = window.clone().acquire_many_owned(SEGMENT as u32).await
                else {
                    break;
                };
                let n = match from.read(&mut buf).await {
                    Ok(0) | Err(_) => break,
                    Ok(n) => n,
                };
                // Hold only what was read: the rest of the reservation goes back.
                if n < SEGMENT {
                    drop(in_window.split(SEGMENT - n));
                }
                let direction = link.direction(way);
                // Room in the shared bottleneck queue (waits, and so stops reading, while it
                // is full); the room is given back when the segment leaves the queue.
                let queued = if link.config.rate_bps.is_some() {
                    let Ok(p) = direction.queue.clone().acquire_many_owned(n as u32).await else {
                        break;
                    };
                    Some(p)
                } else {
                    None
                };
                let (departs, raw, lost) = link.schedule(way, n);
                let placed = order.place(&link.config, departs, raw, lost);
                let arrives = placed.arrives;
                if placed.spurious {
                    direction.spurious.fetch_add(1, Ordering::Relaxed);
                }
                if let Some(p) = queued {
                    tokio::spawn(async move {
                        tokio::time::sleep_until(departs).await;
                        drop(p);
                    });
                }
                if lost {
                    direction.lost.fetch_add(1, Ordering::Relaxed);
                }
                let segment = InFlight {
                    arrives,
                    data: buf[..n].to_vec(),
                    _window: in_window,
                };
                if tx.send(Some(segment)).is_err() {
                    return;
                }
            }
            // The source closed: deliver what is in flight, then close the write side.
            tx.send(None).ok();
        }
    };
    let writer = async move {
        while let Some(Some(segment)) = rx.recv().await {
            tokio::time::sleep_until(segment.arrives).await;
            if to.write_all(&segment.data).await.is_err() {
                return;
            }
            let d = link.direction(way);
            d.bytes
                .fetch_add(segment.data.len() as u64, Ordering::Relaxed);
            d.segments.fetch_add(1, Ordering::Relaxed);
        }
        to.shutdown().await.ok();
    };
    let reader = tokio::spawn(reader);
    writer.await;
    reader.abort();
}

pub mod reorder;

#[cfg(test)]
mod tests;
