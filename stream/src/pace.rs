//! A connection's adaptive frame rate: lowered until the link keeps up, raised again when it
//! recovers.
//!
//! **Why.** Behind a thin link the bytes a connection cannot deliver queue in the network (a
//! bottleneck's buffer, the kernel's socket), where the newest-frame-wins outbox cannot replace
//! them: frames arrive seconds late. So each connection sends only `rate` of every 60 ticks
//! ([`STEPS`]: 60, 45, 30, 24, 20, 15, 12, 10, 8, 6, 5, 4, 3, 2, 1 — frames per second at
//! 60 ticks/s), evenly spread, when that is lower than its subscription's rate.
//!
//! **Signals**, sampled by a small websocket ping every [`PROBE_INTERVAL`] while the
//! connection is subscribed (the payload is the server's time, so the pong gives the round
//! trip; a ping queues behind the frames already on their way, so it measures the queue):
//! - *queueing delay*: the smallest of the last [`CURRENT_OF`] round trips (the *floor*)
//!   above the smallest of the last [`BASE_WINDOW`] (the path's own), less the connection's
//!   *jitter allowance*. A lost segment stalls the samples of a retransmission timeout (at 5 %
//!   loss of 60 segments a second, most of the time is inside one); the smallest recent one
//!   ignores that, a standing queue raises even the smallest.
//! - *jitter is not queueing*: on a jittery path (a radio link; a path that reorders packets,
//!   which TCP turns into head-of-line holds and spurious retransmissions) round trips spread
//!   without the floor rising for good: the smallest of four lands anywhere in the spread,
//!   while the base is the smallest of hundreds. So the queueing delay is counted above twice
//!   the connection's jitter `J` (RFC 3550 §6.4.1's estimator over consecutive round trips,
//!   `J += (|Dᵢ| − J) / 16`, `Dᵢ = rttᵢ − rttᵢ₋₁`), at most [`QUEUE_TARGET`] above — unless
//!   the path floor (below) stands more than [`QUEUE_TARGET`] above the base: spread on a
//!   rising floor is a shared queue's (a thin link's queue moves as its senders do), and is
//!   counted from the base.
//! - *an unanswered ping* older than the base round trip plus [`UNANSWERED_LATE`] counts as a
//!   sample of its age (a queue so long no answer comes back yet); the first ping goes right
//!   after the welcome, before a subscription's descriptions, so the base is known early;
//! - *frames superseded in the outbox while the socket held the writer* (its buffer full: the
//!   link or the reader does not keep up). Frames superseded because the writer itself ran
//!   late (not scheduled in time on a busy host) are not the link's doing and do not count
//!   ([`crate::outbox::Outbox::dropped_while_held`]).
//!
//! **Probing where it informs a decision.** A connection at full rate whose last
//! [`SETTLED_AFTER`] round trips were calm and whose socket shows no standing queue is
//! *settled*: its pings would only confirm that, so it pings once every [`SETTLED_PING_EVERY`]
//! probes (the socket's figures are still read every probe, and frames superseded still count).
//! The first round trip that is not calm, a late ping, a standing queue in the socket or a cut
//! ends the spell, and it probes every [`PROBE_INTERVAL`] again. Without the socket's figures a
//! connection never settles. (At 2,000 viewers on one host the pings were 10,000 writes, reads
//! and wake-ups a second, a tenth of the server's messages.)
//!
//! **What the reader can read** (issue 28). A reader starved of CPU (a client on a loaded
//! machine) answers pings when it runs: hundreds of milliseconds late with no queue anywhere —
//! it reads all that came each time. Round trips alone take that for a queue and cut it to the
//! last step. So on Linux every probe also reads the socket's kernel figures
//! ([`SocketFigures`], `TCP_INFO`), which a reader's lateness cannot fake (its kernel
//! acknowledges at once), and they change how the signals are read ([`Pace::socket`]):
//! - the queues that *stand* are the kernel's to show: unsent bytes that stood through the
//!   last [`SOCKET_WINDOW`] (the reader's receive window closed: it does not keep up; or the
//!   congestion window is full), in seconds at the pace it acknowledged, or the kernel's own
//!   round trip above its smallest (a queue in the network). Either above [`QUEUE_TARGET`]
//!   cuts as queueing does;
//! - round trips then show the queues that *grow* past the socket (a reader's receive buffer
//!   filling, a proxy's queue): they are judged against the smallest of the last
//!   [`TREND_WINDOW`] instead of [`BASE_WINDOW`], the jitter allowance may reach [`FAR_BEHIND`]
//!   (a late reader answers anywhere in its spread) and an unanswered ping counts past it.
//!
//! Without the figures (not Linux, or the kernel refuses) round trips decide as below.
//!
//! **Control** (AIMD on discrete steps, with hysteresis): queueing above [`QUEUE_TARGET`] or
//! superseded frames cut the rate to the step at or below ¾ of it (½ past a quarter of
//! [`FAR_BEHIND`], ¼ past it), at most once per [`HOLD`] so the queue can drain; a rate held
//! without either signal for a probing wait goes up one step. The wait is 1 s per frame/s the
//! step adds (at most 4 s), with ±25 % jitter so connections sharing a link do not move in
//! lock-step. (The wait does not grow after a raise that failed: the connections that had
//! been unlucky would then fall behind the others for good.) The hysteresis is in the
//! thresholds: lowered above [`QUEUE_TARGET`], raised only after a whole wait below half of it.
//!
//! **A blind cut** is one for a silence judged against [`UNKNOWN_BASE`], before any round
//! trip was measured (a joiner whose first frames were lost, or that joined a full queue). It
//! drains what queue there is; then the calm round trips raise the rate a step each (as TCP's
//! slow start after a timeout), until a cut judged against a measured base. (Raised a step per
//! seconds, a joiner at 5 % loss whose first keyframes were lost spent its session at 20–30
//! frames a second.)
//!
//! **Fairness.** Connections sharing a bottleneck see the same queueing delay. A connection
//! that joined while the link was already queued never saw its empty round trip, would take
//! the queue for its base and crowd out the others: connections from one address share their
//! base ([`Paths`]; one address is most often one access link) and the path's cuts. A path cut
//! needs the path's own evidence: the *path floor*, the smallest round trip any of its
//! connections saw in the last [`FLOOR_WINDOW`] (after its last cut), more than
//! [`QUEUE_TARGET`] above the base — a queue the path shares delays every packet on it, even
//! the luckiest; one connection's stall or a jittery sample delays only its own. Then every
//! connection of the path moves to one equal share, at most every [`PATH_HOLD`]: the cut's
//! factor times the mean rate of the path's connections (the path keeps their sum). The path's
//! total falls by the factor as before, but the faster give up more and the slower may gain,
//! so the additive raises between cuts start from equal rates. (Cutting each connection by
//! the factor of its own rate, as before, kept the gaps the raises' jitter had opened: the
//! slowest tenth of 50 viewers on one 2 Mbit/s link got 0.42–0.61 of the fastest tenth's
//! frame rate; with equal shares 0.76–0.82, `tests/link_rate.rs`.) (Until
//! issue 37 any two connections cutting within a second made the whole path cut: with 50
//! connections and jittery round trips, some two always did, and all 50 fell to 3–4 frames/s
//! where each alone kept 59.) Every connection keeps at least the lowest step (1 Hz) — no
//! connection starves while others stream — and, staggered by connection, paced subscribers
//! do not all send on the same tick.
//!
//! Datagram sessions (QUIC paces them) share only their base with the other datagram sessions
//! of their address ([`Pace::share_base`]): fifty of them joining a 2 Mbit/s link at once
//! filled its queue with handshakes and keyframes before the first acknowledgement, each took
//! the queue for its base, and it stood (3 runs of 7).

use std::collections::{HashMap, VecDeque};
use std::net::IpAddr;
use std::sync::atomic::{AtomicU32, Ordering};
use std::sync::{Arc, Mutex, Weak};
use std::time::Duration;
use tokio::time::Instant;

