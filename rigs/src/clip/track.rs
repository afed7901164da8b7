//! Key tracks: times with values, sampled with step, linear or glTF cubic-spline
//! interpolation. Used for glTF channels, BVH frames and any per-joint quaternion data.

use glam::{Quat, Vec3};

use super::ClipError;

/// How values between two keys are found.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Interpolation {
    /// The earlier key's value holds until the next key.
    Step,
    /// Linear for vectors; shortest-path spherical linear (slerp) for rotations.
    Linear,
    /// glTF `CUBICSPLINE`: Hermite with an in- and out-tangent per key, tangents in value units
    /// per second (so they are scaled by the key interval when evaluated).
    CubicSpline,
}

/// A value a [`Track`] can hold.
pub trait TrackValue: Copy + PartialEq + std::fmt::Debug {
    /// Interpolation between `a` and `b` at `u` in [0, 1].
    fn interpolate(a: Self, b: Self, u: f32) -> Self;
    /// The cubic Hermite `h00 p0 + h10 Δ m0 + h01 p1 + h11 Δ m1` over an interval of `dt`.
    fn hermite(p0: Self, m0: Self, p1: Self, m1: Self, u: f32, dt: f32) -> Self;
    /// Whether every component is finite.
    fn finite(&self) -> bool;
    /// Whether two values mean the same thing (for constant-track detection).
    fn same(a: Self, b: Self) -> bool;
    /// Whether the value is zero (tangents of a constant cubic track).
    fn is_zero(&self) -> bool;
    /// Puts a value in canonical form (unit length for rotations).
    fn canonical(self) -> Self {
        self
    }
}

fn hermite_basis(u: f32) -> [f32; 4] {
    let u2 = u * u;
    let u3 = u2 * u;
    [
        2.0 * u3 - 3.0 * u2 + 1.0,
        u3 - 2.0 * u2 + u,
        -2.0 * u3 + 3.0 * u2,
        u3 - u2,
    ]
}

impl TrackValue for Vec3 {
    fn interpolate(a: Self, b: Self, u: f32) -> Self {
        a + (b - a) * u
    }
    fn hermite(p0: Self, m0: Self, p1: Self, m1: Self, u: f32, dt: f32) -> Self {
        let [h00, h10, h01, h11] = hermite_basis(u);
        p0 * h00 + m0 * (h10 * dt) + p1 * h01 + m1 * (h11 * dt)
    }
    fn finite(&self) -> bool {
        self.is_finite()
    }
    fn same(a: Self, b: Self) -> bool {
        a == b
    }
    fn is_zero(&self) -> bool {
        *self == Vec3::ZERO
    }
}

impl TrackValue for f32 {
    fn interpolate(a: Self, b: Self, u: f32) -> Self {
        a + (b - a) * u
    }
    fn hermite(p0: Self, m0: Self, p1: Self, m1: Self, u: f32, dt: f32) -> Self {
        let [h00, h10, h01, h11] = hermite_basis(u);
        p0 * h00 + m0 * (h10 * dt) + p1 * h01 + m1 * (h11 * dt)
    }
    fn finite(&self) -> bool {
        self.is_finite()
    }
    fn same(a: Self, b: Self) -> bool {
        a == b
    }
    fn is_zero(&self) -> bool {
        *self == 0.0
    }
}

/// Shortest-path slerp: `b` is negated when `a · b < 0`, and nearly parallel rotations fall
/// back to normalised lerp (where slerp's `sin θ` denominator loses precision).
#[must_use]
pub fn slerp_shortest(a: Quat, b: Quat, u: f32) -> Quat {
    let mut d = a.dot(b);
    let b = if d < 0.0 {
        d = -d;
        -b
    } else {
        b
    };
    if d > 0.9995 {
        return (a + (b - a) * u).normalize();
    }
    let theta = d.clamp(-1.0, 1.0).acos();
    let s = theta.sin();
    let wa = ((1.0 - u) * theta).sin() / s;
    let wb = (u * theta).sin() / s;
    (a * wa + b * wb).normalize()
}

/// `q / |q|`, or `fallback` when `q` is zero or not finite.
fn normalize_or(q: Quat, fallback: Quat) -> Quat {
    let len = q.length();
    if len.is_finite() && len > 1e-12 {
        q / len
    } else {
        fallback
    }
}

