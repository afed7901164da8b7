//! Who gets a connection slot: a global cap and a cap per client address, counted from
//! `accept` until the socket closes (an upgraded websocket keeps its HTTP connection's slot).
//!
//! A [`Permit`] lives inside the connection's I/O object ([`Admitted`]), so the slot is given
//! back exactly when the descriptor is closed — whether hyper drops the connection, a
//! websocket session ends, or a shutdown drops everything (after a lingering close when the
//! peer's input is unread, [`super::linger`]) — and no code path can forget it.

use crate::metrics::Metrics;
pub use crate::metrics::net::Refusal;
use futures_util::task::AtomicWaker;
use std::collections::HashMap;
use std::net::{IpAddr, Ipv6Addr};
use std::pin::Pin;
use std::sync::atomic::{AtomicBool, AtomicU8, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};
use std::time::{Duration, Instant};
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::TcpStream;

/// Connections heard from within this long are not idle: an anonymous websocket is evicted
/// only after this much silence. A subscribed viewer answers the adaptive rate's probes five
/// times a second; one that only holds the socket answers a ping every 15 s.
pub const IDLE_BEFORE_EVICTION: Duration = Duration::from_secs(2);

/// The share of the global cap kept for authenticated clients: anonymous websockets (after
/// their hello) may hold all slots but this twentieth (none under a cap of 20).
pub const AUTHENTICATED_HEADROOM_DIVISOR: usize = 20;

/// Which counters of [`Metrics`] an admission keeps.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Counted {
    /// TCP connections (HTTP and websockets): `metrics.net`.
    Tcp,
    /// WebTransport sessions (`super::quic`): `metrics.quic`.
    Quic,
}

/// The connection counts (shared by the accept loop and every permit).
#[derive(Debug)]
pub struct Admission {
    counted: Counted,
    max_total: usize,
    max_per_address: usize,
    /// Slots anonymous websockets may hold at most (`max_total` less the headroom).
    max_anonymous: usize,
    counts: Mutex<Counts>,
    metrics: Arc<Metrics>,
    epoch: Instant,
}

#[derive(Debug, Default)]
struct Counts {
    total: usize,
    /// Only addresses with at least one open connection: at most `max_total` entries.
    per_address: HashMap<IpAddr, usize>,
    /// Slots of websockets that said hello without a token.
    anonymous: usize,
    /// Every slot held, by admission order (the candidates for eviction).
    slots: HashMap<u64, Arc<Slot>>,
    next_id: u64,
}

/// What a connection has shown of itself, which decides whether it may be evicted.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(u8)]
pub enum Stage {
    /// No websocket hello yet: a socket that has said nothing, an HTTP connection, a websocket
    /// before its hello. Evicted first.
    Unproven = 0,
    /// A websocket that said hello without a token. Evicted when idle.
    Anonymous = 1,
    /// A websocket that said hello with a known token. Never evicted.
    Authenticated = 2,
}

impl Stage {
    fn from_u8(v: u8) -> Self {
        match v {
            0 => Self::Unproven,
            1 => Self::Anonymous,
            _ => Self::Authenticated,
        }
    }

    /// The label in `/metrics`.
    #[must_use]
    pub fn label(self) -> &'static str {
        match self {
            Self::Unproven => "unproven",
            Self::Anonymous => "anonymous",
            Self::Authenticated => "authenticated",
        }
    }
}

/// One held slot as eviction sees it; shared by the admission, the connection's I/O and its
/// websocket session.
#[derive(Debug)]
pub struct Slot {
    id: u64,
    key: IpAddr,
    epoch: Instant,
    stage: AtomicU8,
    /// When the peer last sent a byte, milliseconds after `epoch`.
    heard_ms: AtomicU64,
    /// Given back already (by eviction): the permit's drop must not count it again. Changed
    /// under the counts' lock only.
    released: AtomicBool,
    evicted: AtomicBool,
    /// The connection's reader, woken to fail once evicted.
    reader: AtomicWaker,
}

impl Slot {
    fn now_ms(&self) -> u64 {
        u64::try_from(self.epoch.elapsed().as_millis()).unwrap_or(u64::MAX)
    }

    fn heard(&self) {
        self.heard_ms.store(self.now_ms(), Ordering::Relaxed);
    }

