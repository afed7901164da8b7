//! Precision per subscription (protocol version 5): how finely a subscriber's wire v2 frames
//! code each joint.
//!
//! Wire v2 ([`crate::frame2`]) codes a rotation as three 15-bit smallest-three levels
//! ([`crate::quant`], worst angle [`finest_degrees`] ≈ 0.0086°) and a translation in steps of
//! [`crate::frame2::TRANSLATION_STEP`]. A subscription may ask for less: its frames then code
//! each joint's levels on a coarser grid, `m` levels a step ([`Steps`]), so every residual is
//! about `log₂ m` bits shorter per component. The grid is integer arithmetic on the levels, so
//! the encoder and every decoder reconstruct identical values whatever their floating point.
//!
//! A [`Precision`] names the bound:
//! - `degrees`: the worst angle between a streamed rotation and the server's, per joint;
//! - `millimetres` (with `shell`): a world-space bound instead, in the style of ACL's error
//!   metric — how far a point `shell` metres from a joint (a virtual skin vertex) may move
//!   because of every rotation above it. Each joint gets its own angle from its reach (the
//!   distance to the farthest joint below it, plus the shell, in the rest pose), so a
//!   fingertip is coded more coarsely than a hip: joint `a` gets `θ_a = ε / (reach_a · D_a)`
//!   where `D_a` counts the joints on the longest root-to-leaf path through `a`, so along any
//!   path `Σ θ_a · reach_a ≤ ε`. With both, each joint takes the finer of the two;
//! - `translation`: the worst error of a streamed translation, metres.
//!
//! **The grid** ([`coarse_rotation_level`], [`fine_rotation_level`]). With `Z = 16383` the
//! level of a zero component and `Zₘ = ⌈Z / m⌉`, a level `l` is sent as
//! `c = round((l − Z) / m) + Zₘ` (half away from zero) and read back as
//! `clamp(Z + (c − Zₘ) · m, 0, 2Z)`. Zero stays exact (a still joint stays still). A
//! translation level `t` is sent as `round(t / m)` and read back as `t · m`.
//!
//! **The bound.** A component's error is at most `(⌊m/2⌋ + ½)` level steps `Δ = √2 / 32766`
//! (half a step from quantising, `⌊m/2⌋` from the grid). With the three small components each
//! off by `e`, the rotation moves by at most `|Δq| ≤ 2√3 · e` (the dropped component, at least
//! ½, follows as `√(1 − Σ)`; the worst case is `q = (½, ½, ½, ½)`), an angle of at most
//! `4√3 · e` radians: [`rotation_bound_degrees`].
//!
//! **Near an axis** (protocol version 6, [`Steps::near`]). With the largest component `d`, the
//! rotation moves by at most `|Δq| ≤ √3 · e / d`, an angle of `2√3 · e / d`: the worst case above
//! is `d = ½`. A rotation whose levels are [`near_axis`] (`d ≥` [`NEAR_AXIS`]) goes on its
//! joint's near grid, whose step is the coarsest within the same angle at `d = 0.849`
//! ([`near_rotation_bound_degrees`]): about 1.7 times the step, about 0.8 bits a component
//! fewer. The encoder chooses the grid and marks it in the rotation's bit 47 (its *tier*), so a
//! decoder only reads it; the choice is a function of the tick's levels alone, so frames at one
//! precision stay shareable between subscribers.

use crate::description::AvatarDescription;
use glam::{Affine3A, Quat, Vec3};
use serde::{Deserialize, Serialize};

/// The level of a zero component (the middle of the 15-bit range).
pub const ZERO_LEVEL: i64 = 16383;
/// Largest rotation step (levels per grid step).
pub const MAX_ROTATION_STEP: u8 = 255;
/// Largest translation step.
pub const MAX_TRANSLATION_STEP: u16 = u16::MAX;

/// Translation quantisation step of wire v2, metres: the finest grid (re-exported by
/// [`crate::frame2`]).
pub const TRANSLATION_STEP: f64 = 1.0 / 8192.0;
/// Default shell distance for `millimetres`, metres (ACL's default virtual vertex distance).
pub const DEFAULT_SHELL: f32 = 0.03;

