//! Jitter buffer: keeps an avatar's recent poses by server time and gives an interpolated pose
//! at a render time a little in the past, so irregular arrival does not show as stutter.
//!
//! The playout delay adapts to the measured jitter of arrival (RFC 3550's estimator,
//! `J += (|D| − J) / 16` where `D` is the change in transit time between consecutive frames):
//! `delay = one tick + 3 J`, clamped to `[one tick, 500 ms]`.

use posecast_proto::Transform;
use std::collections::VecDeque;

/// Frames kept per avatar (about a second at 60 Hz).
pub const CAPACITY: usize = 64;

/// Buffered poses of one avatar.
#[derive(Debug, Clone)]
pub struct JitterBuffer {
    frames: VecDeque<(u64, Vec<Transform>)>,
    tick_us: f64,
    jitter_us: f64,
    last_transit: Option<f64>,
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
            jitter_us: 0.0,
            last_transit: None,
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
            self.jitter_us += ((transit - last).abs() - self.jitter_us) / 16.0;
        }
        self.last_transit = Some(transit);
        if self.frames.len() == CAPACITY {
            self.frames.pop_front();
        }
        self.frames.push_back((server_time_us, pose));
    }

    /// Measured arrival jitter, microseconds.
    #[must_use]
    pub fn jitter_us(&self) -> f64 {
        self.jitter_us
    }

    /// The current playout delay, microseconds.
    #[must_use]
    pub fn delay_us(&self) -> f64 {
        (self.tick_us + 3.0 * self.jitter_us).clamp(self.tick_us, 500_000.0)
    }

    /// The newest pose and its server time.
    #[must_use]
    pub fn latest(&self) -> Option<(u64, &[Transform])> {
        self.frames.back().map(|(t, p)| (*t, p.as_slice()))
    }

    /// The pose at server time `time_us`: the two frames around it blended
    /// ([`Transform::blend`]: shortest-arc slerp of rotations, lerp of translations and
    /// scales), the oldest frame before the buffer, the newest after it (no extrapolation).
    #[must_use]
    pub fn sample(&self, time_us: f64) -> Option<Vec<Transform>> {
        let first = self.frames.front()?;
        if time_us <= first.0 as f64 {
            return Some(first.1.clone());
        }
        let after = self.frames.iter().position(|(t, _)| *t as f64 >= time_us);
        let Some(i) = after else {
            return self.frames.back().map(|(_, p)| p.clone());
        };
        let (t1, p1) = &self.frames[i];
        let (t0, p0) = &self.frames[i - 1];
        let w = ((time_us - *t0 as f64) / (*t1 as f64 - *t0 as f64)) as f32;
        Some(p0.iter().zip(p1).map(|(a, b)| a.blend(b, w)).collect())
    }

    /// The pose to show at client time `now_us`, given the estimated server clock offset
    /// (`server = client + offset`): [`Self::sample`] at `now + offset − delay`.
    #[must_use]
    pub fn playout(&self, now_us: u64, offset_us: f64) -> Option<Vec<Transform>> {
        self.sample(now_us as f64 + offset_us - self.delay_us())
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
        // Steady arrival: no jitter, delay is one tick.
        assert!(b.jitter_us() < 1e-9);
        assert!((b.delay_us() - 1e6 / 60.0).abs() < 1e-6);
    }

    #[test]
    fn delay_grows_with_irregular_arrival() {
        let mut b = JitterBuffer::new(60.0);
        for i in 0..50u64 {
            let wobble = if i % 2 == 0 { 0 } else { 8_000 };
            b.push(i * 16_667, i * 16_667 + 500 + wobble, pose(0.0, 0.0));
        }
        assert!(b.jitter_us() > 4_000.0, "jitter {}", b.jitter_us());
        assert!(b.delay_us() > 1e6 / 60.0 + 12_000.0);
    }
}