/// The rates a connection steps through: frames per 60 ticks (per second at 60 ticks/s).
/// Neighbours differ by at most half, so a probe upwards overloads a link by at most that much.
pub const STEPS: [u32; 15] = [60, 45, 30, 24, 20, 15, 12, 10, 8, 6, 5, 4, 3, 2, 1];

/// Whether a connection at `rate` frames per 60 ticks sends tick `seq`; `phase` staggers
/// connections (so they do not all send on one tick). `rate` of every 60 consecutive ticks
/// are sent, evenly spread.
#[must_use]
pub fn sends(rate: u32, seq: u64, phase: u64) -> bool {
    let j = seq.wrapping_add(phase) % 60;
    let rate = u64::from(rate.min(60));
    (j + 1) * rate / 60 != j * rate / 60
}

/// How often a subscribed connection's round trip is sampled.
pub const PROBE_INTERVAL: Duration = Duration::from_millis(200);

/// A *settled* connection ([`Pace::probe`]) pings on every this many probes instead of every one:
/// once a second, while the socket's figures are still read every probe.
pub const SETTLED_PING_EVERY: u32 = 5;

/// Consecutive calm round trips (none more than [`QUEUE_TARGET`] above the base and the jitter
/// allowance: none that would show a queue on its own) before a connection at full rate counts as settled: 2 s of
/// them at the full probing pace, so a link that queues from the start is never settled.
pub const SETTLED_AFTER: u32 = 10;

/// Time after a lowering before a connection may settle again.
pub const SETTLED_NOT_BEFORE: Duration = Duration::from_secs(10);

/// Queueing delay past which the rate goes down.
pub const QUEUE_TARGET: Duration = Duration::from_millis(40);

/// Queueing delay past which it goes down two steps.
pub const FAR_BEHIND: Duration = Duration::from_millis(400);

/// Least time between two lowerings (the queue drains meanwhile).
pub const HOLD: Duration = Duration::from_millis(500);

/// Least time between two cuts shared by a path.
pub const PATH_HOLD: Duration = Duration::from_secs(2);

/// How far back the path floor looks: two probes of each connection (a path of one or two
/// connections has too few samples for a floor: its own round trips judge it). Short, so the
/// floor follows a thin link's queue as it moves; on a path of many connections it is still
/// the smallest of dozens of round trips.
pub const FLOOR_WINDOW: Duration = Duration::from_millis(400);

/// The path floor's buckets (one minimum each), so a busy path costs a fixed memory.
const FLOOR_BUCKET: Duration = Duration::from_millis(50);

/// Round trips the current one is the smallest of (0.8 s of samples).
pub const CURRENT_OF: usize = 4;

/// How long the smallest round trip is remembered (the path's own round trip).
pub const BASE_WINDOW: Duration = Duration::from_secs(10);

/// How far past the base round trip an unanswered ping counts as late: more than a
/// retransmission stall (a lost segment holds a ping back 200 ms or more without any queue).
pub const UNANSWERED_LATE: Duration = Duration::from_millis(300);

/// The round trip assumed before the first answer.
pub const UNKNOWN_BASE: Duration = Duration::from_millis(200);

/// The wait before raising by one frame per second.
const PROBE_WAIT: Duration = Duration::from_secs(1);

/// With the socket's kernel figures ([`SocketFigures`]) round trips are judged against the
/// smallest of the last this long (the connection's own), not of [`BASE_WINDOW`]: a queue
/// *growing* past the socket (in a bottleneck's buffer, in the reader's receive buffer) raises
/// them within it, while a reader late by its own scheduling answers about as late throughout.
/// Queues that *stand* are the kernel's to show: unsent bytes, its own round trip.
pub const TREND_WINDOW: Duration = Duration::from_secs(3);

/// How far back the socket's figures are judged: a backlog that stood through all of it is
/// standing, and what the reader acknowledged over it is its pace.
pub const SOCKET_WINDOW: Duration = Duration::from_secs(1);

/// Socket readings a judgement needs (one per probe: 0.8 s of them).
const SOCKET_SAMPLES: usize = 4;

/// The kernel's figures of a connection's socket (Linux: `getsockopt(TCP_INFO)` on the
/// accepted socket), read every probe beside the ping ([`Pace::socket`]). They show the queues
/// that stand, which a reader's lateness cannot fake: a reader starved of CPU answers pings
/// late without any queue, but its kernel still acknowledges at once.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct SocketFigures {
    /// Bytes the peer acknowledged since the connection opened (`tcpi_bytes_acked`).
    pub acked: u64,
    /// Bytes written to the socket and not sent yet (`tcpi_notsent_bytes`): they stand when
    /// the reader's receive window is closed (it does not keep up) or the congestion window
    /// is full (the path does not).
    pub unsent: u64,
    /// The kernel's smoothed round trip (`tcpi_rtt`): the network's queues, not the reader's.
    pub rtt: Duration,
    /// The smallest round trip the kernel saw (`tcpi_min_rtt`).
    pub min_rtt: Duration,
}

/// Frames per second at step `level` when the scene ticks at 60 Hz (the steps' unit).
fn hz(level: usize) -> f64 {
    f64::from(STEPS[level.min(STEPS.len() - 1)])
}

/// The multiplicative decrease for a queue of `queueing`: the further behind, the bigger the
/// cut (of a connection's own rate; a path's shared cut gives each of its connections this
/// factor of their mean rate, [`Path::judge`]).
fn cut_factor(queueing: Duration) -> f64 {
    if queueing > FAR_BEHIND {
        0.25
    } else if queueing > FAR_BEHIND / 4 {
        0.5
    } else {
        0.75
    }
}

/// Connections from one client address: the smallest round trip any of them saw lately (the
/// path's own, without a queue), the smallest in the last [`FLOOR_WINDOW`] (the path floor) and the
/// path's last cut.
#[derive(Debug)]
pub struct Path {
    /// (start of the current window, its minimum, the previous window's minimum).
    windows: Mutex<(Instant, Option<Duration>, Option<Duration>)>,
    /// The path floor: (bucket start, smallest round trip, samples) over [`FLOOR_WINDOW`],
    /// since the last cut.
    floor: Mutex<VecDeque<(Instant, Duration, u32)>>,
    /// The last cut of the path: when, and the rate (frames per second at 60 Hz) it gives
    /// every connection on it.
    congestion: Mutex<Option<(Instant, f64)>>,
    /// The rates of the connections on the path (frames per second at 60 Hz): their sum and
    /// how many, for the share a cut gives each.
    rates: Mutex<(f64, u32)>,
    /// The smallest round trip of each [`FLOOR_BUCKET`] over the last [`TREND_WINDOW`].
    recent: Mutex<VecDeque<(Instant, Duration)>>,
}

impl Path {
    fn new() -> Self {
        Self {
            windows: Mutex::new((Instant::now(), None, None)),
            floor: Mutex::new(VecDeque::new()),
            congestion: Mutex::new(None),
            rates: Mutex::new((0.0, 0)),
            recent: Mutex::new(VecDeque::new()),
        }
    }

    /// Judges the path floor at `now` against the path's `base`: when every round trip of the
    /// last [`FLOOR_WINDOW`] (at least [`CURRENT_OF`] of them) stood more than
    /// [`QUEUE_TARGET`] above it, the queue is the path's: a cut for every connection on it,
    /// to the factor of that queue times their mean rate — one equal share each, so the
    /// faster give up more and the slower may gain, and the path's total still falls by the
    /// factor — unless the last was less than [`PATH_HOLD`] ago (one queue, one cut: it takes
    /// a while to drain after everyone cut). Returns the cut: when, and the share.
    fn judge(&self, now: Instant, base: Duration) -> Option<(Instant, f64)> {
        let queueing = self.floor_above(now, base)?;
        if queueing <= QUEUE_TARGET {
            return None;
        }
        let mut c = self
            .congestion
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        if c.is_some_and(|(at, _)| now - at < PATH_HOLD) {
            return None;
        }
        let (sum, count) = *self.rates_lock();
        let mean = if count == 0 {
            hz(0)
        } else {
            sum / f64::from(count)
        };
        let cut = (now, mean * cut_factor(queueing));
        *c = Some(cut);
        // Judge the next cut by the round trips after this one.
        self.floor_lock().clear();
        Some(cut)
    }