/// What precision a subscription asks for (`subscribe`'s `precision`). Absent fields take the
/// finest precision (what a subscription without `precision` gets).
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
#[cfg_attr(feature = "ts", derive(ts_rs::TS))]
#[serde(deny_unknown_fields)]
pub struct Precision {
    /// Worst angle of any joint's rotation, degrees (at least [`finest_degrees`], at most
    /// 45). Absent: the finest, unless `millimetres` is given.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[cfg_attr(feature = "ts", ts(optional))]
    pub degrees: Option<f32>,
    /// Worst world-space movement, millimetres, of a point `shell` metres from any joint
    /// caused by the rotations' coding (0.01–10,000).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[cfg_attr(feature = "ts", ts(optional))]
    pub millimetres: Option<f32>,
    /// The shell distance of `millimetres`, metres (0–10; default 0.03).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[cfg_attr(feature = "ts", ts(optional))]
    pub shell: Option<f32>,
    /// Worst error of a streamed translation, metres (at least half of
    /// [`TRANSLATION_STEP`], at most 1).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[cfg_attr(feature = "ts", ts(optional))]
    pub translation: Option<f32>,
}

/// A hashable identity of a [`Precision`] (its fields' bit patterns), for caches of frames
/// made at that precision.
pub type PrecisionKey = [u32; 4];

/// What a subscriber's frames are coded at: its precision, and whether its decoder takes
/// near-axis steps ([`Steps::near`], protocol version 6). Subscribers of one precision and
/// versions on either side of 6 get frames made apart.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Grid {
    /// The precision asked for.
    pub precision: Precision,
    /// Whether rotations near an axis may go on coarser steps.
    pub near: bool,
}

/// A hashable identity of a [`Grid`].
pub type GridKey = (PrecisionKey, bool);

impl Grid {
    /// The grid of a subscriber of protocol `version` asking for `precision`.
    #[must_use]
    pub fn for_version(precision: Precision, version: u32) -> Self {
        Self {
            precision,
            near: version >= 6,
        }
    }

    /// The cache identity of this grid.
    #[must_use]
    pub fn key(&self) -> GridKey {
        (self.precision.key(), self.near)
    }

    /// The steps of an avatar of rig `d` on this grid ([`Precision::resolve_with`]).
    #[must_use]
    pub fn resolve(&self, d: &AvatarDescription) -> Steps {
        self.precision.resolve_with(d, self.near)
    }
}

/// How one avatar's frames are coded: a grid step per joint's rotation and one for its
/// translations ([`Precision::resolve`]). Sent in keyframe chunks (flag 16).
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub struct Steps {
    /// Levels per grid step of each joint's rotation components (1: the finest).
    pub rotations: Vec<u8>,
    /// Levels per grid step of the translations (1: the finest).
    pub translation: u16,
    /// Protocol version 6: each joint's step for a rotation *near an axis* (its largest
    /// component at least [`NEAR_AXIS`] in magnitude), coarser than `rotations` for the same
    /// bound (see the module docs, "Near an axis"). Empty: no joint has one (a frame's
    /// rotations are all on `rotations`' grid).
    pub near: Vec<u8>,
}

impl Steps {
    /// Whether every step is 1 (the frames are coded as without a precision).
    #[must_use]
    pub fn is_finest(&self) -> bool {
        self.translation == 1
            && self.rotations.iter().all(|&s| s == 1)
            && self.near.iter().all(|&s| s == 1)
    }

    /// Whether rotations near an axis have steps of their own (keyframe chunk flag 32): the
    /// frames' rotations then carry a tier bit (bit 47) and escaped joints go in 48 bits.
    #[must_use]
    pub fn tiered(&self) -> bool {
        !self.near.is_empty()
    }

    /// The step of joint `j`'s rotation `bits` (its tier bit says which grid it is on).
    #[must_use]
    pub fn rotation_step(&self, j: usize, bits: u64) -> u8 {
        let grid = if bits >> 47 & 1 == 1 {
            &self.near
        } else {
            &self.rotations
        };
        grid.get(j).copied().unwrap_or(1)
    }
}

/// How large a rotation's largest component must be for its joint's near-axis step
/// ([`Steps::near`]) to apply: 0.85, a rotation within 63.6° of the identity (or of a half
/// turn about an axis). Motion capture's joints spend nearly all of their time there.
pub const NEAR_AXIS: f64 = 0.85;

/// Whether the rotation of smallest-three levels `levels` (as [`crate::quant::encode`] gives
/// them) is near an axis: `Σ (lᵢ − Z)² ≤ (1 − NEAR_AXIS²) / Δ²`, in integers (the encoder's
/// choice; a decoder reads it from the tier bit).
#[must_use]
pub fn near_axis(levels: [i64; 3]) -> bool {
    /// `⌊(1 − 0.85²) / Δ²⌋` with `1 / Δ² = 32766² / 2`.
    const LIMIT: i64 = 148_963_492;
    levels.iter().map(|l| (l - ZERO_LEVEL).pow(2)).sum::<i64>() <= LIMIT
}

