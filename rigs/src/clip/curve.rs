//! CSE169 animation curves: one scalar DOF as cubic Hermite keys with tangent rules and
//! extrapolation modes (the `.anim` format, Rotenberg's "Channels" notes).

use super::ClipError;
use super::track::{check_times, find_segment};

/// What a curve does outside its first and last key.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Extrapolation {
    /// Holds the end key's value.
    Constant,
    /// Continues along the end key's tangent.
    Linear,
    /// Repeats the key span.
    Cycle,
    /// Repeats the key span, each repetition shifted by `last − first` value.
    CycleOffset,
    /// Repeats the key span alternately forwards and backwards.
    Bounce,
}

/// How a key's tangent (slope, value units per second) is chosen.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Tangent {
    /// Zero slope.
    Flat,
    /// Slope towards the neighbouring key on that side (one-sided at the ends).
    Linear,
    /// `(p_next − p_prev) / (t_next − t_prev)`; the linear rule at the first and last key.
    Smooth,
    /// An explicit slope.
    Value(f32),
}

/// One key as written in a `.anim` file.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Key {
    /// Key time, seconds.
    pub time: f32,
    /// The DOF's value at the key (radians for a rotation, file units for a translation).
    pub value: f32,
    /// The rule for the slope arriving at the key.
    pub tangent_in: Tangent,
    /// The rule for the slope leaving the key.
    pub tangent_out: Tangent,
}

/// A scalar Hermite curve with resolved tangents.
#[derive(Clone, Debug, PartialEq)]
pub struct Curve {
    times: Vec<f32>,
    values: Vec<f32>,
    /// Resolved slopes per key (per second).
    slope_in: Vec<f32>,
    slope_out: Vec<f32>,
    before: Extrapolation,
    after: Extrapolation,
}

impl Curve {
    /// Resolves the tangent rules of `keys` (strictly increasing times) into slopes.
    pub fn new(
        keys: &[Key],
        before: Extrapolation,
        after: Extrapolation,
    ) -> Result<Self, ClipError> {
        if keys.is_empty() {
            return Err(ClipError::NoKeys);
        }
        let times: Vec<f32> = keys.iter().map(|k| k.time).collect();
        check_times(&times)?;
        let values: Vec<f32> = keys.iter().map(|k| k.value).collect();
        let bad = |t: &Tangent| matches!(t, Tangent::Value(v) if !v.is_finite());
        if let Some(key) = keys
            .iter()
            .position(|k| !k.value.is_finite() || bad(&k.tangent_in) || bad(&k.tangent_out))
        {
            return Err(ClipError::NotFinite { key });
        }
        let n = keys.len();
        let slope = |a: usize, b: usize| (values[b] - values[a]) / (times[b] - times[a]);
        // Slope of the segment before and after key k, when there is one.
        let prev = |k: usize| (k > 0).then(|| slope(k - 1, k));
        let next = |k: usize| (k + 1 < n).then(|| slope(k, k + 1));
        let resolve = |k: usize, rule: Tangent, incoming: bool| -> f32 {
            match rule {
                Tangent::Flat => 0.0,
                Tangent::Value(v) => v,
                Tangent::Linear => {
                    let (near, far) = if incoming {
                        (prev(k), next(k))
                    } else {
                        (next(k), prev(k))
                    };
                    near.or(far).unwrap_or(0.0)
                }
                Tangent::Smooth => {
                    if k > 0 && k + 1 < n {
                        slope(k - 1, k + 1)
                    } else {
                        // Linear rule at the ends: the one neighbouring segment.
                        next(k).or(prev(k)).unwrap_or(0.0)
                    }
                }
            }
        };
        let slope_in = (0..n)
            .map(|k| resolve(k, keys[k].tangent_in, true))
            .collect();
        let slope_out = (0..n)
            .map(|k| resolve(k, keys[k].tangent_out, false))
            .collect();
        Ok(Self {
            times,
            values,
            slope_in,
            slope_out,
            before,
            after,
        })
    }