    /// The path floor's height above `base` at `now`, once the last [`FLOOR_WINDOW`] holds at
    /// least [`CURRENT_OF`] round trips.
    fn floor_above(&self, now: Instant, base: Duration) -> Option<Duration> {
        let mut floor = self.floor_lock();
        while floor
            .front()
            .is_some_and(|(at, _, _)| now - *at > FLOOR_WINDOW)
        {
            floor.pop_front();
        }
        let samples: u32 = floor.iter().map(|(_, _, n)| n).sum();
        // The window must be (nearly) full: a cut's first samples are not a floor yet.
        let spans = floor
            .front()
            .is_some_and(|(at, _, _)| now - *at + FLOOR_BUCKET >= FLOOR_WINDOW);
        let smallest = floor.iter().map(|(_, m, _)| *m).min()?;
        (spans && samples as usize >= CURRENT_OF).then(|| smallest.saturating_sub(base))
    }

    fn floor_lock(&self) -> std::sync::MutexGuard<'_, VecDeque<(Instant, Duration, u32)>> {
        self.floor
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    fn rates_lock(&self) -> std::sync::MutexGuard<'_, (f64, u32)> {
        self.rates
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// A connection's rate moved from `from` to `to` frames per second (`None`: it joined or
    /// left the path).
    fn moved(&self, from: Option<f64>, to: Option<f64>) {
        let mut r = self.rates_lock();
        if let Some(f) = from {
            r.0 -= f;
            r.1 = r.1.saturating_sub(1);
        }
        if let Some(t) = to {
            r.0 += t;
            r.1 += 1;
        }
        if r.1 == 0 {
            // No drift from float sums left over.
            r.0 = 0.0;
        }
    }

    fn congestion(&self) -> Option<(Instant, f64)> {
        *self
            .congestion
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, (Instant, Option<Duration>, Option<Duration>)> {
        self.windows
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// Rolls the windows: each lasts [`BASE_WINDOW`], so the base covers the last 10–20 s.
    fn roll(w: &mut (Instant, Option<Duration>, Option<Duration>), now: Instant) {
        if now - w.0 >= BASE_WINDOW {
            let skipped = now - w.0 >= BASE_WINDOW * 2;
            *w = (now, None, if skipped { None } else { w.1 });
        }
    }

    fn observe(&self, now: Instant, rtt: Duration) {
        self.observe_base(now, rtt);
        {
            let mut recent = self
                .recent
                .lock()
                .unwrap_or_else(std::sync::PoisonError::into_inner);
            match recent.back_mut() {
                Some((at, m)) if now - *at < FLOOR_BUCKET => *m = (*m).min(rtt),
                _ => recent.push_back((now, rtt)),
            }
            while recent
                .front()
                .is_some_and(|(at, _)| now - *at > TREND_WINDOW)
            {
                recent.pop_front();
            }
        }
        let mut floor = self.floor_lock();
        match floor.back_mut() {
            Some((at, m, n)) if now - *at < FLOOR_BUCKET => {
                *m = (*m).min(rtt);
                *n += 1;
            }
            _ => floor.push_back((now, rtt, 1)),
        }
    }

    /// A round trip for the base only, not the floor (a session sharing only its base).
    fn observe_base(&self, now: Instant, rtt: Duration) {
        let mut w = self.lock();
        Self::roll(&mut w, now);
        w.1 = Some(w.1.map_or(rtt, |m| m.min(rtt)));
    }

    /// The smallest round trip of the path over the last [`TREND_WINDOW`].
    fn recent_base(&self, now: Instant) -> Option<Duration> {
        self.recent
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .iter()
            .filter(|(at, _)| now - *at <= TREND_WINDOW)
            .map(|(_, m)| *m)
            .min()
    }

    fn base(&self, now: Instant) -> Option<Duration> {
        let mut w = self.lock();
        Self::roll(&mut w, now);
        match (w.1, w.2) {
            (Some(a), Some(b)) => Some(a.min(b)),
            (a, b) => a.or(b),
        }
    }
}

/// The [`Path`]s of the server's connections, by client address.
#[derive(Debug, Default)]
pub struct Paths {
    by_address: Mutex<HashMap<IpAddr, Weak<Path>>>,
}

impl Paths {
    /// The path of a connection from `address` (its own when the address is unknown).
    pub fn join(&self, address: Option<IpAddr>) -> Arc<Path> {
        let Some(address) = address else {
            return Arc::new(Path::new());
        };
        let mut map = self
            .by_address
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        if let Some(path) = map.get(&address).and_then(Weak::upgrade) {
            return path;
        }
        // Forget the paths nobody uses any more before adding one.
        map.retain(|_, p| p.strong_count() > 0);
        let path = Arc::new(Path::new());
        map.insert(address, Arc::downgrade(&path));
        path
    }
}

/// A change of rate, for the metrics.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Change {
    /// The step before (index into [`STEPS`]).
    pub from: usize,
    /// The step after.
    pub to: usize,
    /// What a cut answered (`None`: a raise).
    pub cause: Option<Cause>,
}

/// What a cut of the rate answered, for operators (`posecast_rate_cuts_total{cause}`): a
/// rate cut for the wrong reason — a busy host read as a slow link — shows there.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Cause {
    /// Round trips standing above the base: a queue past the socket (a proxy's, a receive
    /// buffer filling), or any queue when the kernel's figures are not known.
    RoundTrips,
    /// The socket's kernel figures: unsent bytes that stood, or the kernel's round trip above
    /// its smallest.
    Socket,
    /// A ping unanswered past the base round trip and [`UNANSWERED_LATE`].
    Unanswered,
    /// Frames superseded while the socket held the writer.
    Superseded,
    /// The cut of every connection of the client's address (its path floor rose).
    Path,
}

impl Cause {
    /// Every cause, in the order of [`Cause::label`]'s labels.
    pub const ALL: [Self; 5] = [
        Self::RoundTrips,
        Self::Socket,
        Self::Unanswered,
        Self::Superseded,
        Self::Path,
    ];

    /// Its metric label.
    #[must_use]
    pub fn label(self) -> &'static str {
        match self {
            Self::RoundTrips => "round_trips",
            Self::Socket => "socket",
            Self::Unanswered => "unanswered",
            Self::Superseded => "superseded",
            Self::Path => "path",
        }
    }
}

#[derive(Debug)]
struct Control {
    level: usize,
    /// (when, round trip) of recent samples, for the base.
    rtts: VecDeque<(Instant, Duration)>,
    /// The last [`CURRENT_OF`] round trips.
    recent: VecDeque<Duration>,
    /// RFC 3550's jitter over consecutive round trips, and the last round trip.
    jitter: Duration,
    /// Differences the jitter estimate took in.
    jitter_samples: u32,
    last_rtt: Option<Duration>,
    /// The outbox's superseded-frame count at the last sample.
    superseded: u64,
    last_lowered: Option<Instant>,
    /// Since when neither signal fired.
    calm_since: Instant,
    /// The wait of this calm spell, jittered.
    this_wait: Duration,
    /// The oldest unanswered probe (one in flight at a time).
    outstanding: Option<Instant>,
    /// Consecutive round trips that were calm (see [`SETTLED_AFTER`]).
    calm_streak: u32,
    /// Probes passed without a ping since the last one (a settled connection's).
    quiet_probes: u32,
    seed: u64,
    /// Shared with the other connections from the same address.
    path: Option<Arc<Path>>,
    /// The newest congestion event of the path acted on.
    seen_event: Option<Instant>,
    /// The socket's kernel figures over the last [`SOCKET_WINDOW`] (and one before it); once
    /// any came, round trips are judged by their trend ([`TREND_WINDOW`]).
    socket: VecDeque<(Instant, SocketFigures)>,
    /// The last cut was taken blind: a silence judged against [`UNKNOWN_BASE`] before any
    /// round trip was measured. Until a cut judged against a measured base (or the full rate
    /// again), every calm judgement raises a step ([`Control::decide`]).
    blind: bool,
    /// Shared with the other datagram sessions from the same address for the base round trip
    /// only ([`Pace::share_base`]).
    base_path: Option<Arc<Path>>,
}

