//! The link emulator's UDP path: a proxy that impairs datagrams (QUIC, WebTransport) the way a
//! real path does. Unlike TCP, UDP lets a path really drop and reorder, and the transport on top
//! (QUIC) decides what to do about it.
//!
//! ```text
//! client ──► UdpProxy (127.0.0.1:0) ──► upstream (the server's UDP port)
//!            one socket to the upstream per client address (a NAT's mapping);
//!            per direction, shared by every client: loss → bottleneck queue at `rate`
//!            (tail drop when `queue` bytes wait) → one-way `delay` ± `jitter`
//! ```
//!
//! What each impairment of a [`LinkConfig`] does, per direction, to every datagram:
//! - **loss**: dropped with probability `loss`.
//! - **rate**: a bottleneck shared by every client. A datagram waits behind the bytes queued
//!   before it and takes `bytes × 8 / rate` to leave. When more than `queue` bytes wait, it is
//!   dropped (a router's tail drop). Bytes counted are UDP payload.
//! - **delay** and **jitter**: it arrives `delay + U(−jitter, +jitter)` (never < 0) after it
//!   left the queue, so jitter wider than the gap between two datagrams reorders them.
//!
//! `reorder` and `window` model TCP and do not apply here.

use crate::LinkConfig;
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use std::collections::HashMap;
use std::net::SocketAddr;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tokio::net::UdpSocket;
use tokio::task::JoinHandle;
use tokio::time::Instant;

/// Largest datagram the proxy carries (UDP's limit).
const MAX_DATAGRAM: usize = 65_535;

/// Totals of one direction of a UDP link.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct UdpStats {
    /// Datagrams delivered.
    pub delivered: u64,
    /// Bytes delivered.
    pub bytes: u64,
    /// Datagrams dropped by `loss`.
    pub lost: u64,
    /// Datagrams dropped at a full bottleneck queue.
    pub queue_drops: u64,
}

/// One direction: its dice, its bottleneck's clock, its totals.
#[derive(Debug)]
struct Direction {
    config: LinkConfig,
    rng: Mutex<StdRng>,
    /// When the bottleneck finishes sending what is queued.
    busy_until: Mutex<Instant>,
    delivered: AtomicU64,
    bytes: AtomicU64,
    lost: AtomicU64,
    queue_drops: AtomicU64,
}

impl Direction {
    fn new(config: &LinkConfig, seed: u64) -> Self {
        Self {
            config: config.clone(),
            rng: Mutex::new(StdRng::seed_from_u64(seed)),
            busy_until: Mutex::new(Instant::now()),
            delivered: AtomicU64::new(0),
            bytes: AtomicU64::new(0),
            lost: AtomicU64::new(0),
            queue_drops: AtomicU64::new(0),
        }
    }

    /// When a datagram of `len` bytes sent now arrives, or `None` when the link drops it.
    fn arrival(&self, len: usize, now: Instant) -> Option<Instant> {
        let c = &self.config;
        let (lost, jitter) = {
            let mut rng = self
                .rng
                .lock()
                .unwrap_or_else(std::sync::PoisonError::into_inner);
            let lost = c.loss > 0.0 && rng.random::<f64>() < c.loss;
            let jitter = if c.jitter.is_zero() {
                0.0
            } else {
                rng.random_range(-1.0..=1.0) * c.jitter.as_secs_f64()
            };
            (lost, jitter)
        };
        if lost {
            self.lost.fetch_add(1, Ordering::Relaxed);
            return None;
        }
        let left = match c.rate_bps {
            None => now,
            Some(bps) => {
                let mut busy = self
                    .busy_until
                    .lock()
                    .unwrap_or_else(std::sync::PoisonError::into_inner);
                let start = (*busy).max(now);
                let waiting = start.saturating_duration_since(now).as_secs_f64() * bps as f64 / 8.0;
                if waiting + len as f64 > c.queue_bytes as f64 {
                    self.queue_drops.fetch_add(1, Ordering::Relaxed);
                    return None;
                }
                *busy = start + Duration::from_secs_f64(len as f64 * 8.0 / bps as f64);
                *busy
            }
        };
        let delay = (c.delay.as_secs_f64() + jitter).max(0.0);
        Some(left + Duration::from_secs_f64(delay))
    }

    fn delivered(&self, len: usize) {
        self.delivered.fetch_add(1, Ordering::Relaxed);
        self.bytes.fetch_add(len as u64, Ordering::Relaxed);
    }

    fn stats(&self) -> UdpStats {
        UdpStats {
            delivered: self.delivered.load(Ordering::Relaxed),
            bytes: self.bytes.load(Ordering::Relaxed),
            lost: self.lost.load(Ordering::Relaxed),
            queue_drops: self.queue_drops.load(Ordering::Relaxed),
        }
    }
}

