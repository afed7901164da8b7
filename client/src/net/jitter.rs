//! Jitter buffer: keeps an avatar's recent poses by server time and gives an interpolated pose
//! at a render time a little in the past, so irregular arrival does not show as stutter.
//!
//! **Playout point.** A frame stamped `s` on the server's clock arrives at `a` on the
//! client's; its *raw transit* `a − s` is the one-way delay plus the (constant) clock offset.
//! Rendering at client time `now` samples server time `now − D` with
//! `D = q(a − s) + one frame interval`, where `q` is the 99.5th percentile of the raw transits
//! of the last [`WINDOW`] frames (10 s at 60 Hz) and the interval is the longest gap between
//! the stamps of the last [`GAPS`] frames (one tick at full rate; more when the server paces
//! the connection, `stream/src/pace.rs`). Every frame stamped up to `now − D + tick` then
//! arrived with 99.5 % probability, so the point lies between two received frames and is
//! interpolated. The clock offset cancels out: no ping is needed to play out. The delay
//! follows the link: a steady 25 ms one way gives ~25 ms + a tick; TCP's recovery of a lost
//! segment (a retransmission holds back every frame behind it) shows as a tail of late frames,
//! and the percentile covers it once losses are frequent enough to matter.
//!
//! **Gaps.** Past the newest frame the pose is extrapolated from the last two frames for at
//! most [`MAX_EXTRAPOLATION_US`], then held: a short gap moves on instead of freezing, a long
//! one does not fly off.

use posecast_proto::Transform;
use std::collections::VecDeque;

/// Frames kept per avatar (about a second at 60 Hz).
pub const CAPACITY: usize = 64;

/// Raw transits kept for the delay estimate (10 s at 60 Hz).
pub const WINDOW: usize = 600;

/// The share of recent frames the playout delay waits for: 99.5 % (one frame in 200 may
/// arrive after its turn and is extrapolated over).
pub const QUANTILE: f64 = 0.995;

/// Stamp gaps the frame interval is the longest of.
pub const GAPS: usize = 16;

/// Longest extrapolation past the newest frame, µs.
pub const MAX_EXTRAPOLATION_US: f64 = 100_000.0;

/// Longest playout delay, µs.
pub const MAX_DELAY_US: f64 = 1_000_000.0;

/// How a pose was made from the buffered frames.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Sampled {
    /// Blended between the two received frames around the playout point.
    Interpolated,
    /// Past the newest frame, carried on from the last two (a short gap).
    Extrapolated,
    /// A received frame as is: before the oldest, or a gap longer than extrapolation covers.
    Held,
}

/// Buffered poses of one avatar.
#[derive(Debug, Clone)]
pub struct JitterBuffer {
    frames: VecDeque<(u64, Vec<Transform>)>,
    tick_us: f64,
    /// Raw transits (`arrival − stamp`) of the last frames, µs.
    transits: VecDeque<f64>,
    /// Their [`QUANTILE`].
    transit_p99: f64,
    /// Pushes since it was computed.
    since_sort: u32,
    jitter_us: f64,
    last_transit: Option<f64>,
    /// Gaps between the stamps of the last frames, µs (the server's send interval: a paced
    /// connection gets fewer frames than ticks).
    gaps: VecDeque<f64>,
}

impl JitterBuffer {
    /// A buffer for a stream at `tick_rate` frames per second.
    #[must_use]
    pub fn new(tick_rate: f32) -> Self {
        let rate = if tick_rate.is_finite() && tick_rate > 0.0 {
            f64::from(tick_rate)
        } else {
            60.0
        };
        Self {
            frames: VecDeque::with_capacity(CAPACITY),
            tick_us: 1e6 / rate,
            transits: VecDeque::with_capacity(WINDOW),
            transit_p99: 0.0,
            since_sort: 0,
            jitter_us: 0.0,
            last_transit: None,
            gaps: VecDeque::with_capacity(GAPS),
        }
    }