    /// A curve with one value everywhere.
    #[must_use]
    pub fn constant(value: f32) -> Self {
        Self {
            times: vec![0.0],
            values: vec![value],
            slope_in: vec![0.0],
            slope_out: vec![0.0],
            before: Extrapolation::Constant,
            after: Extrapolation::Constant,
        }
    }

    /// Whether the value never changes (a single key without linear extrapolation, or all keys
    /// equal with zero slopes and no linear extrapolation).
    #[must_use]
    pub fn is_constant(&self) -> bool {
        let v0 = self.values[0];
        self.values.iter().all(|&v| v == v0)
            && self
                .slope_in
                .iter()
                .chain(&self.slope_out)
                .all(|&s| s == 0.0)
    }

    /// Key times in seconds.
    #[must_use]
    pub fn times(&self) -> &[f32] {
        &self.times
    }

    /// Key values.
    #[must_use]
    pub fn values(&self) -> &[f32] {
        &self.values
    }

    /// Resolved (in, out) slopes per key.
    #[must_use]
    pub fn slopes(&self) -> (&[f32], &[f32]) {
        (&self.slope_in, &self.slope_out)
    }

    /// How the curve continues before its first key and after its last.
    #[must_use]
    pub fn extrapolation(&self) -> (Extrapolation, Extrapolation) {
        (self.before, self.after)
    }

    /// The value at `time` (random access).
    #[must_use]
    pub fn evaluate(&self, time: f32) -> f32 {
        let mut cursor = 0;
        self.evaluate_from(time, &mut cursor)
    }

    /// The value at `time`, starting the key search at `cursor` (see [`super::Track::sample_from`]).
    pub fn evaluate_from(&self, time: f32, cursor: &mut usize) -> f32 {
        let n = self.times.len();
        let (t0, t1) = (self.times[0], self.times[n - 1]);
        let (p0, p1) = (self.values[0], self.values[n - 1]);
        if time.is_nan() {
            return p0;
        }
        let mode = if time < t0 {
            self.before
        } else if time > t1 {
            self.after
        } else {
            return self.inside(time, cursor);
        };
        let period = t1 - t0;
        match mode {
            Extrapolation::Constant => {
                if time < t0 {
                    p0
                } else {
                    p1
                }
            }
            Extrapolation::Linear => {
                if time < t0 {
                    p0 + self.slope_in[0] * (time - t0)
                } else {
                    p1 + self.slope_out[n - 1] * (time - t1)
                }
            }
            _ if period <= 0.0 => p0,
            Extrapolation::Cycle => {
                let cycles = ((time - t0) / period).floor();
                self.inside(wrap_into(time - cycles * period, t0, t1), cursor)
            }
            Extrapolation::CycleOffset => {
                let cycles = ((time - t0) / period).floor();
                let local = wrap_into(time - cycles * period, t0, t1);
                self.inside(local, cursor) + cycles * (p1 - p0)
            }
            Extrapolation::Bounce => {
                let phase = (time - t0) / period;
                let cycles = phase.floor();
                let frac = (phase - cycles) * period;
                // Even repetitions run forwards, odd ones backwards.
                let local = if (cycles as i64).rem_euclid(2) == 0 {
                    t0 + frac
                } else {
                    t1 - frac
                };
                self.inside(local.clamp(t0, t1), cursor)
            }
        }
    }

    /// Hermite evaluation for `t0 ≤ time ≤ t1`:
    /// `p(u) = h00 p_k + h10 Δ v_out,k + h01 p_{k+1} + h11 Δ v_in,k+1`, `u = (t − t_k) / Δ`.
    fn inside(&self, time: f32, cursor: &mut usize) -> f32 {
        let n = self.times.len();
        if n == 1 || time <= self.times[0] {
            return self.values[0];
        }
        if time >= self.times[n - 1] {
            return self.values[n - 1];
        }
        let k = find_segment(&self.times, time, cursor);
        let dt = self.times[k + 1] - self.times[k];
        let u = ((time - self.times[k]) / dt).clamp(0.0, 1.0);
        let (u2, u3) = (u * u, u * u * u);
        let h00 = 2.0 * u3 - 3.0 * u2 + 1.0;
        let h10 = u3 - 2.0 * u2 + u;
        let h01 = -2.0 * u3 + 3.0 * u2;
        let h11 = u3 - u2;
        h00 * self.values[k]
            + h10 * dt * self.slope_out[k]
            + h01 * self.values[k + 1]
            + h11 * dt * self.slope_in[k + 1]
    }
}