    fn stage(&self) -> Stage {
        Stage::from_u8(self.stage.load(Ordering::Relaxed))
    }

    fn evicted(&self) -> bool {
        self.evicted.load(Ordering::Acquire)
    }
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
    /// admissions, refusals, evictions and releases are counted in `metrics.net`.
    #[must_use]
    pub fn new(max_total: usize, max_per_address: usize, metrics: Arc<Metrics>) -> Arc<Self> {
        Self::counted(Counted::Tcp, max_total, max_per_address, metrics)
    }

    /// [`Admission::new`] for WebTransport sessions: the same rules under caps of their own,
    /// counted in `metrics.quic`. A session holds its place from its request to its end;
    /// [`Greeter::heard`] marks it heard, and [`Greeter::evicted`] ends when it is evicted.
    #[must_use]
    pub fn for_quic(max_total: usize, max_per_address: usize, metrics: Arc<Metrics>) -> Arc<Self> {
        Self::counted(Counted::Quic, max_total, max_per_address, metrics)
    }

    fn counted(
        counted: Counted,
        max_total: usize,
        max_per_address: usize,
        metrics: Arc<Metrics>,
    ) -> Arc<Self> {
        let max_total = max_total.max(1);
        Arc::new(Self {
            counted,
            max_total,
            max_per_address: max_per_address.max(1),
            max_anonymous: max_total - max_total / AUTHENTICATED_HEADROOM_DIVISOR,
            counts: Mutex::new(Counts::default()),
            metrics,
            epoch: Instant::now(),
        })
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Counts> {
        // Every update is a set of counter changes made under the lock with no panics in
        // between, so a poisoned lock still holds consistent counts.
        self.counts
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// Takes a slot for a connection from `ip`, or says which cap is full. At the global cap
    /// the newcomer is not refused while a slot can be taken back: the connection that has not
    /// said hello and was heard from least recently is evicted (closed at once), else the
    /// anonymous websocket heard from least recently, if it has been idle for
    /// [`IDLE_BEFORE_EVICTION`]. Only a cap full of authenticated or busy connections refuses.
    ///
    /// # Errors
    /// [`Refusal::Global`] or [`Refusal::PerAddress`].
    pub fn try_admit(self: &Arc<Self>, ip: IpAddr) -> Result<Permit, Refusal> {
        let key = address_key(ip);
        let mut counts = self.lock();
        let mut evicted = None;
        let refused = if counts.per_address.get(&key).copied().unwrap_or(0) >= self.max_per_address
        {
            Some(Refusal::PerAddress)
        } else if counts.total >= self.max_total {
            match self.victim(&counts) {
                Some(victim) => {
                    evicted = Some(victim.stage());
                    Self::give_back(&mut counts, &victim);
                    victim.evicted.store(true, Ordering::Release);
                    victim.reader.wake();
                    None
                }
                None => Some(Refusal::Global),
            }
        } else {
            None
        };
        if let Some(why) = refused {
            drop(counts);
            self.count_refused(why);
            return Err(why);
        }
        let id = counts.next_id;
        counts.next_id += 1;
        let slot = Arc::new(Slot {
            id,
            key,
            epoch: self.epoch,
            stage: AtomicU8::new(Stage::Unproven as u8),
            heard_ms: AtomicU64::new(0),
            released: AtomicBool::new(false),
            evicted: AtomicBool::new(false),
            reader: AtomicWaker::new(),
        });
        slot.heard();
        counts.slots.insert(id, slot.clone());
        *counts.per_address.entry(key).or_insert(0) += 1;
        counts.total += 1;
        drop(counts);
        if let Some(stage) = evicted {
            // The evicted connection's slot went to the newcomer: one release, one admission.
            match self.counted {
                Counted::Tcp => self.metrics.net.evicted(stage.label()),
                Counted::Quic => self.metrics.quic.evicted(stage.label()),
            }
            self.count_released();
        }
        match self.counted {
            Counted::Tcp => self.metrics.net.admitted(),
            Counted::Quic => self.metrics.quic.admitted(),
        }
        Ok(Permit {
            admission: self.clone(),
            slot,
        })
    }

    /// The connection to evict for a newcomer: the unproven one heard from least recently,
    /// else the anonymous one idle longest (at least [`IDLE_BEFORE_EVICTION`]).
    fn victim(&self, counts: &Counts) -> Option<Arc<Slot>> {
        let now = u64::try_from(self.epoch.elapsed().as_millis()).unwrap_or(u64::MAX);
        let idle_ms = u64::try_from(IDLE_BEFORE_EVICTION.as_millis()).unwrap_or(u64::MAX);
        let mut unproven: Option<&Arc<Slot>> = None;
        let mut anonymous: Option<&Arc<Slot>> = None;
        let older = |best: Option<&Arc<Slot>>, s: &Arc<Slot>| {
            best.is_none_or(|b| {
                let (hs, hb) = (
                    s.heard_ms.load(Ordering::Relaxed),
                    b.heard_ms.load(Ordering::Relaxed),
                );
                hs < hb || (hs == hb && s.id < b.id)
            })
        };
        for s in counts.slots.values() {
            match s.stage() {
                Stage::Unproven => {
                    if older(unproven, s) {
                        unproven = Some(s);
                    }
                }
                Stage::Anonymous => {
                    if now.saturating_sub(s.heard_ms.load(Ordering::Relaxed)) >= idle_ms
                        && older(anonymous, s)
                    {
                        anonymous = Some(s);
                    }
                }
                Stage::Authenticated => {}
            }
        }
        unproven.or(anonymous).cloned()
    }

    /// Takes `slot` out of the counts (under the lock), once.
    fn give_back(counts: &mut Counts, slot: &Slot) {
        if slot.released.swap(true, Ordering::Relaxed) {
            return;
        }
        counts.slots.remove(&slot.id);
        counts.total = counts.total.saturating_sub(1);
        if slot.stage() == Stage::Anonymous {
            counts.anonymous = counts.anonymous.saturating_sub(1);
        }
        if let Some(n) = counts.per_address.get_mut(&slot.key) {
            *n -= 1;
            if *n == 0 {
                counts.per_address.remove(&slot.key);
            }
        }
    }

    /// Records a websocket's hello: `authenticated` (a known token) or anonymous. An anonymous
    /// hello is refused when anonymous websockets already hold all but the authenticated
    /// clients' headroom ([`AUTHENTICATED_HEADROOM_DIVISOR`]).
    ///
    /// # Errors
    /// [`Refusal::Global`]: no slot for one more anonymous websocket.
    pub fn greet(&self, slot: &Slot, authenticated: bool) -> Result<(), Refusal> {
        let mut counts = self.lock();
        if slot.released.load(Ordering::Relaxed) || slot.stage() != Stage::Unproven {
            return Ok(());
        }
        if authenticated {
            slot.stage
                .store(Stage::Authenticated as u8, Ordering::Relaxed);
            return Ok(());
        }
        if counts.anonymous >= self.max_anonymous {
            drop(counts);
            self.count_refused(Refusal::Global);
            return Err(Refusal::Global);
        }
        counts.anonymous += 1;
        slot.stage.store(Stage::Anonymous as u8, Ordering::Relaxed);
        Ok(())
    }

    /// Connections holding a slot.
    #[cfg(test)]
    fn open(&self) -> usize {
        self.lock().total
    }

    fn release(&self, slot: &Slot) {
        let mut counts = self.lock();
        if slot.released.load(Ordering::Relaxed) {
            // Evicted: its slot was handed on (and counted) then.
            return;
        }
        Self::give_back(&mut counts, slot);
        drop(counts);
        self.count_released();
    }

    fn count_refused(&self, why: Refusal) {
        match self.counted {
            Counted::Tcp => self.metrics.net.refused(why),
            Counted::Quic => self.metrics.quic.refused(),
        }
    }

    fn count_released(&self) {
        match self.counted {
            Counted::Tcp => self.metrics.net.released(),
            Counted::Quic => self.metrics.quic.released(),
        }
    }
}

/// One connection's slot; given back on drop.
#[derive(Debug)]
pub struct Permit {
    admission: Arc<Admission>,
    slot: Arc<Slot>,
}

impl Permit {
    /// The handle the connection's websocket session reports its hello through.
    #[must_use]
    pub fn greeter(&self) -> Greeter {
        Greeter {
            admission: self.admission.clone(),
            slot: self.slot.clone(),
        }
    }
}

impl Drop for Permit {
    fn drop(&mut self) {
        self.admission.release(&self.slot);
    }
}

/// Reports a websocket's hello to the admission ([`Admission::greet`]); an axum extension of
/// each admitted connection.
#[derive(Debug, Clone)]
pub struct Greeter {
    admission: Arc<Admission>,
    slot: Arc<Slot>,
}

impl Greeter {
    /// See [`Admission::greet`].
    ///
    /// # Errors
    /// No slot for one more anonymous websocket.
    pub fn greet(&self, authenticated: bool) -> Result<(), Refusal> {
        self.admission.greet(&self.slot, authenticated)
    }

    /// The peer sent something: it is not idle (a TCP connection's reads mark this
    /// themselves, [`Admitted`]; a WebTransport session's stream and datagrams call it).
    pub fn heard(&self) {
        self.slot.heard();
    }

    /// Ends once the connection is evicted to admit a newcomer (for a WebTransport session,
    /// which has no socket to fail: it closes its connection then). Only one task of a
    /// connection may wait on this: it shares the waker a TCP connection's reads use.
    pub async fn evicted(&self) {
        std::future::poll_fn(|cx| {
            self.slot.reader.register(cx.waker());
            if self.slot.evicted() {
                Poll::Ready(())
            } else {
                Poll::Pending
            }
        })
        .await;
    }
}

/// A connection's socket holding a slot (`G`: a [`Permit`], or a refusal's slot) until it is
/// closed — after a lingering close ([`super::linger`]) when the peer's input is unread.
#[derive(Debug)]
pub struct Admitted<G: Send + 'static = Permit> {
    /// `None` only while being dropped.
    stream: Option<TcpStream>,
    slot: Option<G>,
    /// The admitted slot's eviction state (`None` for a refusal's).
    tracked: Option<Arc<Slot>>,
}

impl<G: Send + 'static> Admitted<G> {
    /// `stream` holding `slot`, not subject to eviction (a refusal being answered).
    pub fn new(stream: TcpStream, slot: G) -> Self {
        Self {
            stream: Some(stream),
            slot: Some(slot),
            tracked: None,
        }
    }