    /// Adds a pose stamped `server_time_us`, received at `arrival_us` on the client's clock
    /// (any epoch: only differences matter). Out-of-order or duplicate stamps are ignored.
    pub fn push(&mut self, server_time_us: u64, arrival_us: u64, pose: Vec<Transform>) {
        if self
            .frames
            .back()
            .is_some_and(|(t, _)| *t >= server_time_us)
        {
            return;
        }
        let transit = arrival_us as f64 - server_time_us as f64;
        if let Some(last) = self.last_transit {
            // RFC 3550's jitter estimator, for people (the delay uses the percentile).
            self.jitter_us += ((transit - last).abs() - self.jitter_us) / 16.0;
        }
        self.last_transit = Some(transit);
        if self.transits.len() == WINDOW {
            self.transits.pop_front();
        }
        self.transits.push_back(transit);
        // The quantile moves slowly: sorting the window every 16 frames (and at once for a
        // frame later than it) keeps a client of many avatars cheap.
        self.since_sort += 1;
        if self.since_sort >= 16 || transit > self.transit_p99 {
            self.since_sort = 0;
            let mut sorted: Vec<f64> = self.transits.iter().copied().collect();
            sorted.sort_by(f64::total_cmp);
            let rank = ((sorted.len() as f64 * QUANTILE).ceil() as usize).clamp(1, sorted.len());
            self.transit_p99 = sorted[rank - 1];
        }
        if let Some((last, _)) = self.frames.back() {
            if self.gaps.len() == GAPS {
                self.gaps.pop_front();
            }
            self.gaps.push_back((server_time_us - last) as f64);
        }
        if self.frames.len() == CAPACITY {
            self.frames.pop_front();
        }
        self.frames.push_back((server_time_us, pose));
    }

    /// Measured arrival jitter (RFC 3550), microseconds.
    #[must_use]
    pub fn jitter_us(&self) -> f64 {
        self.jitter_us
    }

    /// The current playout delay on the client's clock, µs: the 99.5th percentile of the raw
    /// transits plus one frame interval ([`Self::interval_us`]; see the module doc). Includes the clock offset, so only
    /// `now − delay` is meaningful, as a server time.
    #[must_use]
    pub fn delay_us(&self) -> f64 {
        (self.transit_p99 + self.interval_us()).min(self.transit_floor() + MAX_DELAY_US)
    }

    /// The frames' interval: the longest gap between the stamps of the last [`GAPS`] frames,
    /// at least one tick (a paced stream sends fewer frames than ticks: the frame after the
    /// playout point is then up to one interval after it).
    #[must_use]
    pub fn interval_us(&self) -> f64 {
        self.gaps.iter().copied().fold(self.tick_us, f64::max)
    }

    /// The smallest raw transit in the window (the offset plus the fastest delivery).
    fn transit_floor(&self) -> f64 {
        self.transits.iter().copied().fold(f64::INFINITY, f64::min)
    }

    /// The newest pose and its server time.
    #[must_use]
    pub fn latest(&self) -> Option<(u64, &[Transform])> {
        self.frames.back().map(|(t, p)| (*t, p.as_slice()))
    }

    /// The pose at server time `time_us` and how it was made: the two frames around it
    /// blended ([`Transform::blend`]: shortest-arc slerp of rotations, lerp of translations and
    /// scales); past the newest, carried on from the last two for up to
    /// [`MAX_EXTRAPOLATION_US`], then held; before the oldest, the oldest.
    #[must_use]
    pub fn sample_with_kind(&self, time_us: f64) -> Option<(Vec<Transform>, Sampled)> {
        let first = self.frames.front()?;
        if time_us <= first.0 as f64 {
            return Some((first.1.clone(), Sampled::Held));
        }
        let after = self.frames.iter().position(|(t, _)| *t as f64 >= time_us);
        let Some(i) = after else {
            let n = self.frames.len();
            let (t1, p1) = &self.frames[n - 1];
            if n < 2 || time_us - *t1 as f64 > MAX_EXTRAPOLATION_US {
                return Some((p1.clone(), Sampled::Held));
            }
            let (t0, p0) = &self.frames[n - 2];
            let w = ((time_us - *t0 as f64) / (*t1 as f64 - *t0 as f64)) as f32;
            let pose = p0.iter().zip(p1).map(|(a, b)| a.blend(b, w)).collect();
            return Some((pose, Sampled::Extrapolated));
        };
        let (t1, p1) = &self.frames[i];
        let (t0, p0) = &self.frames[i - 1];
        let w = ((time_us - *t0 as f64) / (*t1 as f64 - *t0 as f64)) as f32;
        let pose = p0.iter().zip(p1).map(|(a, b)| a.blend(b, w)).collect();
        Some((pose, Sampled::Interpolated))
    }