impl Control {
    fn new(seed: u64) -> Self {
        let now = Instant::now();
        let mut c = Self {
            level: 0,
            rtts: VecDeque::new(),
            recent: VecDeque::new(),
            jitter: Duration::ZERO,
            jitter_samples: 0,
            last_rtt: None,
            superseded: 0,
            last_lowered: None,
            calm_since: now,
            this_wait: PROBE_WAIT,
            outstanding: None,
            calm_streak: 0,
            quiet_probes: 0,
            seed: seed | 1,
            path: None,
            seen_event: None,
            socket: VecDeque::new(),
            blind: false,
            base_path: None,
        };
        c.rejitter();
        c
    }

    /// The queue the socket's figures show over the last [`SOCKET_WINDOW`] (once they span
    /// most of it): the unsent bytes that stood through it, in seconds of what the reader
    /// acknowledged meanwhile, or the kernel's round trip above its smallest, whichever is
    /// more; both the least of the window (a queue that stood, not a burst).
    fn socket_queueing(&self) -> Option<Duration> {
        let ((first_at, first), (last_at, last)) = (*self.socket.front()?, *self.socket.back()?);
        let span = last_at - first_at;
        if self.socket.len() < SOCKET_SAMPLES + 1 || span * 5 < SOCKET_WINDOW * 4 {
            return None;
        }
        let readings = self.socket.iter().skip(1).map(|(_, f)| f);
        let unsent = readings.clone().map(|f| f.unsent).min()?;
        let acked = last.acked.saturating_sub(first.acked) as f64 / span.as_secs_f64();
        let backlog = if unsent == 0 {
            Duration::ZERO
        } else if acked <= 0.0 {
            FAR_BEHIND
        } else {
            Duration::from_secs_f64((unsent as f64 / acked).min(FAR_BEHIND.as_secs_f64() * 4.0))
        };
        let network = readings
            .map(|f| f.rtt.saturating_sub(f.min_rtt))
            .min()
            .unwrap_or_default();
        Some(backlog.max(network))
    }

    /// Whether the connection is *settled* at `now`: at full rate, not lowered in the last
    /// [`SETTLED_NOT_BEFORE`], its last [`SETTLED_AFTER`] round trips calm and the socket's
    /// figures (which still come every probe) showing no standing queue. Its pings then inform
    /// no decision often enough to be worth one every probe (issue 38: they were 10,000 a
    /// second at 2,000 viewers, each a write, a read and two wake-ups): one every
    /// [`SETTLED_PING_EVERY`] probes keeps the trend of the round trips, and the first one
    /// that is not calm ends it.
    fn settled(&self, now: Instant) -> bool {
        self.level == 0
            && self.calm_streak >= SETTLED_AFTER
            && self
                .last_lowered
                .is_none_or(|t| now - t >= SETTLED_NOT_BEFORE)
            && self.socket_queueing().is_some_and(|q| q <= QUEUE_TARGET)
    }

    /// A new jittered wait: the probing wait × 0.75–1.25.
    fn rejitter(&mut self) {
        // xorshift64: a different sequence per connection, no shared generator.
        self.seed ^= self.seed << 13;
        self.seed ^= self.seed >> 7;
        self.seed ^= self.seed << 17;
        let unit = (self.seed >> 11) as f64 / (1u64 << 53) as f64;
        self.this_wait = PROBE_WAIT.mul_f64(0.75 + 0.5 * unit);
    }

    fn base(&self, now: Instant) -> Option<Duration> {
        if !self.socket.is_empty() {
            // The kernel shows the queues that stand: round trips show those that grow.
            return self
                .rtts
                .iter()
                .filter(|(at, _)| now - *at <= TREND_WINDOW)
                .map(|(_, r)| *r)
                .min();
        }
        let own = self.rtts.iter().map(|(_, r)| *r).min();
        let shared = self.path.as_ref().or(self.base_path.as_ref());
        match (own, shared.and_then(|p| p.base(now))) {
            (Some(a), Some(b)) => Some(a.min(b)),
            (a, b) => a.or(b),
        }
    }

    /// The current round trip: the smallest of the last [`CURRENT_OF`] (once there are).
    fn current(&self) -> Option<Duration> {
        if self.recent.len() < CURRENT_OF {
            return None;
        }
        self.recent.iter().copied().min()
    }

    /// Takes in a round trip: the jitter estimate `J += (|D| − J) / 16` (RFC 3550 §6.4.1),
    /// the mean of the `|D|` so far for the first 16 (from zero, the estimator takes seconds
    /// to reach a spread it sees from the start).
    fn sample(&mut self, rtt: Duration) {
        if let Some(last) = self.last_rtt {
            let d = rtt.abs_diff(last);
            let n = self.jitter_samples.min(15) + 1;
            self.jitter_samples = self.jitter_samples.saturating_add(1);
            self.jitter = if d >= self.jitter {
                self.jitter + (d - self.jitter) / n
            } else {
                self.jitter - (self.jitter - d) / n
            };
        }
        self.last_rtt = Some(rtt);
        if self.recent.len() == CURRENT_OF {
            self.recent.pop_front();
        }
        self.recent.push_back(rtt);
    }

    /// How far above the base the floor of a jittery path lands without any queue: 2 `J`, at
    /// most [`QUEUE_TARGET`] (so a standing queue of twice the target still cuts).
    ///
    /// With the socket's figures, up to [`FAR_BEHIND`]: a reader late by its scheduling
    /// answers anywhere in its spread, and the queues that stand are the kernel's to show.
    fn allowance(&self) -> Duration {
        let most = if self.socket.is_empty() {
            QUEUE_TARGET
        } else {
            FAR_BEHIND
        };
        (self.jitter * 2).min(most)
    }

    /// Moves to step `level`, and tells the path.
    fn set_level(&mut self, level: usize) {
        if level != self.level
            && let Some(path) = &self.path
        {
            path.moved(Some(hz(self.level)), Some(hz(level)));
        }
        self.level = level;
    }

    /// Joins `path` (leaving the one it was on).
    fn join(&mut self, path: Arc<Path>) {
        if let Some(old) = &self.path {
            old.moved(Some(hz(self.level)), None);
        }
        path.moved(None, Some(hz(self.level)));
        self.path = Some(path);
    }

    /// Cuts the rate to the step at or below `factor` of it.
    fn lower(&mut self, now: Instant, factor: f64) {
        self.lower_to(now, hz(self.level) * factor);
    }

    /// Moves to the step at or below `target` frames per second (down, or up to it after a
    /// path's cut to equal shares) and judges the new rate from there.
    fn lower_to(&mut self, now: Instant, target: f64) {
        let level = (0..STEPS.len())
            .find(|&l| hz(l) <= target)
            .unwrap_or(STEPS.len() - 1);
        self.set_level(level);
        self.last_lowered = Some(now);
        self.blind = false;
        self.calm_since = now;
        self.calm_streak = 0;
        // Judge the new rate by its own round trips.
        self.recent.clear();
        self.rejitter();
    }

