//! Who gets a connection slot: a global cap and a cap per client address, counted from
//! `accept` until the socket closes (an upgraded websocket keeps its HTTP connection's slot).
//!
//! A [`Permit`] lives inside the connection's I/O object ([`Admitted`]), so the slot is given
//! back exactly when the descriptor is closed — whether hyper drops the connection, a
//! websocket session ends, or a shutdown drops everything — and no code path can forget it.

use crate::metrics::Metrics;
pub use crate::metrics::net::Refusal;
use std::collections::HashMap;
use std::net::{IpAddr, Ipv6Addr};
use std::pin::Pin;
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};

/// The connection counts (shared by the accept loop and every permit).
#[derive(Debug)]
pub struct Admission {
    max_total: usize,
    max_per_address: usize,
    counts: Mutex<Counts>,
    metrics: Arc<Metrics>,
}

#[derive(Debug, Default)]
struct Counts {
    total: usize,
    /// Only addresses with at least one open connection: at most `max_total` entries.
    per_address: HashMap<IpAddr, usize>,
}

/// The address a per-address cap counts: IPv4 as is (IPv4-mapped IPv6 too), IPv6 by its /64,
/// since one host or customer usually gets a whole /64 and could otherwise open each
/// connection from a new address.
#[must_use]
pub fn address_key(ip: IpAddr) -> IpAddr {
    match ip {
        IpAddr::V4(_) => ip,
        IpAddr::V6(v6) => match v6.to_ipv4_mapped() {
            Some(v4) => IpAddr::V4(v4),
            None => {
                let s = v6.segments();
                IpAddr::V6(Ipv6Addr::new(s[0], s[1], s[2], s[3], 0, 0, 0, 0))
            }
        },
    }
}

impl Admission {
    /// Caps of `max_total` connections and `max_per_address` per address (each at least 1);
    /// admissions, refusals and releases are counted in `metrics.net`.
    #[must_use]
    pub fn new(max_total: usize, max_per_address: usize, metrics: Arc<Metrics>) -> Arc<Self> {
        Arc::new(Self {
            max_total: max_total.max(1),
            max_per_address: max_per_address.max(1),
            counts: Mutex::new(Counts::default()),
            metrics,
        })
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Counts> {
        // Every update is a pair of counter changes made under the lock with no panics in
        // between, so a poisoned lock still holds consistent counts.
        self.counts
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// Takes a slot for a connection from `ip`, or says which cap is full.
    ///
    /// # Errors
    /// [`Refusal::Global`] or [`Refusal::PerAddress`].
    pub fn try_admit(self: &Arc<Self>, ip: IpAddr) -> Result<Permit, Refusal> {
        let key = address_key(ip);
        let mut counts = self.lock();
        let refused = if counts.total >= self.max_total {
            Some(Refusal::Global)
        } else if counts.per_address.get(&key).copied().unwrap_or(0) >= self.max_per_address {
            Some(Refusal::PerAddress)
        } else {
            None
        };
        if let Some(why) = refused {
            drop(counts);
            self.metrics.net.refused(why);
            return Err(why);
        }
        *counts.per_address.entry(key).or_insert(0) += 1;
        counts.total += 1;
        drop(counts);
        self.metrics.net.admitted();
        Ok(Permit {
            admission: self.clone(),
            key,
        })
    }

    /// Connections holding a slot.
    #[cfg(test)]
    fn open(&self) -> usize {
        self.lock().total
    }

    fn release(&self, key: IpAddr) {
        let mut counts = self.lock();
        counts.total = counts.total.saturating_sub(1);
        if let Some(n) = counts.per_address.get_mut(&key) {
            *n -= 1;
            if *n == 0 {
                counts.per_address.remove(&key);
            }
        }
        drop(counts);
        self.metrics.net.released();
    }
}

/// One connection's slot; given back on drop.
#[derive(Debug)]
pub struct Permit {
    admission: Arc<Admission>,
    key: IpAddr,
}

impl Drop for Permit {
    fn drop(&mut self) {
        self.admission.release(self.key);
    }
}

/// A connection's I/O holding a slot (`G`: a [`Permit`], or a refusal's slot) until the
/// stream is dropped, i.e. until its descriptor is closed.
#[derive(Debug)]
pub struct Admitted<S, G = Permit> {
    stream: S,
    _slot: G,
}

impl<S, G> Admitted<S, G> {
    /// `stream` holding `slot`.
    pub fn new(stream: S, slot: G) -> Self {
        Self {
            stream,
            _slot: slot,
        }
    }
}

impl<S: AsyncRead + Unpin, G: Unpin> AsyncRead for Admitted<S, G> {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.stream).poll_read(cx, buf)
    }
}