    fn stream(&mut self) -> std::io::Result<Pin<&mut TcpStream>> {
        self.stream
            .as_mut()
            .map(Pin::new)
            .ok_or_else(|| std::io::ErrorKind::NotConnected.into())
    }
}

impl Admitted<Permit> {
    /// `stream` holding an admitted slot: every byte it receives marks it heard, and evicting
    /// it makes its reads and writes fail, which ends the connection wherever it is (request
    /// head, websocket session).
    pub fn with_permit(stream: TcpStream, permit: Permit) -> Self {
        let tracked = Some(permit.slot.clone());
        Self {
            stream: Some(stream),
            slot: Some(permit),
            tracked,
        }
    }
}

impl Admitted<Permit> {
    /// The socket, to be shared by a websocket's reader and the writes its outbox makes
    /// directly (`super::ws::direct`), and the admission it holds: its slot, eviction and
    /// lingering close, which [`Shared`] keeps.
    pub fn into_shared(mut self) -> Option<(Arc<TcpStream>, Shared)> {
        let stream = Arc::new(self.stream.take()?);
        let shared = Shared {
            stream: Some(stream.clone()),
            slot: self.slot.take(),
            tracked: self.tracked.take(),
        };
        Some((stream, shared))
    }
}

/// An admitted socket shared by several handles ([`Admitted::into_shared`]): when this one
/// goes, the socket closes as [`Admitted`]'s does (lingering when input is unread) if no other
/// handle still holds it.
#[derive(Debug)]
pub struct Shared {
    /// `None` only while being dropped.
    stream: Option<Arc<TcpStream>>,
    slot: Option<Permit>,
    tracked: Option<Arc<Slot>>,
}