    /// Acts on the signals at `now`: `queueing` (if known) and frames superseded since the last
    /// sample, after any cut of the path.
    fn decide(
        &mut self,
        now: Instant,
        queueing: Option<Duration>,
        superseded: u64,
        source: Cause,
    ) -> Option<Change> {
        let from = self.level;
        let may_lower = self.last_lowered.is_none_or(|t| now - t >= HOLD);
        // The path's floor rose: the queue is shared, so every connection on it cuts (the cuts
        // of one path are simultaneous, which is what makes AIMD converge to fair rates).
        let event = self.path.as_ref().and_then(|p| p.congestion());
        if let Some((at, share)) = event
            && self.seen_event.is_none_or(|seen| at > seen)
        {
            self.seen_event = Some(at);
            if may_lower {
                self.lower_to(now, share);
                return (self.level != from).then_some(Change {
                    from,
                    to: self.level,
                    cause: (self.level > from).then_some(Cause::Path),
                });
            }
        }
        let queued = queueing.is_some_and(|q| q > QUEUE_TARGET);
        let congested = superseded >= 2 || queued;
        if congested {
            self.calm_since = now;
            if may_lower && self.level + 1 < STEPS.len() {
                let factor = queueing.map_or(0.75, cut_factor);
                self.lower(now, factor);
            }
        } else if queueing.is_some_and(|q| q <= QUEUE_TARGET / 2) {
            // Additive increase: the wait grows with the step (1 s per frame/s, at most 4 s),
            // so every connection gains frames per second at about the same pace. After a
            // blind cut, none: a step each calm judgement (as TCP's slow start after a
            // timeout), back to where a measured base shows a queue or to the full rate.
            let wait = if self.blind {
                Duration::ZERO
            } else {
                self.this_wait
                    .mul_f64((hz(self.level.saturating_sub(1)) - hz(self.level)).clamp(1.0, 4.0))
            };
            if self.level > 0 && now - self.calm_since >= wait {
                self.set_level(self.level - 1);
                self.calm_since = now;
                self.rejitter();
            }
            self.blind &= self.level > 0;
        }
        (self.level != from).then_some(Change {
            from,
            to: self.level,
            cause: (self.level > from).then_some(if queued { source } else { Cause::Superseded }),
        })
    }
}

impl Drop for Control {
    /// The connection leaves its path's rates.
    fn drop(&mut self) {
        if let Some(path) = &self.path {
            path.moved(Some(hz(self.level)), None);
        }
    }
}

/// A connection's pace: its current rate and what decides it.
#[derive(Debug)]
pub struct Pace {
    rate: AtomicU32,
    control: Mutex<Control>,
}

impl Default for Pace {
    /// Full rate, seeded by a running count (each connection probes on its own schedule).
    fn default() -> Self {
        static SEEDS: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(1);
        Self::new(SEEDS.fetch_add(1, Ordering::Relaxed))
    }
}