/// Why a precision was refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("precision.{field} = {value}: {why}")]
pub struct PrecisionError {
    /// The field.
    pub field: &'static str,
    /// The value given.
    pub value: f32,
    /// What is allowed.
    pub why: String,
}

/// The R10 series' mantissas (ISO 3 preferred numbers, ten a decade).
const R10: [f64; 10] = [1.0, 1.25, 1.6, 2.0, 2.5, 3.15, 4.0, 5.0, 6.3, 8.0];

/// `v`'s decade and mantissa in `[1, 10)`, with a relative margin of 1e-6 so that an `f32`
/// near a series value (0.1 is 0.100000001…) counts as it.
fn decade(v: f64) -> (f64, f64) {
    let scale = 10f64.powf(v.log10().floor());
    let mantissa = v / scale;
    if mantissa >= 10.0 * (1.0 - 1e-6) {
        (scale * 10.0, mantissa / 10.0)
    } else {
        (scale, mantissa)
    }
}

/// The largest R10 value at or below `v` (0 and what is not finite and positive unchanged).
fn r10_at_or_below(v: f64) -> f64 {
    if !(v.is_finite() && v > 0.0) {
        return v;
    }
    let (scale, m) = decade(v);
    let r = R10
        .iter()
        .rev()
        .find(|&&r| r <= m * (1.0 + 1e-6))
        .copied()
        .unwrap_or(1.0);
    r * scale
}

/// The smallest R10 value at or above `v` (0 and what is not finite and positive unchanged).
fn r10_at_or_above(v: f64) -> f64 {
    if !(v.is_finite() && v > 0.0) {
        return v;
    }
    let (scale, m) = decade(v);
    R10.iter()
        .find(|&&r| r >= m * (1.0 - 1e-6))
        .map_or(10.0 * scale, |r| r * scale)
}

/// The step of one rotation level, `√2 / 32766` (see [`crate::quant`]).
fn level_step() -> f64 {
    std::f64::consts::SQRT_2 / 32766.0
}

/// The guaranteed worst angle, degrees, of a rotation coded with grid step `step` (1: the
/// finest, ≈ 0.0087°): `4√3 · e` with `e = (⌊m/2⌋ + ½) Δ`, plus 1 % for the second-order
/// terms and 0.00002° for the decoder's `f32` arithmetic.
#[must_use]
pub fn rotation_bound_degrees(step: u8) -> f64 {
    bound_degrees(step, 0.5)
}

/// The guaranteed worst angle, degrees, of a rotation near an axis ([`NEAR_AXIS`]) coded with
/// grid step `step`: `2√3 · e / d` with `d` the smallest largest component a near rotation
/// has (less 0.001 for the quantisation of the levels the choice is made on), with the same
/// margins as [`rotation_bound_degrees`].
#[must_use]
pub fn near_rotation_bound_degrees(step: u8) -> f64 {
    bound_degrees(step, NEAR_AXIS - 0.001)
}

/// `2√3 · e / d` degrees with margins: the worst angle of a rotation whose largest component
/// is at least `d` and whose three others are each off by at most `e = (⌊m/2⌋ + ½) Δ`.
fn bound_degrees(step: u8, d: f64) -> f64 {
    let e = (f64::from(step / 2) + 0.5) * level_step();
    (2.0 * 3f64.sqrt() * e / d).to_degrees() * 1.01 + 2e-5
}

/// The coarsest near-axis step whose bound ([`near_rotation_bound_degrees`]) is within
/// `degrees` (1 when none is coarser).
#[must_use]
pub fn near_rotation_step_for(degrees: f64) -> u8 {
    (0..=MAX_ROTATION_STEP / 2)
        .rev()
        .map(|half| 2 * half + 1)
        .find(|&m| near_rotation_bound_degrees(m) <= degrees)
        .unwrap_or(1)
}

/// The finest worst angle a subscription can ask for, degrees.
#[must_use]
pub fn finest_degrees() -> f64 {
    rotation_bound_degrees(1)
}

/// The guaranteed worst error, metres, of a translation coded with grid step `step`.
#[must_use]
pub fn translation_bound(step: u16) -> f64 {
    (f64::from(step / 2) + 0.5) * TRANSLATION_STEP
}