impl TrackValue for Quat {
    fn interpolate(a: Self, b: Self, u: f32) -> Self {
        slerp_shortest(a, b, u)
    }
    fn hermite(p0: Self, m0: Self, p1: Self, m1: Self, u: f32, dt: f32) -> Self {
        let [h00, h10, h01, h11] = hermite_basis(u);
        let q = p0 * h00 + m0 * (h10 * dt) + p1 * h01 + m1 * (h11 * dt);
        // glTF: the result of a cubic-spline rotation is normalised.
        normalize_or(q, p0)
    }
    fn finite(&self) -> bool {
        self.is_finite()
    }
    fn same(a: Self, b: Self) -> bool {
        a == b || a == -b
    }
    fn is_zero(&self) -> bool {
        *self == Quat::from_xyzw(0.0, 0.0, 0.0, 0.0)
    }
    fn canonical(self) -> Self {
        normalize_or(self, Quat::IDENTITY)
    }
}

/// Keys at strictly increasing times. A track whose values are all the same is stored as one
/// key. Before the first key and after the last the end values hold (clamping).
#[derive(Clone, Debug, PartialEq)]
pub struct Track<T> {
    interpolation: Interpolation,
    times: Vec<f32>,
    values: Vec<T>,
    /// Cubic-spline only: (in, out) tangent per key, per second.
    tangents: Vec<(T, T)>,
}

impl<T: TrackValue> Track<T> {
    /// Builds a track. For [`Interpolation::CubicSpline`] `values` holds three entries per key in
    /// glTF order (in-tangent, value, out-tangent); otherwise one per key. Rotations are
    /// normalised. Errors on empty, non-finite, unordered or mismatched input.
    pub fn new(
        interpolation: Interpolation,
        times: Vec<f32>,
        values: Vec<T>,
    ) -> Result<Self, ClipError> {
        if times.is_empty() {
            return Err(ClipError::NoKeys);
        }
        let per_key = if interpolation == Interpolation::CubicSpline {
            3
        } else {
            1
        };
        if values.len() != times.len() * per_key {
            return Err(ClipError::KeyCount {
                times: times.len(),
                values: values.len(),
                per_key,
            });
        }
        check_times(&times)?;
        if let Some(key) = values.iter().position(|v| !v.finite()) {
            return Err(ClipError::NotFinite { key: key / per_key });
        }
        let (values, tangents) = if per_key == 3 {
            let mut vals = Vec::with_capacity(times.len());
            let mut tans = Vec::with_capacity(times.len());
            for c in values.chunks_exact(3) {
                tans.push((c[0], c[2]));
                vals.push(c[1].canonical());
            }
            (vals, tans)
        } else {
            (values.into_iter().map(T::canonical).collect(), Vec::new())
        };
        let mut track = Self {
            interpolation,
            times,
            values,
            tangents,
        };
        track.collapse_if_constant();
        Ok(track)
    }

    /// A track that holds `value` at all times.
    #[must_use]
    pub fn constant(value: T) -> Self {
        Self {
            interpolation: Interpolation::Step,
            times: vec![0.0],
            values: vec![value.canonical()],
            tangents: Vec::new(),
        }
    }

    fn collapse_if_constant(&mut self) {
        let first = self.values[0];
        let constant = self.values.iter().all(|&v| T::same(v, first))
            && self
                .tangents
                .iter()
                .all(|(a, b)| a.is_zero() && b.is_zero());
        if constant && self.times.len() > 1 {
            let t0 = self.times[0];
            *self = Self::constant(first);
            self.times[0] = t0;
        }
    }

    /// Whether the track holds one value for all time.
    #[must_use]
    pub fn is_constant(&self) -> bool {
        self.times.len() == 1
    }

    /// How values between keys are computed.
    #[must_use]
    pub fn interpolation(&self) -> Interpolation {
        self.interpolation
    }

    /// Key times in seconds.
    #[must_use]
    pub fn times(&self) -> &[f32] {
        &self.times
    }

    /// Key values (without cubic-spline tangents).
    #[must_use]
    pub fn values(&self) -> &[T] {
        &self.values
    }

    /// Cubic-spline only: `(in, out)` tangent per key, value units per second; empty for step
    /// and linear tracks.
    #[must_use]
    pub fn tangents(&self) -> &[(T, T)] {
        &self.tangents
    }