/// Sends `bytes` on `socket` (to `to`, or its connected peer) once `at` comes: the delay line.
fn deliver(
    direction: &Arc<Direction>,
    socket: &Arc<UdpSocket>,
    to: Option<SocketAddr>,
    bytes: Vec<u8>,
) {
    let Some(at) = direction.arrival(bytes.len(), Instant::now()) else {
        return;
    };
    let (direction, socket) = (direction.clone(), socket.clone());
    tokio::spawn(async move {
        tokio::time::sleep_until(at).await;
        let sent = match to {
            Some(to) => socket.send_to(&bytes, to).await,
            None => socket.send(&bytes).await,
        };
        if sent.is_ok() {
            direction.delivered(bytes.len());
        }
    });
}

/// A UDP proxy in front of `upstream` impairing both directions alike ([`LinkConfig`]); stops
/// on drop.
#[derive(Debug)]
pub struct UdpProxy {
    /// Where clients send (127.0.0.1, a free port).
    pub addr: SocketAddr,
    down: Arc<Direction>,
    up: Arc<Direction>,
    task: JoinHandle<()>,
    mappings: Arc<Mutex<HashMap<SocketAddr, JoinHandle<()>>>>,
}

impl Drop for UdpProxy {
    fn drop(&mut self) {
        self.task.abort();
        for (_, task) in self
            .mappings
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .drain()
        {
            task.abort();
        }
    }
}

impl UdpProxy {
    /// Listens on 127.0.0.1 and forwards to `upstream` through the link `config` describes.
    ///
    /// # Errors
    /// A socket cannot be bound.
    pub async fn start(upstream: SocketAddr, config: LinkConfig) -> std::io::Result<Self> {
        let listen = Arc::new(UdpSocket::bind("127.0.0.1:0").await?);
        let addr = listen.local_addr()?;
        let down = Arc::new(Direction::new(&config, config.seed));
        let up = Arc::new(Direction::new(&config, config.seed.wrapping_add(1)));
        let mappings: Arc<Mutex<HashMap<SocketAddr, JoinHandle<()>>>> = Arc::default();
        let (d, u, m) = (down.clone(), up.clone(), mappings.clone());
        let task = tokio::spawn(async move {
            let mut upstreams: HashMap<SocketAddr, Arc<UdpSocket>> = HashMap::new();
            let mut buf = vec![0u8; MAX_DATAGRAM];
            while let Ok((n, client)) = listen.recv_from(&mut buf).await {
                let socket = match upstreams.get(&client) {
                    Some(s) => s.clone(),
                    None => {
                        let Ok(socket) = map(upstream).await else {
                            continue;
                        };
                        let socket = Arc::new(socket);
                        upstreams.insert(client, socket.clone());
                        let back = tokio::spawn(backward(
                            socket.clone(),
                            listen.clone(),
                            client,
                            d.clone(),
                        ));
                        m.lock()
                            .unwrap_or_else(std::sync::PoisonError::into_inner)
                            .insert(client, back);
                        socket
                    }
                };
                deliver(&u, &socket, None, buf[..n].to_vec());
            }
        });
        Ok(Self {
            addr,
            down,
            up,
            task,
            mappings,
        })
    }

    /// Totals from the upstream to the clients.
    #[must_use]
    pub fn down(&self) -> UdpStats {
        self.down.stats()
    }

    /// Totals from the clients to the upstream.
    #[must_use]
    pub fn up(&self) -> UdpStats {
        self.up.stats()
    }
}

/// A socket of its own to the upstream for one client (a NAT's mapping).
async fn map(upstream: SocketAddr) -> std::io::Result<UdpSocket> {
    let socket = UdpSocket::bind("127.0.0.1:0").await?;
    socket.connect(upstream).await?;
    Ok(socket)
}