/// The coarsest rotation step whose bound is within `degrees` (1 when none is coarser).
#[must_use]
pub fn rotation_step_for(degrees: f64) -> u8 {
    // The bound grows with ⌊m/2⌋: the coarsest m of a ⌊m/2⌋ is odd.
    (0..=MAX_ROTATION_STEP / 2)
        .rev()
        .map(|half| 2 * half + 1)
        .find(|&m| rotation_bound_degrees(m) <= degrees)
        .unwrap_or(1)
}

/// The coarsest translation step whose bound is within `metres` (1 when none is coarser).
#[must_use]
pub fn translation_step_for(metres: f64) -> u16 {
    let half = ((metres / TRANSLATION_STEP - 0.5) + 1e-9).floor();
    if !half.is_finite() || half < 1.0 {
        return 1;
    }
    let half = half.min(f64::from(MAX_TRANSLATION_STEP / 2)) as u16;
    2 * half + 1
}

/// A rotation component's level `l` (0…32766) on the grid of step `m`.
#[must_use]
pub fn coarse_rotation_level(l: i64, m: u8) -> i64 {
    let m = i64::from(m.max(1));
    let z_m = (ZERO_LEVEL + m - 1) / m;
    let d = l - ZERO_LEVEL;
    let q = (d.abs() + m / 2) / m;
    (d.signum() * q + z_m).clamp(0, 2 * z_m)
}

/// The level a grid value `c` of step `m` stands for.
#[must_use]
pub fn fine_rotation_level(c: i64, m: u8) -> i64 {
    let m = i64::from(m.max(1));
    let z_m = (ZERO_LEVEL + m - 1) / m;
    (ZERO_LEVEL + (c - z_m) * m).clamp(0, 2 * ZERO_LEVEL)
}

/// A translation level on the grid of step `m`.
#[must_use]
pub fn coarse_translation_level(t: i32, m: u16) -> i32 {
    let m = i64::from(m.max(1));
    let t = i64::from(t);
    let q = (t.abs() + m / 2) / m;
    (t.signum() * q) as i32
}

/// The translation level a grid value `c` of step `m` stands for (clamped to `i32`).
#[must_use]
pub fn fine_translation_level(c: i32, m: u16) -> i32 {
    (i64::from(c) * i64::from(m.max(1))).clamp(i64::from(i32::MIN), i64::from(i32::MAX)) as i32
}

impl Precision {
    /// The finest precision (what a subscription without one gets).
    pub const FINEST: Self = Self {
        degrees: None,
        millimetres: None,
        shell: None,
        translation: None,
    };

    /// The cache identity of this precision.
    #[must_use]
    pub fn key(&self) -> PrecisionKey {
        let bits = |v: Option<f32>| v.map_or(u32::MAX, f32::to_bits);
        [
            bits(self.degrees),
            bits(self.millimetres),
            bits(self.shell),
            bits(self.translation),
        ]
    }

    /// Whether it asks for nothing coarser than the finest.
    #[must_use]
    pub fn is_finest(&self) -> bool {
        let rotations = match (self.degrees, self.millimetres) {
            (None, None) => true,
            (Some(d), None) => rotation_step_for(f64::from(d)) == 1,
            _ => false,
        };
        rotations
            && self
                .translation
                .is_none_or(|t| translation_step_for(f64::from(t)) == 1)
    }

    /// This precision with every field rounded towards finer to the R10 series (ten values a
    /// decade: 1, 1.25, 1.6, 2, 2.5, 3.15, 4, 5, 6.3, 8 × 10ᵏ; `shell` up, the bounds down;
    /// no finer than the finest), so subscriptions that ask for nearly the same share the
    /// frames made for it — a value per client (0.1, 0.1001, 0.0999…) would each cost an
    /// encode a tick — and there are at most about 40 values a field. The guarantee asked for
    /// still holds (each bound is at or below what was asked); the server echoes the rounded
    /// values in `subscribed`. Of a valid precision, valid, and its own canonical form.
    #[must_use]
    pub fn canonical(&self) -> Self {
        let down =
            |v: Option<f32>, least: f64| v.map(|v| r10_at_or_below(f64::from(v)).max(least) as f32);
        Self {
            degrees: down(self.degrees, finest_degrees()),
            millimetres: down(self.millimetres, 0.01),
            shell: self
                .shell
                .map(|v| r10_at_or_above(f64::from(v)).min(10.0) as f32),
            translation: down(self.translation, translation_bound(1)),
        }
    }