    /// First and last key times.
    #[must_use]
    pub fn time_range(&self) -> (f32, f32) {
        (self.times[0], self.times[self.times.len() - 1])
    }

    /// The value at `time`, starting the key search at `cursor` and leaving it on the segment
    /// used, so forward playback finds its key in O(1). Any cursor gives the same value.
    #[inline]
    pub fn sample_from(&self, time: f32, cursor: &mut usize) -> T {
        let n = self.times.len();
        let last = n - 1;
        if n == 1 || time.is_nan() || time <= self.times[0] {
            return self.values[0];
        }
        if time >= self.times[last] {
            return self.values[last];
        }
        let k = find_segment(&self.times, time, cursor);
        let (t0, t1) = (self.times[k], self.times[k + 1]);
        let dt = t1 - t0;
        let u = ((time - t0) / dt).clamp(0.0, 1.0);
        match self.interpolation {
            Interpolation::Step => self.values[k],
            Interpolation::Linear => T::interpolate(self.values[k], self.values[k + 1], u),
            Interpolation::CubicSpline => T::hermite(
                self.values[k],
                self.tangents[k].1,
                self.values[k + 1],
                self.tangents[k + 1].0,
                u,
                dt,
            ),
        }
    }

    /// The value at `time` (random access).
    #[must_use]
    pub fn sample(&self, time: f32) -> T {
        let mut cursor = 0;
        self.sample_from(time, &mut cursor)
    }
}

/// Checks that key times are finite and strictly increasing.
pub(crate) fn check_times(times: &[f32]) -> Result<(), ClipError> {
    if let Some(key) = times.iter().position(|t| !t.is_finite()) {
        return Err(ClipError::NotFinite { key });
    }
    if let Some(key) = times.windows(2).position(|w| w[1] <= w[0]) {
        return Err(ClipError::Unordered { key: key + 1 });
    }
    Ok(())
}