    /// [`Self::sample_with_kind`], the pose only.
    #[must_use]
    pub fn sample(&self, time_us: f64) -> Option<Vec<Transform>> {
        self.sample_with_kind(time_us).map(|(pose, _)| pose)
    }

    /// The pose to show at client time `now_us`: [`Self::sample`] at server time
    /// `now − delay` ([`Self::delay_us`]).
    #[must_use]
    pub fn playout(&self, now_us: u64) -> Option<Vec<Transform>> {
        self.sample(self.playout_time(now_us))
    }

    /// The server time shown at client time `now_us`.
    #[must_use]
    pub fn playout_time(&self, now_us: u64) -> f64 {
        now_us as f64 - self.delay_us()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::{Quat, Vec3};

    fn pose(angle: f32, x: f32) -> Vec<Transform> {
        vec![Transform {
            translation: Vec3::X * x,
            rotation: Quat::from_rotation_y(angle),
            scale: Vec3::ONE,
        }]
    }

    #[test]
    fn interpolates_between_bracketing_frames_and_clamps_outside() {
        let mut b = JitterBuffer::new(60.0);
        b.push(1_000_000, 1_000_100, pose(0.0, 0.0));
        b.push(1_016_000, 1_016_100, pose(0.4, 1.0));
        let mid = b.sample(1_008_000.0).unwrap();
        assert!((mid[0].translation.x - 0.5).abs() < 1e-6);
        assert!(mid[0].rotation.angle_between(Quat::from_rotation_y(0.2)) < 1e-5);
        assert_eq!(b.sample(0.0).unwrap(), pose(0.0, 0.0));
        assert_eq!(b.sample(9e9).unwrap(), pose(0.4, 1.0));
        // Steady arrival 100 µs after the stamp: no jitter, delay is that transit and a tick.
        assert!(b.jitter_us() < 1e-9);
        assert!((b.delay_us() - (100.0 + 1e6 / 60.0)).abs() < 1e-6);
    }

    #[test]
    fn delay_grows_with_irregular_arrival() {
        let mut b = JitterBuffer::new(60.0);
        for i in 0..50u64 {
            let wobble = if i % 2 == 0 { 0 } else { 8_000 };
            b.push(i * 16_667, i * 16_667 + 500 + wobble, pose(0.0, 0.0));
        }
        assert!(b.jitter_us() > 4_000.0, "jitter {}", b.jitter_us());
        // The late half arrives 8.5 ms after its stamp: the delay covers it, plus the frames'
        // interval (16,667 µs between stamps).
        assert!((b.delay_us() - (8_500.0 + 16_667.0)).abs() < 1e-6);
    }

    /// A link with one-way `delay` ± `jitter` (uniform), and TCP loss: a lost segment is
    /// resent a round trip and three ticks later (fast retransmit), and every frame behind it
    /// waits for it (head-of-line blocking). Frames at 60 Hz for `seconds`; returns each
    /// frame's (stamp, arrival), µs, arrivals in order.
    fn link(delay: f64, jitter: f64, loss: f64, seconds: f64, seed: u64) -> Vec<(u64, u64)> {
        let mut state = seed;
        let mut random = move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        let tick = 1e6 / 60.0;
        let mut out = Vec::new();
        let mut previous = 0.0f64;
        // The server clock is 3.7 s ahead of the client's: only differences may matter.
        let offset = 3_700_000.0;
        for i in 0..(seconds * 60.0) as u64 {
            let sent = 10_000_000.0 + i as f64 * tick;
            let mut arrival = sent + delay + (random() * 2.0 - 1.0) * jitter;
            if random() < loss {
                arrival += 2.0 * delay + 3.0 * tick;
            }
            arrival = arrival.max(previous);
            previous = arrival;
            out.push(((sent + offset) as u64, arrival as u64));
        }
        out
    }

    /// Renders `frames` at 60 Hz (half a tick out of phase) through the buffer after a
    /// 2 s warm-up; returns the shares of interpolated, extrapolated and held poses and the
    /// oldest shown pose's age past the playout delay, µs.
    fn render(frames: &[(u64, u64)]) -> (f64, f64, f64, f64) {
        let mut b = JitterBuffer::new(60.0);
        let tick = 1e6 / 60.0;
        let start = frames[0].1 as f64 + 2e6;
        let end = frames[frames.len() - 1].1 as f64;
        let (mut counts, mut worst) = ([0usize; 3], 0.0f64);
        let mut next = 0;
        let mut now = frames[0].1 as f64 + tick / 2.0;
        while now < end {
            while next < frames.len() && frames[next].1 as f64 <= now {
                let (stamp, arrival) = frames[next];
                b.push(stamp, arrival, pose(0.0, stamp as f32));
                next += 1;
            }
            if now >= start {
                let t = b.playout_time(now as u64);
                let (shown, kind) = b.sample_with_kind(t).unwrap();
                counts[kind as usize] += 1;
                // The shown pose's stamp is its x translation: how far behind the playout
                // point is it?
                worst = worst.max(t - f64::from(shown[0].translation.x));
            }
            now += tick;
        }
        let total = counts.iter().sum::<usize>() as f64;
        (
            counts[0] as f64 / total,
            counts[1] as f64 / total,
            counts[2] as f64 / total,
            worst,
        )
    }

    #[test]
    fn on_a_delayed_jittery_link_with_loss_nearly_every_pose_is_interpolated() {
        let tick = 1e6 / 60.0;
        for (loss, max_held) in [(0.0, 0.0), (0.01, 0.01), (0.05, 0.05)] {
            let frames = link(25_000.0, 10_000.0, loss, 60.0, 7 + (loss * 1000.0) as u64);
            let (interpolated, extrapolated, held, worst) = render(&frames);
            eprintln!(
                "25 ± 10 ms, {:.0} % loss: interpolated {:.2} %, extrapolated {:.2} %, held {:.2} %",
                loss * 100.0,
                interpolated * 100.0,
                extrapolated * 100.0,
                held * 100.0
            );
            if loss <= 0.01 {
                assert!(interpolated >= 0.99, "{loss}: {interpolated}");
            }
            assert!(held <= max_held, "{loss}: {held} held");
            // Never older than the playout point allows: a held pose is at most the
            // extrapolation bound behind it, an interpolated one not at all.
            assert!(worst <= MAX_EXTRAPOLATION_US + tick, "{worst}");
        }
    }

    #[test]
    fn a_paced_stream_is_interpolated_too() {
        // 5 frames a second (a paced connection at 60 ticks/s), 30 ms in transit, rendered at
        // 60 Hz: the playout point waits one frame interval (200 ms), so the next frame has
        // always arrived.
        let frames: Vec<(u64, u64)> = (0..100u64)
            .map(|i| (10_000_000 + i * 200_000, 10_030_000 + i * 200_000))
            .collect();
        let mut b = JitterBuffer::new(60.0);
        let (mut interpolated, mut other) = (0, 0);
        let mut next = 0;
        let mut now = frames[0].1 as f64;
        while now < frames[frames.len() - 1].1 as f64 {
            while next < frames.len() && frames[next].1 as f64 <= now {
                b.push(frames[next].0, frames[next].1, pose(0.0, 0.0));
                next += 1;
            }
            if now >= frames[0].1 as f64 + 2e6 {
                match b.sample_with_kind(b.playout_time(now as u64)).unwrap().1 {
                    Sampled::Interpolated => interpolated += 1,
                    _ => other += 1,
                }
            }
            now += 1e6 / 60.0;
        }
        assert!((b.interval_us() - 200_000.0).abs() < 1.0);
        assert_eq!(other, 0, "{interpolated} interpolated");
    }

    #[test]
    fn a_short_gap_is_extrapolated_a_long_one_held() {
        let mut b = JitterBuffer::new(60.0);
        b.push(0, 0, pose(0.0, 0.0));
        b.push(16_667, 16_667, pose(0.1, 1.0));
        let (p, kind) = b.sample_with_kind(33_333.0).unwrap();
        assert_eq!(kind, Sampled::Extrapolated);
        assert!((p[0].translation.x - 2.0).abs() < 1e-3);
        assert!(p[0].rotation.angle_between(Quat::from_rotation_y(0.2)) < 1e-4);
        let (p, kind) = b
            .sample_with_kind(16_667.0 + MAX_EXTRAPOLATION_US + 1.0)
            .unwrap();
        assert_eq!(kind, Sampled::Held);
        assert_eq!(p, pose(0.1, 1.0));
    }
}