    /// Checks every field's range.
    ///
    /// # Errors
    /// The first field out of range, with what is allowed.
    pub fn validate(&self) -> Result<(), PrecisionError> {
        let check = |field: &'static str, v: Option<f32>, lo: f64, hi: f64| match v {
            Some(v) if !v.is_finite() || f64::from(v) < lo || f64::from(v) > hi => {
                Err(PrecisionError {
                    field,
                    value: v,
                    why: format!("must be a number from {lo:.6} to {hi}"),
                })
            }
            _ => Ok(()),
        };
        // The smallest values are the finest bounds, less a rounding margin (a client may
        // send the figure it was told, rounded).
        check("degrees", self.degrees, finest_degrees() * 0.999, 45.0)?;
        check("millimetres", self.millimetres, 0.01 * 0.999, 10_000.0)?;
        check("shell", self.shell, 0.0, 10.0)?;
        check(
            "translation",
            self.translation,
            translation_bound(1) * 0.999,
            1.0,
        )?;
        Ok(())
    }

    /// The steps of an avatar of rig `d` at this precision (see the module docs), for a
    /// receiver of protocol version 5 (no near-axis steps). Rest positions come from the
    /// description's rest transforms.
    #[must_use]
    pub fn resolve(&self, d: &AvatarDescription) -> Steps {
        self.resolve_with(d, false)
    }

    /// The steps of an avatar of rig `d` at this precision; with `near` (a receiver of
    /// protocol version 6) each joint also gets a step for rotations near an axis, within the
    /// same bound ([`Steps::near`]).
    #[must_use]
    pub fn resolve_with(&self, d: &AvatarDescription, near: bool) -> Steps {
        let n = d.joint_names.len();
        // Each joint's worst angle, degrees (`None`: the finest).
        let angles: Vec<Option<f64>> = match self.millimetres {
            None => vec![self.degrees.map(f64::from); n],
            Some(mm) => {
                let shell = f64::from(self.shell.unwrap_or(DEFAULT_SHELL));
                let reach = reaches(d);
                let longest = longest_paths(d);
                (0..n)
                    .map(|j| {
                        let angle = (f64::from(mm)
                            / 1000.0
                            / ((reach[j] + shell).max(1e-6) * longest[j] as f64))
                            .to_degrees();
                        Some(self.degrees.map_or(angle, |f| f64::from(f).min(angle)))
                    })
                    .collect()
            }
        };
        let rotations: Vec<u8> = angles
            .iter()
            .map(|a| a.map_or(1, rotation_step_for))
            .collect();
        let near_steps: Vec<u8> = angles
            .iter()
            .zip(&rotations)
            .map(|(a, &m)| a.map_or(1, near_rotation_step_for).max(m))
            .collect();
        let near = near && near_steps != rotations;
        Steps {
            rotations,
            translation: self
                .translation
                .map_or(1, |t| translation_step_for(f64::from(t))),
            near: if near { near_steps } else { Vec::new() },
        }
    }
}

/// Each joint's parent as an index (`None` for a root or a parent out of order).
fn parent(d: &AvatarDescription, j: usize) -> Option<usize> {
    usize::try_from(*d.parents.get(j)?).ok().filter(|&p| p < j)
}

/// Rest world positions of every joint (parents come first in a description).
fn rest_positions(d: &AvatarDescription) -> Vec<Vec3> {
    let mut world: Vec<Affine3A> = Vec::with_capacity(d.joint_names.len());
    for j in 0..d.joint_names.len() {
        let t = d.rest_translations.get(j).copied().unwrap_or_default();
        let r = d
            .rest_rotations
            .get(j)
            .copied()
            .unwrap_or([0.0, 0.0, 0.0, 1.0]);
        let s = d.rest_scales.get(j).copied().unwrap_or([1.0; 3]);
        let r = Quat::from_array(r);
        let r = if r.is_finite() && r.length_squared() > 1e-12 {
            r.normalize()
        } else {
            Quat::IDENTITY
        };
        let local =
            Affine3A::from_scale_rotation_translation(Vec3::from_array(s), r, Vec3::from_array(t));
        let w = parent(d, j).map_or(local, |p| world[p] * local);
        world.push(w);
    }
    world.iter().map(|w| Vec3::from(w.translation)).collect()
}

/// Each joint's reach: the distance from it to the farthest joint below it (0 for a leaf).
fn reaches(d: &AvatarDescription) -> Vec<f64> {
    let p = rest_positions(d);
    let mut reach = vec![0.0f64; p.len()];
    for k in 0..p.len() {
        let mut a = parent(d, k);
        while let Some(j) = a {
            let dist = f64::from(p[k].distance(p[j]));
            if dist.is_finite() && dist > reach[j] {
                reach[j] = dist;
            }
            a = parent(d, j);
        }
    }
    reach
}