/// The `k` with `times[k] ≤ time < times[k + 1]`, for `times[0] < time < times[last]`.
/// Tries the cursor's segment and the next one; past them, gallops forwards from the cursor
/// (playback at a lower rate than the keys skips a few per call) and binary-searches the
/// bracket found; before the cursor, binary-searches all keys. Every path finds the same `k`.
#[inline]
pub(crate) fn find_segment(times: &[f32], time: f32, cursor: &mut usize) -> usize {
    let n = times.len();
    let within = |k: usize| k + 1 < n && times[k] <= time && time < times[k + 1];
    let c = *cursor;
    let k = if within(c) {
        c
    } else if within(c + 1) {
        c + 1
    } else if c + 1 < n && times[c] <= time {
        // times[lo] ≤ time; the first key after `time` is in (lo, hi], or there is none.
        let (mut lo, mut step) = (c, 1);
        let mut hi = c + 1;
        while hi < n && times[hi] <= time {
            lo = hi;
            step *= 2;
            hi = lo + step;
        }
        let hi = hi.min(n);
        (lo + times[lo + 1..hi].partition_point(|&t| t <= time)).min(n.saturating_sub(2))
    } else {
        // First index whose time is > `time`, minus one.
        times
            .partition_point(|&t| t <= time)
            .saturating_sub(1)
            .min(n.saturating_sub(2))
    };
    *cursor = k;
    k
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn linear_vec3_and_clamping() {
        let t = Track::new(
            Interpolation::Linear,
            vec![1.0, 2.0, 4.0],
            vec![Vec3::ZERO, Vec3::X, Vec3::new(3.0, 0.0, 0.0)],
        )
        .unwrap();
        assert_eq!(t.sample(0.0), Vec3::ZERO);
        assert_eq!(t.sample(1.5), Vec3::new(0.5, 0.0, 0.0));
        assert_eq!(t.sample(3.0), Vec3::new(2.0, 0.0, 0.0));
        assert_eq!(t.sample(9.0), Vec3::new(3.0, 0.0, 0.0));
    }

    #[test]
    fn step_holds_earlier_key() {
        let t = Track::new(
            Interpolation::Step,
            vec![0.0, 1.0],
            vec![Vec3::ZERO, Vec3::Y],
        )
        .unwrap();
        assert_eq!(t.sample(0.999), Vec3::ZERO);
        assert_eq!(t.sample(1.0), Vec3::Y);
    }

    #[test]
    fn slerp_takes_the_short_way() {
        let a = Quat::from_rotation_y(0.1);
        let b = -Quat::from_rotation_y(0.5); // same rotation as +, opposite hemisphere
        let t = Track::new(Interpolation::Linear, vec![0.0, 1.0], vec![a, b]).unwrap();
        let mid = t.sample(0.5);
        assert!(mid.dot(Quat::from_rotation_y(0.3)).abs() > 1.0 - 1e-6);
        // Exactly by the slerp formula with θ = 0.2 rad between the halves.
        let far = Track::new(
            Interpolation::Linear,
            vec![0.0, 1.0],
            vec![Quat::IDENTITY, Quat::from_rotation_z(2.0)],
        )
        .unwrap();
        assert!(far.sample(0.25).dot(Quat::from_rotation_z(0.5)).abs() > 1.0 - 1e-6);
    }

    #[test]
    fn cubic_spline_scales_tangents_by_interval() {
        // p(t) = t² on [0, 2]: p0 = 0, p1 = 4, p'(0) = 0, p'(2) = 4 per second.
        let v = |x: f32| Vec3::new(x, 0.0, 0.0);
        let t = Track::new(
            Interpolation::CubicSpline,
            vec![0.0, 2.0],
            vec![v(0.0), v(0.0), v(0.0), v(4.0), v(4.0), v(0.0)],
        )
        .unwrap();
        for x in [0.25f32, 0.5, 1.0, 1.5] {
            assert!((t.sample(x).x - x * x).abs() < 1e-5, "{x}");
        }
    }

    #[test]
    fn constant_tracks_collapse() {
        let t = Track::new(Interpolation::Linear, vec![0.0, 1.0, 2.0], vec![Vec3::Y; 3]).unwrap();
        assert!(t.is_constant());
        assert_eq!(t.sample(1.5), Vec3::Y);
        let q = Track::new(
            Interpolation::Linear,
            vec![0.0, 1.0],
            vec![Quat::from_rotation_x(1.0), -Quat::from_rotation_x(1.0)],
        )
        .unwrap();
        assert!(q.is_constant());
    }

    #[test]
    fn rejects_bad_keys() {
        let e = Track::new(Interpolation::Linear, vec![0.0, 0.0], vec![Vec3::ZERO; 2]);
        assert_eq!(e, Err(ClipError::Unordered { key: 1 }));
        let e = Track::new(Interpolation::CubicSpline, vec![0.0], vec![Vec3::ZERO; 2]);
        assert!(matches!(e, Err(ClipError::KeyCount { .. })));
        let e = Track::<Vec3>::new(Interpolation::Linear, vec![], vec![]);
        assert_eq!(e, Err(ClipError::NoKeys));
        let e = Track::new(Interpolation::Linear, vec![0.0], vec![Vec3::NAN]);
        assert!(matches!(e, Err(ClipError::NotFinite { .. })));
    }

    #[test]
    fn galloping_forwards_finds_the_binary_search_segment() {
        // Keys at 120 Hz read at 60 Hz and slower: the cursor skips 2 to 40 keys per call.
        let times: Vec<f32> = (0..500).map(|i| i as f32 / 120.0).collect();
        for skip in [2.0f32, 2.7, 5.0, 17.3, 40.0] {
            let mut cursor = 0;
            let mut t = 0.001;
            while t < times[times.len() - 1] {
                let expected = times.partition_point(|&x| x <= t) - 1;
                assert_eq!(
                    find_segment(&times, t, &mut cursor),
                    expected,
                    "t = {t}, skip {skip}"
                );
                t += skip / 120.0;
            }
        }
    }

    #[test]
    fn cursor_gives_same_result_as_random_access() {
        let times: Vec<f32> = (0..50).map(|i| i as f32 * 0.1 + 0.05).collect();
        let values: Vec<Vec3> = (0..50).map(|i| Vec3::splat((i as f32).sin())).collect();
        let t = Track::new(Interpolation::Linear, times, values).unwrap();
        let mut cursor = 0;
        for i in 0..700 {
            let x = (i as f32 * 0.37).sin() * 3.0 + 2.5;
            assert_eq!(t.sample_from(x, &mut cursor), t.sample(x));
        }
    }
}