impl Shared {
    /// Whether the connection was evicted (its reads and writes must fail).
    pub fn evicted(&self) -> bool {
        self.tracked.as_ref().is_some_and(|t| t.evicted())
    }

    /// The eviction state, for a writer holding the socket apart from this handle.
    pub fn eviction(&self) -> Option<Arc<Slot>> {
        self.tracked.clone()
    }

    /// Before a read: registers the reader to be woken by an eviction, and fails once evicted.
    ///
    /// # Errors
    /// The connection was evicted.
    pub fn before_read(&self, waker: &std::task::Waker) -> std::io::Result<()> {
        if let Some(t) = &self.tracked {
            t.reader.register(waker);
            if t.evicted() {
                return Err(evicted_error());
            }
        }
        Ok(())
    }

    /// Bytes were read: the connection was heard.
    pub fn heard(&self) {
        if let Some(t) = &self.tracked {
            t.heard();
        }
    }
}

impl Slot {
    /// Fails once the connection was evicted (for writes made apart from its reader).
    ///
    /// # Errors
    /// The connection was evicted.
    pub fn check(&self) -> std::io::Result<()> {
        if self.evicted() {
            return Err(evicted_error());
        }
        Ok(())
    }
}

impl Drop for Shared {
    fn drop(&mut self) {
        if self.evicted() {
            return;
        }
        if let (Some(stream), Some(slot)) = (self.stream.take(), self.slot.take())
            && let Ok(stream) = Arc::try_unwrap(stream)
        {
            super::linger::close(stream, slot);
        }
    }
}