/// For each joint, the number of joints on the longest root-to-leaf path through it.
fn longest_paths(d: &AvatarDescription) -> Vec<usize> {
    let n = d.joint_names.len();
    let mut depth = vec![1usize; n];
    for j in 0..n {
        if let Some(p) = parent(d, j) {
            depth[j] = depth[p] + 1;
        }
    }
    let mut below = vec![0usize; n];
    for j in (0..n).rev() {
        if let Some(p) = parent(d, j) {
            below[p] = below[p].max(below[j] + 1);
        }
    }
    (0..n).map(|j| depth[j] + below[j]).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::quant;

    #[test]
    fn the_grid_keeps_zero_and_stays_within_half_a_step() {
        for m in [1u8, 2, 3, 5, 11, 29, 254, 255] {
            let c = coarse_rotation_level(ZERO_LEVEL, m);
            assert_eq!(fine_rotation_level(c, m), ZERO_LEVEL, "m = {m}");
            for l in 0..=2 * ZERO_LEVEL {
                let back = fine_rotation_level(coarse_rotation_level(l, m), m);
                assert!(
                    (back - l).abs() <= i64::from(m / 2),
                    "m {m} l {l} back {back}"
                );
                assert!((0..=2 * ZERO_LEVEL).contains(&back));
            }
        }
        for m in [1u16, 3, 15, 65535] {
            for t in [
                -100_000i32,
                -8,
                -1,
                0,
                1,
                7,
                8,
                9,
                123_456,
                i32::MAX,
                i32::MIN,
            ] {
                let back = fine_translation_level(coarse_translation_level(t, m), m);
                assert!(
                    (i64::from(back) - i64::from(t)).abs() <= i64::from(m / 2),
                    "{m} {t}"
                );
            }
        }
    }

    /// The angle bound holds on random rotations and on the worst case the bound is derived
    /// from, `(½, ½, ½, ½)` with every component off the same way.
    #[test]
    fn coded_rotations_stay_within_the_bound() {
        let mut seed = 0x9e37_79b9_7f4a_7c15u64;
        let mut rnd = move || {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            (seed >> 11) as f32 / (1u64 << 53) as f32 * 2.0 - 1.0
        };
        for m in [1u8, 3, 5, 11, 29, 101, 255] {
            let bound = rotation_bound_degrees(m);
            let mut worst = 0.0f64;
            let mut qs: Vec<Quat> = (0..50_000)
                .map(|_| Quat::from_xyzw(rnd(), rnd(), rnd(), rnd()).normalize())
                .collect();
            for k in 0..2000 {
                let e = k as f32 * 1e-6;
                qs.push(Quat::from_xyzw(0.5 + e, 0.5 + e, 0.5 + e, 0.5).normalize());
                qs.push(Quat::from_xyzw(0.5 - e, 0.5 - e, 0.5 - e, 0.5).normalize());
            }
            for q in qs {
                let bits = quant::encode(q);
                let mut coded = bits & !((1u64 << 45) - 1);
                for c in 0..3 {
                    let shift = 15 * (2 - c);
                    let l = ((bits >> shift) & 0x7fff) as i64;
                    let back = fine_rotation_level(coarse_rotation_level(l, m), m);
                    coded |= (back as u64) << shift;
                }
                let angle = quant::angle_between_degrees(q, quant::decode(coded));
                worst = worst.max(angle);
            }
            assert!(worst <= bound, "m {m}: worst {worst}° > bound {bound}°");
            // The bound is not loose by more than a factor of 2.5 (it is reached near the
            // worst case).
            assert!(
                worst >= bound / 2.5,
                "m {m}: worst {worst}° for bound {bound}°"
            );
        }
    }

    /// Near an axis the bound holds for the near step: random rotations whose levels are near
    /// an axis (by [`near_axis`], as the encoder chooses), the worst case at the threshold
    /// (every small component equal, the largest just at 0.85), coded on the near grid. The
    /// near step is coarser than the general one for the same bound, and the integer
    /// threshold is `(1 − 0.85²) / Δ²`.
    #[test]
    fn near_axis_rotations_stay_within_the_near_bound() {
        assert_eq!(
            ((1.0 - NEAR_AXIS * NEAR_AXIS) / (level_step() * level_step())).floor(),
            148_963_492.0
        );
        let mut seed = 0x2545_f491_4f6c_dd1du64;
        let mut rnd = move || {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            (seed >> 11) as f32 / (1u64 << 53) as f32 * 2.0 - 1.0
        };
        let levels = |bits: u64| [0, 1, 2].map(|c| ((bits >> (15 * (2 - c))) & 0x7fff) as i64);
        for m in [1u8, 3, 5, 9, 19, 51, 101, 255] {
            let bound = near_rotation_bound_degrees(m);
            let mut qs: Vec<Quat> = Vec::new();
            while qs.len() < 50_000 {
                // Rotations up to about 70° from the identity or a half turn, so that both
                // sides of the threshold are drawn.
                let s = rnd().abs() * 0.6;
                let axis = Vec3::new(rnd(), rnd(), rnd()).normalize_or(Vec3::X);
                let v = axis * s;
                let big = (1.0 - s * s).max(0.0).sqrt();
                let q = match qs.len() % 4 {
                    0 => Quat::from_xyzw(v.x, v.y, v.z, big),
                    1 => Quat::from_xyzw(big, v.x, v.y, v.z),
                    2 => Quat::from_xyzw(v.x, big, v.y, v.z),
                    _ => Quat::from_xyzw(v.x, v.y, big, v.z),
                };
                qs.push(q.normalize());
            }
            // At the threshold: small components equal, pushed the way that grows the error.
            let t = ((1.0 - NEAR_AXIS * NEAR_AXIS) / 3.0).sqrt() as f32;
            for k in 0..2000 {
                let e = k as f32 * 1e-6;
                qs.push(Quat::from_xyzw(t - e, t - e, t - e, 0.85 + 3.0 * e).normalize());
            }
            let (mut worst, mut near) = (0.0f64, 0usize);
            for q in qs {
                let bits = quant::encode(q);
                if !near_axis(levels(bits)) {
                    continue;
                }
                near += 1;
                let mut coded = bits & !((1u64 << 45) - 1);
                for (c, l) in levels(bits).into_iter().enumerate() {
                    let back = fine_rotation_level(coarse_rotation_level(l, m), m);
                    coded |= (back as u64) << (15 * (2 - c));
                }
                worst = worst.max(quant::angle_between_degrees(q, quant::decode(coded)));
            }
            assert!(near > 20_000, "m {m}: {near} rotations near an axis");
            assert!(
                worst <= bound,
                "m {m}: worst {worst}° > near bound {bound}°"
            );
            assert!(
                worst >= bound / 2.5,
                "m {m}: worst {worst}° for near bound {bound}°"
            );
        }
        for deg in [0.02, 0.05, 0.1, 0.25, 1.0] {
            let (m, near) = (rotation_step_for(deg), near_rotation_step_for(deg));
            assert!(near_rotation_bound_degrees(near) <= deg, "{deg}");
            assert!(near_rotation_bound_degrees(near + 2) > deg, "{deg}");
            // About 1.7× coarser: 0.85 / 0.5.
            assert!(
                f64::from(near) >= 1.5 * f64::from(m),
                "{deg}: {near} against {m}"
            );
        }
    }

    #[test]
    fn steps_are_the_coarsest_within_the_bound() {
        assert_eq!(rotation_step_for(0.0086), 1);
        assert_eq!(rotation_step_for(0.01), 1);
        for deg in [0.02, 0.05, 0.1, 0.25, 1.0, 45.0] {
            let m = rotation_step_for(deg);
            assert!(rotation_bound_degrees(m) <= deg, "{deg}");
            if m < MAX_ROTATION_STEP {
                assert!(
                    rotation_bound_degrees(m + 2) > deg,
                    "{deg}: {m} is not the coarsest"
                );
            }
        }
        assert_eq!(rotation_step_for(0.05), 5);
        assert_eq!(rotation_step_for(0.1), 11);
        assert_eq!(near_rotation_step_for(0.05), 9);
        assert_eq!(near_rotation_step_for(0.1), 19);
        assert_eq!(translation_step_for(0.001), 15);
        assert!(translation_bound(15) <= 0.001 && translation_bound(17) > 0.001);
    }

    fn chain(lengths: &[f32]) -> AvatarDescription {
        use crate::{Skeleton, Transform};
        let n = lengths.len();
        let rest: Vec<Transform> = lengths
            .iter()
            .map(|&l| Transform::from_translation(Vec3::new(0.0, l, 0.0)))
            .collect();
        let skeleton = Skeleton::new(
            (0..n).map(|j| format!("j{j}")).collect(),
            (0..n).map(|j| j.checked_sub(1)).collect(),
            rest,
            vec![glam::Mat4::IDENTITY; n],
        )
        .unwrap();
        AvatarDescription::new(
            crate::msg::AvatarId("a".into()),
            1,
            "A".into(),
            &skeleton,
            &[],
            &[],
            None,
        )
    }

    /// A chain's joints get coarser towards its tip, and the world-space bound derived from
    /// the steps chosen holds along it (each joint's angle bound times its reach, summed).
    #[test]
    fn a_world_space_budget_codes_the_tip_coarser_than_the_root() {
        let d = chain(&[0.0, 0.5, 0.4, 0.3, 0.05, 0.03]);
        let p = Precision {
            millimetres: Some(2.0),
            ..Precision::FINEST
        };
        let steps = p.resolve(&d);
        assert!(
            steps.rotations.windows(2).all(|w| w[0] <= w[1]),
            "{:?}",
            steps.rotations
        );
        assert!(
            steps.rotations[5] > steps.rotations[0],
            "{:?}",
            steps.rotations
        );
        let reach = reaches(&d);
        let total: f64 = (0..6)
            .map(|j| rotation_bound_degrees(steps.rotations[j]).to_radians() * (reach[j] + 0.03))
            .sum();
        assert!(total <= 0.002, "world bound {total} m");
        // A flat bound as well caps every joint.
        let both = Precision {
            degrees: Some(0.05),
            ..p
        }
        .resolve(&d);
        assert!(
            both.rotations.iter().all(|&s| s <= 5),
            "{:?}",
            both.rotations
        );
    }

    #[test]
    fn out_of_range_fields_are_refused_by_name() {
        let bad = [
            Precision {
                degrees: Some(0.001),
                ..Precision::FINEST
            },
            Precision {
                degrees: Some(f32::NAN),
                ..Precision::FINEST
            },
            Precision {
                millimetres: Some(-1.0),
                ..Precision::FINEST
            },
            Precision {
                translation: Some(1e30),
                ..Precision::FINEST
            },
        ];
        let fields = ["degrees", "degrees", "millimetres", "translation"];
        for (p, f) in bad.iter().zip(fields) {
            assert_eq!(p.validate().unwrap_err().field, f);
        }
        assert!(Precision::FINEST.validate().is_ok());
        assert!(Precision::FINEST.is_finest());
        let json: Precision = serde_json::from_str(r#"{"degrees":0.1}"#).unwrap();
        assert_eq!(json.degrees, Some(0.1));
        assert!(serde_json::from_str::<Precision>(r#"{"degree":0.1}"#).is_err());
    }

    #[test]
    fn canonical_precisions_are_finer_within_one_step_few_and_stable() {
        let mut seed = 0x5eed_u64;
        let mut next = || {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            (seed >> 11) as f64 / (1u64 << 53) as f64
        };
        let mut degrees = std::collections::BTreeSet::new();
        for _ in 0..20_000 {
            // Log-uniform over each field's range.
            let log = |lo: f64, hi: f64, u: f64| (lo.ln() + (hi.ln() - lo.ln()) * u).exp() as f32;
            let p = Precision {
                degrees: Some(log(finest_degrees(), 45.0, next())),
                millimetres: Some(log(0.01, 10_000.0, next())),
                shell: Some(log(0.001, 10.0, next())),
                translation: Some(log(translation_bound(1), 1.0, next())),
            };
            assert!(p.validate().is_ok(), "{p:?}");
            let c = p.canonical();
            assert!(c.validate().is_ok(), "{p:?} → {c:?}");
            assert_eq!(c.canonical(), c, "{p:?}");
            // Towards finer, by less than one step of the series (1.28× at most: 1.25 → 1.6).
            for (asked, got, finer_is_smaller) in [
                (p.degrees, c.degrees, true),
                (p.millimetres, c.millimetres, true),
                (p.shell, c.shell, false),
                (p.translation, c.translation, true),
            ] {
                let (a, g) = (f64::from(asked.unwrap()), f64::from(got.unwrap()));
                let ratio = if finer_is_smaller { a / g } else { g / a };
                assert!((1.0 - 1e-6..1.29).contains(&ratio), "{asked:?} → {got:?}");
            }
            degrees.insert(c.degrees.unwrap().to_bits());
        }
        // 0.0087–45 degrees: about 37 values of the series and the finest.
        assert!((30..=40).contains(&degrees.len()), "{}", degrees.len());
        // Series values stay as they are (clients send what they were told).
        for d in [0.01f32, 0.05, 0.1, 0.25, 1.0, 2.5, 40.0] {
            let c = Precision {
                degrees: Some(d),
                ..Precision::FINEST
            }
            .canonical();
            assert_eq!(c.degrees, Some(d), "{d}");
        }
        assert_eq!(Precision::FINEST.canonical(), Precision::FINEST);
    }
}