/// The upstream's datagrams to one client, through the link.
async fn backward(
    socket: Arc<UdpSocket>,
    listen: Arc<UdpSocket>,
    client: SocketAddr,
    down: Arc<Direction>,
) {
    let mut buf = vec![0u8; MAX_DATAGRAM];
    while let Ok(n) = socket.recv(&mut buf).await {
        deliver(&down, &listen, Some(client), buf[..n].to_vec());
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    /// An echo server: what the proxy's upstream sees comes back.
    async fn echo() -> SocketAddr {
        let socket = UdpSocket::bind("127.0.0.1:0").await.unwrap();
        let addr = socket.local_addr().unwrap();
        tokio::spawn(async move {
            let mut buf = vec![0u8; MAX_DATAGRAM];
            while let Ok((n, from)) = socket.recv_from(&mut buf).await {
                socket.send_to(&buf[..n], from).await.ok();
            }
        });
        addr
    }

    /// Round trips through a link of 20 ms each way take at least 40 ms; with 10 % loss each
    /// way about 19 % of 2,000 echoes do not come back (the link's own counts agree with what
    /// came back); distinct clients get distinct mappings.
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn datagrams_are_delayed_and_dropped_as_configured() {
        let upstream = echo().await;
        let config: LinkConfig = "delay=20ms,loss=10%,seed=3".parse().unwrap();
        let proxy = UdpProxy::start(upstream, config).await.unwrap();
        let client = UdpSocket::bind("127.0.0.1:0").await.unwrap();
        client.connect(proxy.addr).await.unwrap();
        let started = Instant::now();
        client.send(b"first").await.unwrap();
        let mut tries = 1u64;
        let mut buf = [0u8; 64];
        // The first may be lost: send until one comes back.
        let n = loop {
            match tokio::time::timeout(Duration::from_secs(2), client.recv(&mut buf)).await {
                Ok(n) => break n.unwrap(),
                Err(_) => {
                    client.send(b"first").await.unwrap();
                    tries += 1;
                }
            }
        };
        assert_eq!(&buf[..n], b"first");
        assert!(started.elapsed() >= Duration::from_millis(40));

        let sent = 2_000u32;
        // Read while sending (loopback's socket buffers hold a few hundred datagrams), until
        // nothing has come for well past the delay.
        let client = Arc::new(client);
        let reader = client.clone();
        let counting = tokio::spawn(async move {
            let mut buf = [0u8; 64];
            let mut back = 0u32;
            while let Ok(Ok(_)) =
                tokio::time::timeout(Duration::from_secs(2), reader.recv(&mut buf)).await
            {
                back += 1;
            }
            back
        });
        for i in 0..sent {
            client.send(&i.to_le_bytes()).await.unwrap();
            if i % 20 == 19 {
                tokio::time::sleep(Duration::from_millis(2)).await;
            }
        }
        let back = counting.await.unwrap();
        // Every datagram went through or was lost, each way; what came back is what the link
        // delivered down.
        let (up, down) = (proxy.up(), proxy.down());
        assert_eq!(up.delivered + up.lost, tries + u64::from(sent));
        assert_eq!(down.delivered + down.lost, up.delivered);
        assert_eq!(u64::from(back) + 1, down.delivered);
        assert_eq!(up.queue_drops + down.queue_drops, 0);
        // 1 − 0.9² = 19 %: with 2,000 tries, 5 standard deviations are ±4.4 %.
        let share = 1.0 - f64::from(back) / f64::from(sent);
        assert!((0.146..=0.234).contains(&share), "{share}");

        let other = UdpSocket::bind("127.0.0.1:0").await.unwrap();
        other.connect(proxy.addr).await.unwrap();
        assert_eq!(proxy.mappings.lock().unwrap().len(), 1);
        other.send(b"x").await.unwrap();
        let grown = tokio::time::timeout(Duration::from_secs(10), async {
            while proxy.mappings.lock().unwrap().len() < 2 {
                tokio::time::sleep(Duration::from_millis(5)).await;
            }
        })
        .await;
        assert!(grown.is_ok(), "a second client got no mapping of its own");
    }

    /// A 1 Mbit/s bottleneck with a 10 kB queue: a burst of 100 datagrams of 1,000 bytes is
    /// cut to what the queue holds (tail drop), and what passes leaves at the rate.
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn the_bottleneck_paces_and_tail_drops() {
        let upstream = UdpSocket::bind("127.0.0.1:0").await.unwrap();
        let config: LinkConfig = "rate=1mbit,queue=10kb".parse().unwrap();
        let proxy = UdpProxy::start(upstream.local_addr().unwrap(), config)
            .await
            .unwrap();
        let client = UdpSocket::bind("127.0.0.1:0").await.unwrap();
        client.connect(proxy.addr).await.unwrap();
        for _ in 0..100 {
            client.send(&[7u8; 1000]).await.unwrap();
        }
        let mut buf = vec![0u8; 2048];
        let mut got = 0;
        let mut first = None;
        let mut last = Instant::now();
        while let Ok(Ok(_)) =
            tokio::time::timeout(Duration::from_secs(1), upstream.recv(&mut buf)).await
        {
            got += 1;
            last = Instant::now();
            first.get_or_insert(last);
        }
        // 10 KiB of queue: ten datagrams wait, an eleventh is being sent. More pass when the
        // sends themselves take time (a busy machine: the queue drains meanwhile), never all.
        assert!((10..100).contains(&got), "{got} passed");
        // What did not pass was dropped at the queue, or (a proxy starved of CPU while the
        // burst arrived: 100 kB and the kernel's per-datagram overhead overflow a default
        // receive buffer) by the kernel before the proxy saw it: 83 at the queue and 7 never
        // read in one CI run. Never more than that, and the queue did drop.
        let up = proxy.up();
        assert_eq!(up.delivered, got);
        assert!(
            up.queue_drops > 0 && up.queue_drops <= 100 - got,
            "{} dropped at the queue, {got} passed",
            up.queue_drops
        );
        // Each takes 8 ms at 1 Mbit/s.
        let spread = last - first.unwrap();
        let want = Duration::from_millis(8 * (got - 1));
        assert!(
            spread + Duration::from_millis(4) >= want,
            "{spread:?} < {want:?}"
        );
    }
}