fn evicted_error() -> std::io::Error {
    std::io::Error::new(
        std::io::ErrorKind::ConnectionAborted,
        "evicted: the server is at its connection cap",
    )
}

impl<G: Send + 'static> Drop for Admitted<G> {
    fn drop(&mut self) {
        if self.tracked.as_ref().is_some_and(|t| t.evicted()) {
            // An evicted connection is closed at once, whatever it left unread.
            return;
        }
        if let (Some(stream), Some(slot)) = (self.stream.take(), self.slot.take()) {
            super::linger::close(stream, slot);
        }
    }
}

impl<G: Send + Unpin + 'static> AsyncRead for Admitted<G> {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<std::io::Result<()>> {
        let tracked = self.tracked.clone();
        if let Some(t) = &tracked {
            // Registered before the check: an eviction in between still wakes this read.
            t.reader.register(cx.waker());
            if t.evicted() {
                return Poll::Ready(Err(evicted_error()));
            }
        }
        let before = buf.filled().len();
        let polled = match self.stream() {
            Ok(s) => s.poll_read(cx, buf),
            Err(e) => Poll::Ready(Err(e)),
        };
        if let (Poll::Ready(Ok(())), Some(t)) = (&polled, &tracked)
            && buf.filled().len() > before
        {
            t.heard();
        }
        polled
    }
}