impl<S: AsyncWrite + Unpin, G: Unpin> AsyncWrite for Admitted<S, G> {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<std::io::Result<usize>> {
        Pin::new(&mut self.stream).poll_write(cx, buf)
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.stream).poll_flush(cx)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.stream).poll_shutdown(cx)
    }

    fn poll_write_vectored(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[std::io::IoSlice<'_>],
    ) -> Poll<std::io::Result<usize>> {
        Pin::new(&mut self.stream).poll_write_vectored(cx, bufs)
    }

    fn is_write_vectored(&self) -> bool {
        self.stream.is_write_vectored()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ip(s: &str) -> IpAddr {
        s.parse().unwrap()
    }

    #[test]
    fn caps_count_per_address_and_in_all_and_free_on_drop() {
        let a = Admission::new(5, 2, Arc::default());
        let p1 = a.try_admit(ip("10.0.0.1")).unwrap();
        let _p2 = a.try_admit(ip("10.0.0.1")).unwrap();
        assert_eq!(
            a.try_admit(ip("10.0.0.1")).unwrap_err(),
            Refusal::PerAddress
        );
        let _p3 = a.try_admit(ip("10.0.0.2")).unwrap();
        let _p4 = a.try_admit(ip("10.0.0.2")).unwrap();
        let _p5 = a.try_admit(ip("10.0.0.3")).unwrap();
        assert_eq!(a.open(), 5);
        assert_eq!(a.try_admit(ip("10.0.0.4")).unwrap_err(), Refusal::Global);
        drop(p1);
        assert_eq!(a.open(), 4);
        // The freed slot is 10.0.0.1's, and the global one is free again.
        let _again = a.try_admit(ip("10.0.0.1")).unwrap();
        assert_eq!(a.try_admit(ip("10.0.0.4")).unwrap_err(), Refusal::Global);
    }

    #[test]
    fn an_address_with_no_connection_left_is_forgotten() {
        let a = Admission::new(100, 100, Arc::default());
        let permits: Vec<_> = (0..50)
            .map(|i| a.try_admit(ip(&format!("10.0.1.{i}"))).unwrap())
            .collect();
        assert_eq!(a.lock().per_address.len(), 50);
        drop(permits);
        assert_eq!(a.lock().per_address.len(), 0);
        assert_eq!(a.open(), 0);
    }

    #[test]
    fn ipv6_counts_by_its_64_and_mapped_ipv4_as_ipv4() {
        let a = Admission::new(100, 1, Arc::default());
        let _p = a.try_admit(ip("2001:db8:1:2::1")).unwrap();
        assert_eq!(
            a.try_admit(ip("2001:db8:1:2:ffff::9")).unwrap_err(),
            Refusal::PerAddress
        );
        let _q = a.try_admit(ip("2001:db8:1:3::1")).unwrap();
        let _r = a.try_admit(ip("192.0.2.7")).unwrap();
        assert_eq!(
            a.try_admit(ip("::ffff:192.0.2.7")).unwrap_err(),
            Refusal::PerAddress
        );
    }
}