/// Guards the float rounding of `time − cycles · period` so the result stays in `[t0, t1]`.
fn wrap_into(local: f32, t0: f32, t1: f32) -> f32 {
    local.clamp(t0, t1)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn key(time: f32, value: f32, rule: Tangent) -> Key {
        Key {
            time,
            value,
            tangent_in: rule,
            tangent_out: rule,
        }
    }

    #[test]
    fn tangent_rules() {
        let keys = [
            key(0.0, 0.0, Tangent::Smooth),
            key(1.0, 1.0, Tangent::Smooth),
            key(3.0, 5.0, Tangent::Linear),
            key(4.0, 5.0, Tangent::Flat),
        ];
        let c = Curve::new(&keys, Extrapolation::Constant, Extrapolation::Constant).unwrap();
        let (i, o) = c.slopes();
        assert_eq!((i[0], o[0]), (1.0, 1.0)); // smooth at an end = linear rule
        assert_eq!((i[1], o[1]), (5.0 / 3.0, 5.0 / 3.0)); // (5 − 0) / (3 − 0)
        assert_eq!((i[2], o[2]), (2.0, 0.0)); // linear: incoming 4/2, outgoing 0/1
        assert_eq!((i[3], o[3]), (0.0, 0.0));
        assert_eq!(c.evaluate(1.0), 1.0);
        assert_eq!(c.evaluate(-1.0), 0.0);
        assert_eq!(c.evaluate(10.0), 5.0);
    }

    #[test]
    fn linear_tangents_reproduce_a_line() {
        let keys = [
            key(0.0, 1.0, Tangent::Linear),
            key(2.0, 5.0, Tangent::Linear),
        ];
        let c = Curve::new(&keys, Extrapolation::Linear, Extrapolation::Linear).unwrap();
        for t in [-1.0f32, 0.5, 1.0, 1.7, 3.0] {
            assert!((c.evaluate(t) - (1.0 + 2.0 * t)).abs() < 1e-5, "{t}");
        }
    }

    #[test]
    fn extrapolation_modes() {
        let keys = [
            key(1.0, 0.0, Tangent::Linear),
            key(3.0, 2.0, Tangent::Linear),
        ];
        let make = |m| Curve::new(&keys, m, m).unwrap();
        let cycle = make(Extrapolation::Cycle);
        assert!((cycle.evaluate(3.5) - 0.5).abs() < 1e-5);
        assert!((cycle.evaluate(0.5) - 1.5).abs() < 1e-5);
        let offset = make(Extrapolation::CycleOffset);
        assert!((offset.evaluate(3.5) - 2.5).abs() < 1e-5);
        assert!((offset.evaluate(-0.5) - (-1.5)).abs() < 1e-5);
        let bounce = make(Extrapolation::Bounce);
        assert!((bounce.evaluate(3.5) - 1.5).abs() < 1e-5);
        assert!((bounce.evaluate(5.5) - 0.5).abs() < 1e-5);
        assert!((bounce.evaluate(0.5) - 0.5).abs() < 1e-5);
        let constant = make(Extrapolation::Constant);
        assert_eq!(constant.evaluate(100.0), 2.0);
    }

    #[test]
    fn single_key_and_bad_input() {
        let c = Curve::new(
            &[key(0.0, 0.95, Tangent::Smooth)],
            Extrapolation::Cycle,
            Extrapolation::Cycle,
        )
        .unwrap();
        assert_eq!(c.evaluate(7.0), 0.95);
        assert!(c.is_constant());
        let e = Curve::new(
            &[key(1.0, 0.0, Tangent::Flat), key(1.0, 0.0, Tangent::Flat)],
            Extrapolation::Constant,
            Extrapolation::Constant,
        );
        assert!(e.is_err());
        assert!(Curve::new(&[], Extrapolation::Constant, Extrapolation::Constant).is_err());
    }
}