impl<G: Send + Unpin + 'static> AsyncWrite for Admitted<G> {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<std::io::Result<usize>> {
        if self.tracked.as_ref().is_some_and(|t| t.evicted()) {
            return Poll::Ready(Err(evicted_error()));
        }
        match self.stream() {
            Ok(s) => s.poll_write(cx, buf),
            Err(e) => Poll::Ready(Err(e)),
        }
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        match self.stream() {
            Ok(s) => s.poll_flush(cx),
            Err(e) => Poll::Ready(Err(e)),
        }
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        match self.stream() {
            Ok(s) => s.poll_shutdown(cx),
            Err(e) => Poll::Ready(Err(e)),
        }
    }

    fn poll_write_vectored(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[std::io::IoSlice<'_>],
    ) -> Poll<std::io::Result<usize>> {
        match self.stream() {
            Ok(s) => s.poll_write_vectored(cx, bufs),
            Err(e) => Poll::Ready(Err(e)),
        }
    }

    fn is_write_vectored(&self) -> bool {
        self.stream
            .as_ref()
            .is_some_and(TcpStream::is_write_vectored)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ip(s: &str) -> IpAddr {
        s.parse().unwrap()
    }

    /// A permit whose websocket said hello with a token: never evicted.
    fn authenticated(a: &Arc<Admission>, from: &str) -> Permit {
        let p = a.try_admit(ip(from)).unwrap();
        p.greeter().greet(true).unwrap();
        p
    }

    #[test]
    fn caps_count_per_address_and_in_all_and_free_on_drop() {
        let a = Admission::new(5, 2, Arc::default());
        let p1 = authenticated(&a, "10.0.0.1");
        let _p2 = authenticated(&a, "10.0.0.1");
        assert_eq!(
            a.try_admit(ip("10.0.0.1")).unwrap_err(),
            Refusal::PerAddress
        );
        let _p3 = authenticated(&a, "10.0.0.2");
        let _p4 = authenticated(&a, "10.0.0.2");
        let _p5 = authenticated(&a, "10.0.0.3");
        assert_eq!(a.open(), 5);
        assert_eq!(a.try_admit(ip("10.0.0.4")).unwrap_err(), Refusal::Global);
        drop(p1);
        assert_eq!(a.open(), 4);
        // The freed slot is 10.0.0.1's, and the global one is free again.
        let _again = authenticated(&a, "10.0.0.1");
        assert_eq!(a.try_admit(ip("10.0.0.4")).unwrap_err(), Refusal::Global);
    }

    #[test]
    fn at_the_cap_the_unproven_heard_least_recently_is_evicted_then_idle_anonymous_ones() {
        let metrics = Arc::new(Metrics::default());
        let mut a = Admission::new(4, 4, metrics.clone());
        // Started a while ago, so a slot can have been silent for longer than the idle bound.
        let admission = Arc::get_mut(&mut a).unwrap();
        admission.epoch = admission
            .epoch
            .checked_sub(Duration::from_secs(60))
            .unwrap();
        let auth = authenticated(&a, "10.0.0.1");
        let anon = a.try_admit(ip("10.0.0.2")).unwrap();
        anon.greeter().greet(false).unwrap();
        let old = a.try_admit(ip("10.0.0.3")).unwrap();
        let young = a.try_admit(ip("10.0.0.4")).unwrap();
        // `young` was heard before `old`: silence, not age, decides.
        old.slot.heard_ms.store(5_000, Ordering::Relaxed);
        young.slot.heard_ms.store(1_000, Ordering::Relaxed);
        assert_eq!(a.open(), 4);
        let new1 = a.try_admit(ip("10.0.0.5")).unwrap();
        assert!(young.slot.evicted() && !old.slot.evicted());
        assert_eq!(a.open(), 4);
        // Its permit's drop does not give the slot back twice.
        drop(young);
        assert_eq!(a.open(), 4);
        assert_eq!(a.lock().per_address.get(&ip("10.0.0.4")), None);
        // Next the other unproven ones, oldest heard first (ties: admitted first).
        let new2 = a.try_admit(ip("10.0.0.6")).unwrap();
        assert!(old.slot.evicted());
        let new3 = a.try_admit(ip("10.0.0.7")).unwrap();
        assert!(new1.slot.evicted() && !new2.slot.evicted());
        // Only a heard-from anonymous websocket and authenticated ones would be left: make every
        // unproven one authenticated, and the anonymous one is spared until idle.
        new2.greeter().greet(true).unwrap();
        new3.greeter().greet(true).unwrap();
        assert_eq!(a.try_admit(ip("10.0.0.8")).unwrap_err(), Refusal::Global);
        let idle = u64::try_from(IDLE_BEFORE_EVICTION.as_millis()).unwrap();
        let now = anon.slot.now_ms();
        anon.slot
            .heard_ms
            .store(now.saturating_sub(idle + 1), Ordering::Relaxed);
        let _new4 = a.try_admit(ip("10.0.0.8")).unwrap();
        assert!(anon.slot.evicted());
        assert_eq!(a.lock().anonymous, 0);
        assert_eq!(metrics.net.evicted_total("anonymous"), 1);
        assert!(!auth.slot.evicted());
        assert_eq!(metrics.net.evicted_total("unproven"), 3);
        assert_eq!(metrics.net.open(), 4);
    }

    #[test]
    fn anonymous_websockets_leave_the_headroom_to_authenticated_ones() {
        let a = Admission::new(40, 40, Arc::default());
        let max_anonymous = 40 - 40 / AUTHENTICATED_HEADROOM_DIVISOR;
        let anonymous: Vec<Permit> = (0..max_anonymous)
            .map(|_| {
                let p = a.try_admit(ip("10.0.0.1")).unwrap();
                p.greeter().greet(false).unwrap();
                p
            })
            .collect();
        let late = a.try_admit(ip("10.0.0.2")).unwrap();
        assert_eq!(late.greeter().greet(false).unwrap_err(), Refusal::Global);
        late.greeter().greet(true).unwrap();
        drop(anonymous);
        assert_eq!(a.lock().anonymous, 0);
        assert_eq!(a.open(), 1);
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