impl Pace {
    /// Full rate; `seed` (e.g. the connection id) staggers its probing from other connections'.
    #[must_use]
    pub fn new(seed: u64) -> Self {
        Self {
            rate: AtomicU32::new(STEPS[0]),
            control: Mutex::new(Control::new(seed.wrapping_mul(0x9e37_79b9_7f4a_7c15))),
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Control> {
        // Every update leaves the state consistent: a poisoned lock is still usable.
        self.control
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// The connection's rate: frames per 60 ticks (60: every tick); see [`sends`].
    #[must_use]
    pub fn rate(&self) -> u32 {
        self.rate.load(Ordering::Relaxed)
    }

    /// Shares the base round trip with the other connections on `path`.
    pub fn set_path(&self, path: Arc<Path>) {
        self.lock().join(path);
    }

    /// Shares the base round trip with the other connections on `path`, and nothing else:
    /// not its floor, not its cuts. For datagram sessions (QUIC paces them, and their round
    /// trips are the acknowledgements of frames): fifty viewers joining a thin link at once
    /// fill its queue with their keyframes before anyone's first answer, and a session that
    /// never saw it drained would take the queue for its base — one that did is enough.
    pub fn share_base(&self, path: Arc<Path>) {
        self.lock().base_path = Some(path);
    }

    /// The current step (index into [`STEPS`]).
    #[must_use]
    pub fn level(&self) -> usize {
        self.lock().level
    }

    fn apply(&self, change: Option<Change>) -> Option<Change> {
        if let Some(c) = change {
            self.rate.store(STEPS[c.to], Ordering::Relaxed);
        }
        change
    }

    /// Time to probe at `now`: returns whether to send a ping (none while one is unanswered).
    /// An unanswered ping older than the base round trip plus [`UNANSWERED_LATE`] counts as a
    /// sample of its age; `superseded` is the outbox's running count of superseded frames.
    pub fn probe(&self, now: Instant, superseded: u64) -> (bool, Option<Change>) {
        let mut c = self.lock();
        let new_superseded = superseded.saturating_sub(c.superseded);
        c.superseded = superseded;
        match c.outstanding {
            None if c.settled(now) && c.quiet_probes + 1 < SETTLED_PING_EVERY => {
                c.quiet_probes += 1;
                // Its calm round trip still counts towards its path's floor: a settled
                // connection pinging less must not leave the floor to the late and slow
                // readers of its address, whose round trips would read as the path's queue
                // and cut every connection on it.
                if let (Some(path), Some(rtt)) = (c.path.clone(), c.last_rtt) {
                    path.observe(now, rtt);
                }
                let change = if new_superseded >= 2 {
                    c.calm_streak = 0;
                    c.decide(now, None, new_superseded, Cause::Superseded)
                } else {
                    None
                };
                drop(c);
                (false, self.apply(change))
            }
            None => {
                c.quiet_probes = 0;
                c.outstanding = Some(now);
                let change = if new_superseded >= 2 {
                    c.decide(now, None, new_superseded, Cause::Superseded)
                } else {
                    None
                };
                drop(c);
                (true, self.apply(change))
            }
            Some(sent) => {
                let age = now - sent;
                // Before the first answer the path's round trip is unknown: take it as
                // UNKNOWN_BASE (a long path), so a first ping stuck behind a queue still counts.
                let known = c.base(now);
                let base = known.unwrap_or(UNKNOWN_BASE);
                // With the socket's figures, less the reader's spread (its scheduling).
                let spread = if c.socket.is_empty() {
                    Duration::ZERO
                } else {
                    c.allowance()
                };
                let queueing = Some(age.saturating_sub(base).saturating_sub(spread));
                // Past a retransmission stall: one lost segment (TCP's 200 ms minimum RTO)
                // is not a queue.
                let late = queueing.filter(|q| *q > UNANSWERED_LATE);
                if late.is_some() {
                    c.calm_streak = 0;
                }
                let change = if late.is_some() || new_superseded >= 2 {
                    c.decide(now, late, new_superseded, Cause::Unanswered)
                } else {
                    None
                };
                // Cut for a silence with no round trip measured: on a lossy path a joiner
                // whose first frames were lost (its keyframe goes again every 250 ms until
                // one is acknowledged) is silent that long with no queue anywhere; behind a
                // thin link the joiners' first frames fill its queue. Either way the cut
                // drains what there is, and the round trips after it are judged against a
                // measured base: they bring the rate back fast (slow start), not a step per
                // seconds.
                if known.is_none() && change.is_some_and(|ch| ch.to > ch.from) {
                    c.blind = true;
                }
                drop(c);
                (false, self.apply(change))
            }
        }
    }

    /// The kernel's figures of the connection's socket at `now` (every probe, with the
    /// ping): a backlog of unsent bytes that stood through the last [`SOCKET_WINDOW`], or a
    /// kernel round trip standing above its smallest, is a queue of that many seconds at the
    /// pace the reader acknowledged — cut as round trips' queueing is. From the first figures
    /// on, round trips are judged by their trend ([`TREND_WINDOW`]).
    pub fn socket(&self, now: Instant, figures: SocketFigures) -> Option<Change> {
        let mut c = self.lock();
        c.socket.push_back((now, figures));
        // Keep one reading at or before the window's start: rates are measured from it.
        while c.socket.len() > 2 && now - c.socket[1].0 >= SOCKET_WINDOW {
            c.socket.pop_front();
        }
        let queueing = c.socket_queueing()?;
        let change = if queueing > QUEUE_TARGET {
            c.decide(now, Some(queueing), 0, Cause::Socket)
        } else {
            None
        };
        drop(c);
        self.apply(change)
    }

    /// A pong arrived at `now` for a ping sent `rtt` ago.
    pub fn answered(&self, now: Instant, rtt: Duration) -> Option<Change> {
        let mut c = self.lock();
        c.outstanding = None;
        c.rtts.push_back((now, rtt));
        while c.rtts.front().is_some_and(|(t, _)| now - *t > BASE_WINDOW) {
            c.rtts.pop_front();
        }
        c.sample(rtt);
        let mut allowance = c.allowance();
        let kernel = !c.socket.is_empty();
        if let (Some(path), Some(base)) = (c.path.clone(), c.base(now)) {
            path.observe(now, rtt);
            // With the kernel's figures, the path's floor against its own recent smallest:
            // a shared queue growing (every connection's round trips rise together).
            let base = if kernel {
                path.recent_base(now).unwrap_or(base)
            } else {
                base
            };
            // Spread on a rising floor is a queue's, not jitter: no allowance then.
            if path
                .floor_above(now, base)
                .is_some_and(|q| q > QUEUE_TARGET)
            {
                allowance = Duration::ZERO;
            }
            path.judge(now, base);
        } else if let Some(path) = &c.path {
            path.observe(now, rtt);
        } else if let Some(path) = &c.base_path {
            path.observe_base(now, rtt);
        }
        // Above the base and the jitter allowance: a queue of this connection's own (or of
        // its path).
        let base = c.base(now);
        let queueing = match (c.current(), base) {
            (Some(m), Some(b)) => Some(m.saturating_sub(b).saturating_sub(allowance)),
            _ => None,
        };
        // This round trip alone, judged alike: one that would show a queue ends a settled
        // spell.
        let calm =
            base.is_some_and(|b| rtt.saturating_sub(b).saturating_sub(allowance) <= QUEUE_TARGET);
        c.calm_streak = if calm {
            c.calm_streak.saturating_add(1)
        } else {
            0
        };
        let change = c.decide(now, queueing, 0, Cause::RoundTrips);
        drop(c);
        self.apply(change)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const MS: Duration = Duration::from_millis(1);

    #[test]
    fn a_rate_sends_that_many_of_60_ticks_evenly_whatever_the_phase() {
        for rate in STEPS {
            for phase in [0, 7, 59, 1_000_003] {
                let sent: Vec<u64> = (1_000..1_120).filter(|&s| sends(rate, s, phase)).collect();
                assert_eq!(sent.len() as u32, 2 * rate, "{rate} {phase}");
                // Evenly: gaps differ by at most one tick.
                let gaps: Vec<u64> = sent.windows(2).map(|w| w[1] - w[0]).collect();
                let (min, max) = (gaps.iter().min(), gaps.iter().max());
                if let (Some(min), Some(max)) = (min, max) {
                    assert!(max - min <= 1, "{rate}: {gaps:?}");
                }
            }
        }
        // Phases spread connections of one rate over the ticks.
        let first: std::collections::BTreeSet<u64> = (0..10)
            .map(|phase| (0..60).find(|&s| sends(5, s, phase)).unwrap())
            .collect();
        assert!(first.len() >= 8, "{first:?}");
    }

    /// Feeds probes every 200 ms from `from_s` to `to_s` whose round trip is `rtt(t)`.
    fn run(pace: &Pace, start: Instant, from_s: f64, to_s: f64, rtt: impl Fn(f64) -> Duration) {
        let mut t = from_s;
        while t < to_s {
            let now = start + Duration::from_secs_f64(t);
            let (send, _) = pace.probe(now, 0);
            if send {
                let r = rtt(t);
                pace.answered(now + r, r);
            }
            t += 0.2;
        }
    }

    #[test]
    fn a_standing_queue_lowers_the_rate_and_a_drained_one_raises_it_again() {
        let pace = Pace::new(1);
        let start = Instant::now();
        // 50 ms round trips: the path's own; full rate stays.
        run(&pace, start, 0.0, 5.0, |_| 50 * MS);
        assert_eq!(pace.rate(), 60);
        // A queue of 100 ms builds: one step down per HOLD (500 ms) while it stands.
        run(&pace, start, 5.0, 7.0, |_| 150 * MS);
        let lowered = pace.level();
        assert!((2..=4).contains(&lowered), "{lowered}");
        // The queue drains: back up one step per probing wait (≥ 1.5 s each).
        run(&pace, start, 7.0, 30.0, |_| 50 * MS);
        assert_eq!(pace.rate(), 60);
    }

    #[test]
    fn retransmission_stalls_do_not_lower_it() {
        let pace = Pace::new(2);
        let start = Instant::now();
        // Retransmission stalls (250 ms) in three samples of ten among 50 ms round trips:
        // the smallest of four ignores them.
        run(&pace, start, 0.0, 20.0, |t| {
            if matches!((t * 5.0).round() as u64 % 10, 3..=5) {
                250 * MS
            } else {
                50 * MS
            }
        });
        assert_eq!(pace.rate(), 60);
    }

    #[test]
    fn superseded_frames_lower_it_and_it_never_drops_below_the_last_step() {
        let pace = Pace::new(3);
        let start = Instant::now();
        run(&pace, start, 0.0, 1.0, |_| 10 * MS);
        let mut superseded = 0;
        for i in 0..100u32 {
            superseded += 5;
            let now = start + Duration::from_secs(1) + 600 * MS * i;
            let (send, _) = pace.probe(now, superseded);
            if send {
                pace.answered(now + 10 * MS, 10 * MS);
            }
        }
        assert_eq!(pace.rate(), *STEPS.last().unwrap());
    }

    /// A seeded uniform draw in `[0, 1)` (xorshift64), so the simulated links repeat.
    fn unit(state: &mut u64) -> f64 {
        *state ^= *state << 13;
        *state ^= *state >> 7;
        *state ^= *state << 17;
        (*state >> 11) as f64 / (1u64 << 53) as f64
    }

    /// `n` connections, of one address if `shared` (else each of its own), each probing every
    /// 200 ms (staggered) for `seconds`; `rtt(connection, t, dice)` gives a round trip.
    /// Returns each connection's mean frames per second over the second half.
    fn path_of(
        shared: bool,
        n: usize,
        seconds: f64,
        mut rtt: impl FnMut(usize, f64, &mut u64) -> f64,
    ) -> Vec<f64> {
        let paths = Paths::default();
        let paces: Vec<Pace> = (0..n)
            .map(|i| {
                let p = Pace::new(100 + i as u64);
                let last = if shared { 7 } else { i as u8 };
                p.set_path(paths.join(Some(IpAddr::from([192, 0, 2, last]))));
                p
            })
            .collect();
        let start = Instant::now();
        let mut dice = 0x2545_f491_4f6c_dd1d_u64;
        let mut sums = vec![0.0; n];
        let mut counted = 0u32;
        // Answers in flight: (when it arrives, who, its round trip), in milliseconds.
        let mut pending: Vec<(u64, usize, f64)> = Vec::new();
        let at = |ms: u64| start + Duration::from_millis(ms);
        for ms in (0..(seconds * 1000.0) as u64).step_by(2) {
            let t = ms as f64 / 1e3;
            // Connection i probes at i × 4 ms (mod 200 ms).
            for (i, pace) in paces.iter().enumerate() {
                if ms % 200 == (i as u64 * 4) % 200 && pace.probe(at(ms), 0).0 {
                    let r = rtt(i, t, &mut dice);
                    pending.push((ms + (r * 1e3).round() as u64, i, r));
                }
            }
            pending.retain(|&(arrives, i, r)| {
                let due = arrives <= ms;
                if due {
                    paces[i].answered(at(ms), Duration::from_secs_f64(r));
                }
                !due
            });
            if t >= seconds / 2.0 && ms % 100 == 0 {
                for (sum, pace) in sums.iter_mut().zip(&paces) {
                    *sum += f64::from(pace.rate());
                }
                counted += 1;
            }
        }
        sums.iter().map(|s| s / f64::from(counted.max(1))).collect()
    }

    #[test]
    fn jitter_without_a_rising_floor_is_not_a_queue() {
        // 25 ± 20 ms each way (reordering jitter as wide as the queue target): round trips
        // spread over 10–90 ms, the floor stays at 10.
        let rates = path_of(false, 1, 60.0, |_, _, d| {
            0.010 + 0.040 * unit(d) + 0.040 * unit(d)
        });
        assert!(rates[0] >= 57.0, "{rates:?}");
    }

    #[test]
    fn fifty_connections_of_one_address_do_not_multiply_each_others_stalls() {
        // 25 ± 10 ms each way, and now and then one connection's own stall (a spurious
        // retransmission cutting its window): a second of round trips 80 ms longer, about
        // every 20 s per connection — 2.5 a second among 50.
        let stalls = || {
            let mut stalled_until = [0.0f64; 50];
            move |i: usize, t: f64, d: &mut u64| {
                if t >= stalled_until[i] && unit(d) < 0.2 / 20.0 {
                    stalled_until[i] = t + 1.0;
                }
                let stall = if t < stalled_until[i] { 0.080 } else { 0.0 };
                0.030 + 0.020 * unit(d) + 0.020 * unit(d) + stall
            }
        };
        // What each gets alone (its own address), and behind one address.
        let alone = path_of(false, 50, 60.0, stalls());
        let shared = path_of(true, 50, 60.0, stalls());
        let figures = |r: &[f64]| {
            let min = r.iter().copied().fold(f64::INFINITY, f64::min);
            (min, r.iter().sum::<f64>() / r.len() as f64)
        };
        let ((alone_min, alone_mean), (min, mean)) = (figures(&alone), figures(&shared));
        eprintln!(
            "50 connections with their own stalls: frames/s alone min {alone_min:.1} mean \
             {alone_mean:.1}; behind one address min {min:.1} mean {mean:.1}"
        );
        assert!(mean >= 0.95 * alone_mean, "{shared:?} vs alone {alone:?}");
        assert!(min >= alone_min - 5.0, "{shared:?} vs alone {alone:?}");
    }

    #[test]
    fn a_shared_cut_gives_every_connection_of_the_path_one_equal_share() {
        let paths = Paths::default();
        let path = paths.join(Some(IpAddr::from([192, 0, 2, 9])));
        let paces: Vec<Pace> = [0usize, 2, 5, 9]
            .iter()
            .map(|&level| {
                let p = Pace::new(level as u64 + 1);
                p.set_path(path.clone());
                p.lock().set_level(level);
                p
            })
            .collect();
        // 60, 30, 15 and 6 frames/s.
        let mean = (60.0 + 30.0 + 15.0 + 6.0) / 4.0;
        assert_eq!(*path.rates_lock(), (111.0, 4));
        // Every round trip of the last half second 110 ms above the base of 20 ms: a queue
        // past a quarter of FAR_BEHIND, so the path's rate halves.
        let start = Instant::now();
        for ms in (0..=500).step_by(20) {
            path.observe(start + Duration::from_millis(ms), 130 * MS);
        }
        let now = start + Duration::from_millis(500);
        let (_, share) = path.judge(now, 20 * MS).expect("a shared cut");
        assert!((share - mean * 0.5).abs() < 1e-9, "{share}");
        for p in &paces {
            let change = p.lock().decide(now, None, 0, Cause::RoundTrips);
            p.apply(change);
        }
        // Half the mean, 13.9 frames/s, each: all at the step below, 12 — the fastest down
        // from 60, the slowest up from 6; the path's total falls from 111 to 48.
        let rates: Vec<u32> = paces.iter().map(Pace::rate).collect();
        assert_eq!(rates, [12, 12, 12, 12]);
        assert_eq!(*path.rates_lock(), (48.0, 4));
        // Connections that end leave the path's rates.
        drop(paces);
        assert_eq!(*path.rates_lock(), (0.0, 0));
    }

    #[test]
    fn a_standing_queue_shared_by_the_path_cuts_every_connection() {
        // 20 connections behind one bottleneck: at 10 s a queue of 150 ms stands for all.
        let rates = path_of(true, 20, 20.0, |_, t, d| {
            0.020 + 0.002 * unit(d) + if t >= 10.0 { 0.150 } else { 0.0 }
        });
        assert!(rates.iter().all(|&r| r <= 30.0), "{rates:?}");
    }

    #[test]
    fn an_unanswered_ping_counts_as_a_late_one() {
        let pace = Pace::new(4);
        let start = Instant::now();
        run(&pace, start, 0.0, 2.0, |_| 20 * MS);
        // A ping sent at 2 s is not answered: at 2.2 s it could be a lost segment's
        // retransmission (no cut); by 2.4 s it is 400 ms old, 380 ms more than the base —
        // past a quarter of FAR_BEHIND, so the rate halves: 60 → 30.
        assert!(pace.probe(start + 2000 * MS, 0).0);
        assert_eq!(pace.probe(start + 2200 * MS, 0), (false, None));
        let (send, change) = pace.probe(start + 2400 * MS, 0);
        assert!(!send, "one ping in flight at a time");
        assert_eq!(
            change,
            Some(Change {
                from: 0,
                to: 2,
                cause: Some(Cause::Unanswered)
            })
        );
        assert_eq!(pace.rate(), 30);
    }

    /// A silence before any round trip (a joiner's lost keyframes) is cut blind, against
    /// the assumed base; the calm round trips after it bring the rate back a step each (slow
    /// start), where a cut judged against a measured base comes back a step per seconds.
    #[test]
    fn after_a_blind_cut_calm_round_trips_bring_the_rate_back_fast() {
        let start = Instant::now();
        let blind = Pace::new(5);
        assert!(blind.probe(start, 0).0);
        let (_, change) = blind.probe(start + 600 * MS, 0);
        assert_eq!(change.and_then(|c| c.cause), Some(Cause::Unanswered));
        assert_eq!(blind.rate(), 30);
        blind.answered(start + 650 * MS, 50 * MS);
        run(&blind, start, 0.8, 2.6, |_| 50 * MS);
        assert_eq!(
            blind.rate(),
            60,
            "back within two seconds of calm round trips"
        );

        let measured = Pace::new(5);
        run(&measured, start, 0.0, 2.0, |_| 50 * MS);
        assert!(measured.probe(start + 2000 * MS, 0).0);
        measured.probe(start + 2400 * MS, 0);
        let cut = measured.level();
        assert!(cut > 0);
        measured.answered(start + 2450 * MS, 50 * MS);
        run(&measured, start, 2.6, 4.4, |_| 50 * MS);
        assert!(
            measured.level() + 1 >= cut,
            "{} from {cut}",
            measured.level()
        );
    }

    /// Datagram sessions of one address share their base and nothing else: one that only
    /// ever saw the queue its neighbours' keyframes filled judges it against the round trip
    /// another measured before — and a neighbour's queued round trips cut no one else.
    #[test]
    fn a_shared_base_shows_a_queue_a_latecomer_never_saw_drained() {
        let start = Instant::now();
        let queued = |_: f64| 130 * MS;
        let alone = Pace::new(6);
        run(&alone, start, 0.0, 3.0, queued);
        assert_eq!(
            alone.rate(),
            60,
            "no base but the queue: nothing to judge it by"
        );

        let paths = Paths::default();
        let address = Some(IpAddr::from([10, 0, 0, 1]));
        let (early, late) = (Pace::new(7), Pace::new(8));
        early.share_base(paths.join(address));
        late.share_base(paths.join(address));
        run(&early, start, 0.0, 1.0, |_| 5 * MS);
        run(&late, start, 1.0, 4.0, queued);
        assert!(late.rate() <= 30, "{}", late.rate());
        assert_eq!(early.rate(), 60, "no shared cut");
    }

    /// [`run`] with the socket's figures every probe: `socket(t)` gives the unsent bytes and
    /// the kernel's round trip above its smallest; the reader acknowledges 50 KB a second.
    fn run_with_socket(
        pace: &Pace,
        start: Instant,
        from_s: f64,
        to_s: f64,
        rtt: impl Fn(f64) -> Duration,
        socket: impl Fn(f64) -> (u64, Duration),
    ) {
        let mut t = from_s;
        while t < to_s {
            let now = start + Duration::from_secs_f64(t);
            let (unsent, queued) = socket(t);
            pace.socket(
                now,
                SocketFigures {
                    acked: (t * 50_000.0) as u64,
                    unsent,
                    rtt: MS + queued,
                    min_rtt: MS,
                },
            );
            let (send, _) = pace.probe(now, 0);
            if send {
                let r = rtt(t);
                pace.answered(now + r, r);
            }
            t += 0.2;
        }
    }

    /// Round trips of a reader that runs every 300 ms: 0–300 ms late, whatever the rate.
    fn late_reader(seed: u64) -> impl Fn(f64) -> Duration {
        move |t| {
            let mut d = ((t * 5.0).round() as u64 ^ seed).wrapping_mul(0x9e37_79b9_7f4a_7c15) | 1;
            MS + Duration::from_secs_f64(0.3 * unit(&mut d))
        }
    }

    #[test]
    fn a_late_reader_with_an_empty_socket_keeps_its_rate_and_without_the_figures_is_cut() {
        let start = Instant::now();
        let with = Pace::new(7);
        run_with_socket(&with, start, 0.0, 30.0, late_reader(7), |_| {
            (0, Duration::ZERO)
        });
        let without = Pace::new(7);
        run(&without, start, 0.0, 30.0, late_reader(7));
        assert_eq!(with.rate(), 60);
        assert!(without.rate() <= 30, "{}", without.rate());
    }

    #[test]
    fn a_backlog_standing_in_the_socket_or_a_kernel_queue_lowers_the_rate() {
        let start = Instant::now();
        // Prompt round trips, but 20 KB stand unsent (0.4 s at what the reader takes).
        let backlog = Pace::new(8);
        run_with_socket(
            &backlog,
            start,
            0.0,
            3.0,
            |_| 2 * MS,
            |_| (20_000, Duration::ZERO),
        );
        assert!(backlog.rate() <= 30, "{}", backlog.rate());
        // A burst (unsent at one reading, gone at the next) is not a backlog.
        let burst = Pace::new(9);
        run_with_socket(
            &burst,
            start,
            0.0,
            3.0,
            |_| 2 * MS,
            |t| {
                (
                    if ((t * 5.0).round() as u64).is_multiple_of(2) {
                        20_000
                    } else {
                        0
                    },
                    Duration::ZERO,
                )
            },
        );
        assert_eq!(burst.rate(), 60);
        // The kernel's round trip 150 ms above its smallest: a queue in the network.
        let network = Pace::new(10);
        run_with_socket(&network, start, 0.0, 3.0, |_| 2 * MS, |_| (0, 150 * MS));
        assert!(network.rate() <= 30, "{}", network.rate());
    }

    #[test]
    fn with_the_figures_a_growing_queue_past_the_socket_still_lowers_the_rate() {
        // A queue the kernel cannot see (a receive buffer filling, a proxy): round trips grow
        // by 100 ms a second from 5 s on.
        let pace = Pace::new(11);
        let start = Instant::now();
        let growing = |t: f64| MS * 20 + Duration::from_secs_f64((t - 5.0).max(0.0) * 0.1);
        run_with_socket(&pace, start, 0.0, 5.0, growing, |_| (0, Duration::ZERO));
        assert_eq!(pace.rate(), 60);
        run_with_socket(&pace, start, 5.0, 8.0, growing, |_| (0, Duration::ZERO));
        assert!(pace.rate() <= 45, "{}", pace.rate());
    }

    /// Pings `pace` sends from `from_s` to `to_s` at probes 200 ms apart, round trips `rtt(t)`,
    /// the socket's figures every probe when `socket` (an empty socket), none otherwise.
    fn pings(
        pace: &Pace,
        start: Instant,
        from_s: f64,
        to_s: f64,
        rtt: impl Fn(f64) -> Duration,
        socket: bool,
    ) -> usize {
        let mut t = from_s;
        let mut sent = 0;
        while t < to_s - 1e-9 {
            let now = start + Duration::from_secs_f64(t);
            if socket {
                pace.socket(
                    now,
                    SocketFigures {
                        acked: (t * 50_000.0) as u64,
                        unsent: 0,
                        rtt: MS,
                        min_rtt: MS,
                    },
                );
            }
            let (send, _) = pace.probe(now, 0);
            if send {
                sent += 1;
                let r = rtt(t);
                pace.answered(now + r, r);
            }
            t += 0.2;
        }
        sent
    }

    /// A calm connection at full rate with the socket's figures settles after
    /// `SETTLED_AFTER` calm round trips and pings once a second instead of five times; the
    /// first round trip that is not calm brings back every probe's ping, and the queue it shows
    /// still lowers the rate. Without the figures (round trips are all it has) it never settles.
    #[test]
    fn a_settled_connection_pings_once_a_second_until_a_round_trip_is_not_calm() {
        let start = Instant::now();
        let pace = Pace::new(12);
        let calm = |_| 20 * MS;
        // The first 2 s: every probe (10), then settled: one ping a second.
        assert_eq!(pings(&pace, start, 0.0, 2.0, calm, true), 10);
        let settled = pings(&pace, start, 2.0, 12.0, calm, true);
        assert!(
            (10..=11).contains(&settled),
            "{settled} pings in 10 s settled"
        );
        assert_eq!(pace.rate(), 60);
        // A queue grows past the socket (a proxy's): 150 ms more from 12 s on.
        let queued = |t: f64| if t >= 12.0 { 170 * MS } else { 20 * MS };
        // The next ping (within a second) finds it; every probe pings from then on.
        let after = pings(&pace, start, 12.0, 14.0, queued, true);
        assert!(after >= 6, "{after} pings in the 2 s after the rise");
        assert!(pace.rate() < 60, "{}", pace.rate());
        // Without the socket's figures: every probe, however calm.
        let bare = Pace::new(13);
        assert_eq!(pings(&bare, start, 0.0, 12.0, calm, false), 60);
    }

    /// Each cut names what it answered: the socket's backlog, round trips that rose, frames
    /// superseded; a raise names nothing.
    #[test]
    fn every_cut_names_its_cause() {
        let start = Instant::now();
        let at = |t: f64| start + Duration::from_secs_f64(t);
        let figures = |t: f64, unsent| SocketFigures {
            acked: (t * 50_000.0) as u64,
            unsent,
            rtt: MS,
            min_rtt: MS,
        };
        // 20 KB standing unsent, prompt round trips: the socket's doing.
        let socket = Pace::new(21);
        let mut causes = Vec::new();
        for k in 0..15 {
            let t = f64::from(k) * 0.2;
            causes.extend(socket.socket(at(t), figures(t, 20_000)));
            let (send, change) = socket.probe(at(t), 0);
            causes.extend(change);
            if send {
                causes.extend(socket.answered(at(t) + 2 * MS, 2 * MS));
            }
        }
        assert!(!causes.is_empty());
        assert!(
            causes.iter().all(|c| c.cause == Some(Cause::Socket)),
            "{causes:?}"
        );
        // Round trips 150 ms above their base, no figures: round trips.
        let rtts = Pace::new(22);
        let mut causes = Vec::new();
        for k in 0..40 {
            let t = f64::from(k) * 0.2;
            let r = if t < 4.0 { 20 * MS } else { 170 * MS };
            let (send, change) = rtts.probe(at(t), 0);
            causes.extend(change);
            if send {
                causes.extend(rtts.answered(at(t) + r, r));
            }
        }
        assert!(!causes.is_empty());
        assert!(
            causes.iter().all(|c| c.cause == Some(Cause::RoundTrips)),
            "{causes:?}"
        );
        // Frames superseded, calm round trips: superseded; back up later with no cause.
        let superseded = Pace::new(23);
        let (send, change) = superseded.probe(at(0.0), 5);
        assert_eq!(change.map(|c| c.cause), Some(Some(Cause::Superseded)));
        assert!(send);
        assert_eq!(superseded.answered(at(0.02), 20 * MS), None);
        let mut raised = Vec::new();
        for k in 1..100 {
            let t = f64::from(k) * 0.2;
            let (send, change) = superseded.probe(at(t), 5);
            raised.extend(change);
            if send {
                raised.extend(superseded.answered(at(t) + 20 * MS, 20 * MS));
            }
        }
        assert_eq!(superseded.rate(), 60);
        assert!(raised.iter().all(|c| c.to < c.from && c.cause.is_none()));
    }
}
