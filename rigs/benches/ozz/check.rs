//! The port's correctness check: ozz's sampled locals and model matrices against ours at many
//! times, within bounds derived from ozz's formats and estimates (never from its output).
//!
//! Per key, ozz loses:
//! - rotations: the three stored components are rounded to `√2 / 32767 / 2 = 2.16e-5`; the
//!   largest is rebuilt as `x · RSqrtEst(x)`, `x = 1 − a² − b² − c²`, so it is off by up to
//!   `1.5 · 2⁻¹² = 3.66e-4` of itself (rsqrtps) plus `2 · Σ|c| · 2.16e-5 ≤ 6.5e-5` from the
//!   others. Only the part orthogonal to `q` turns it (`≤ √3/2` of the error on one axis), so
//!   a key is within `ROT_KEY = (3.66e-4 + 6.5e-5) · √3/2 + √3 · 2.16e-5 = 4.1e-4` rad of the
//!   exact one in quaternion angle (twice that as a rotation angle).
//! - translations and scales: half floats, rounded half up: `2⁻¹¹` of the value, `2⁻²⁵` near 0.
//!
//! Between the two keys around the time (of the raw keys, found per sample): the coefficient
//! `(r − r₀) · RcpEst(r₁ − r₀)` is off by `1.5 · 2⁻¹²` of itself, plus the f32 rounding of time
//! ratios (`4 · 2⁻²³ · duration / Δt` for keys `Δt` apart; ours rounds times alike), which
//! moves a rotation by that times the keys' quaternion angle `φ` and a vector by that times its
//! step; nlerp (ozz) against slerp (ours) differs by exactly
//! `|atan2(u sin φ, 1 − u + u cos φ) − u φ|` at coefficient `u`; `NLerpEst`'s `RSqrtEstNR`
//! leaves `|q|` within `1e-5` of 1.
//!
//! Model matrices: a joint's columns are off by at most the sum, over its chain, of each
//! local's rotation bound (plus `2 · | |q|² − 1 |`), and its origin by the sum of each link's
//! column error times the distance from that link to the joint, plus each link's translation
//! bound; both with 10 % and `1e-5 · (1 + |p|)` of slack for f32 rounding and second-order
//! terms.

use glam::{DQuat, Mat4, Quat, Vec3};
use posecast_proto::{Skeleton, Transform};

use super::builder::RawAnimation;
use super::simd::SoaTransform;

/// A key's rotation error bound, quaternion angle (radians); see the module doc.
pub const ROT_KEY: f64 = (3.66e-4 + 6.5e-5) * 0.866_025_4 + 1.732_050_8 * 2.16e-5;
/// `RcpEst`'s relative error.
const RCP_EST: f64 = 1.5 / 4096.0;

/// Error bounds of each joint, from the raw keys around the sampled time.
#[derive(Clone, Debug)]
pub struct Bounds {
    raw: RawAnimation,
}

/// The two keys around `t` and the coefficient between them (clamped at the ends).
fn around<V: Copy>(keys: &[(f32, V)], t: f32) -> (V, V, f64, f64) {
    let k = keys.partition_point(|(kt, _)| *kt <= t);
    if k == 0 || k == keys.len() {
        let v = keys[k.min(keys.len() - 1)].1;
        return (v, v, 0.0, 0.0);
    }
    let ((t0, v0), (t1, v1)) = (keys[k - 1], keys[k]);
    let dt = f64::from(t1 - t0);
    (v0, v1, (f64::from(t - t0) / dt).clamp(0.0, 1.0), dt)
}

/// Rotation angle (3-D, radians) between two unit quaternions, well conditioned near 0.
fn quat_angle(a: DQuat, b: DQuat) -> f64 {
    let b = if a.dot(b) < 0.0 { -b } else { b };
    let chord = (a - b).length();
    4.0 * (chord / 2.0).min(1.0).asin()
}

/// The coefficient error between keys `dt` seconds apart in a clip of `duration` seconds.
fn coefficient_error(dt: f64, duration: f64) -> f64 {
    if dt > 0.0 {
        RCP_EST + 4.0 * f64::from(f32::EPSILON) * duration / dt
    } else {
        0.0
    }
}

/// Per-component bound of a half-float track between two keys.
fn vector_bound(keys: &[(f32, Vec3)], t: f32, duration: f64) -> f64 {
    let (a, b, _, dt) = around(keys, t);
    let max_abs = f64::from(a.abs().max(b.abs()).max_element());
    let step = f64::from((b - a).abs().max_element());
    max_abs / 2048.0 + 3e-8 + coefficient_error(dt, duration) * step + 1e-6 * max_abs
}

impl Bounds {
    #[must_use]
    pub fn new(raw: &RawAnimation) -> Self {
        Self { raw: raw.clone() }
    }

    /// (rotation angle, translation component, scale component) bounds of joint `j` at `t`
    /// seconds from the clip's start.
    fn local(&self, j: usize, t: f32) -> (f64, f64, f64) {
        let d = f64::from(self.raw.duration);
        let track = &self.raw.tracks[j];
        let (q0, q1, u, dt) = around(&track.rotations, t);
        let (q0, q1) = (q0.as_dquat(), q1.as_dquat());
        let phi = quat_angle(q0, q1) / 2.0;
        // Where nlerp lands against slerp, as angles from the first key.
        let nlerp = (u * phi.sin()).atan2(1.0 - u + u * phi.cos());
        let rotation =
            2.0 * (ROT_KEY + coefficient_error(dt, d) * phi + (nlerp - u * phi).abs() + 1e-6);
        (
            rotation,
            vector_bound(&track.translations, t, d),
            vector_bound(&track.scales, t, d),
        )
    }
}

/// Worst errors seen, and their share of the bound.
#[derive(Clone, Copy, Debug, Default)]
pub struct Worst {
    pub rotation: f64,
    pub rotation_share: f64,
    pub norm: f64,
    pub translation: f64,
    pub translation_share: f64,
    pub columns: f64,
    pub columns_share: f64,
    pub origin: f64,
    pub origin_share: f64,
    pub samples: usize,
}

/// Lane `lane` of an SoA transform.
#[must_use]
pub fn lane(soa: &[SoaTransform], joint: usize) -> (Vec3, Quat, Vec3) {
    let s = &soa[joint / 4];
    let l = joint % 4;
    (
        Vec3::new(s.translation.x[l], s.translation.y[l], s.translation.z[l]),
        Quat::from_xyzw(
            s.rotation.x[l],
            s.rotation.y[l],
            s.rotation.z[l],
            s.rotation.w[l],
        ),
        Vec3::new(s.scale.x[l], s.scale.y[l], s.scale.z[l]),
    )
}

/// Compares one pose; `Err` names the first joint and quantity out of bounds.
pub fn compare(
    bounds: &Bounds,
    skeleton: &Skeleton,
    time: f32,
    ours: &[Transform],
    ours_world: &[Mat4],
    ozz: &[SoaTransform],
    ozz_models: &[Mat4],
    worst: &mut Worst,
) -> Result<(), String> {
    let n = skeleton.len();
    let local: Vec<(f64, f64, f64)> = (0..n).map(|j| bounds.local(j, time)).collect();
    let mut column_bound = vec![0.0f64; n];
    let fail = |what: &str, j: usize, err: f64, bound: f64| {
        Err(format!(
            "t = {time} s, joint {j} ({}): {what} error {err:.3e} > bound {bound:.3e}",
            skeleton.names()[j]
        ))
    };
    for j in 0..n {
        let (t, q, s) = lane(ozz, j);
        let norm = f64::from(q.length());
        let q_dir = q.as_dquat() / norm;
        let rot = quat_angle(q_dir, ours[j].rotation.as_dquat());
        if (norm - 1.0).abs() > 1e-5 {
            return fail("|q| − 1", j, (norm - 1.0).abs(), 1e-5);
        }
        if rot > local[j].0 {
            return fail("rotation", j, rot, local[j].0);
        }
        let dt = f64::from((t - ours[j].translation).abs().max_element());
        if dt > local[j].1 {
            return fail("translation", j, dt, local[j].1);
        }
        let ds = f64::from((s - ours[j].scale).abs().max_element());
        if ds > local[j].2 {
            return fail("scale", j, ds, local[j].2);
        }
        worst.rotation = worst.rotation.max(rot);
        worst.rotation_share = worst.rotation_share.max(rot / local[j].0);
        worst.norm = worst.norm.max((norm - 1.0).abs());
        worst.translation = worst.translation.max(dt);
        worst.translation_share = worst.translation_share.max(dt / local[j].1);

        // Chain bounds, accumulated from the parent's.
        let scale = f64::from(ours[j].scale.abs().max_element()).max(1.0);
        let own = (local[j].0 + 2.0 * (norm * norm - 1.0).abs() + local[j].2) * scale;
        let parent = skeleton.parents()[j];
        column_bound[j] = own + parent.map_or(0.0, |p| column_bound[p]);
        let cb = 1.1 * column_bound[j] + 1e-5;
        let pj = ours_world[j].w_axis.truncate();
        // Origin: every link's column error times its distance to this joint, plus its
        // translation error carried by its parent's linear part.
        let mut origin_bound = 0.0f64;
        let mut k = Some(j);
        while let Some(link) = k {
            let link_parent = skeleton.parents()[link];
            let pk = ours_world[link].w_axis.truncate();
            let parent_linear = link_parent.map_or(1.0, |p| {
                let w = ours_world[p];
                f64::from(
                    w.x_axis
                        .truncate()
                        .length()
                        .max(w.y_axis.truncate().length())
                        .max(w.z_axis.truncate().length()),
                )
            });
            let link_local = local[link].0 + 4e-5 + local[link].2;
            origin_bound += link_local * f64::from((pj - pk).length())
                + 3f64.sqrt() * local[link].1 * parent_linear;
            k = link_parent;
        }
        let ob = 1.1 * origin_bound + 1e-5 * (1.0 + f64::from(pj.length()));

        let (a, b) = (ozz_models[j], ours_world[j]);
        let cols = [
            (a.x_axis - b.x_axis).truncate().length(),
            (a.y_axis - b.y_axis).truncate().length(),
            (a.z_axis - b.z_axis).truncate().length(),
        ]
        .into_iter()
        .fold(0.0f32, f32::max);
        let cols = f64::from(cols);
        if cols > cb {
            return fail("model matrix column", j, cols, cb);
        }
        let origin = f64::from((a.w_axis - b.w_axis).truncate().length());
        if origin > ob {
            return fail("model origin", j, origin, ob);
        }
        let row = glam::Vec4::new(a.x_axis.w, a.y_axis.w, a.z_axis.w, a.w_axis.w);
        if row != glam::Vec4::new(0.0, 0.0, 0.0, 1.0) {
            return fail(
                "model last row",
                j,
                f64::from((row - glam::Vec4::W).length()),
                0.0,
            );
        }
        worst.columns = worst.columns.max(cols);
        worst.columns_share = worst.columns_share.max(cols / cb);
        worst.origin = worst.origin.max(origin);
        worst.origin_share = worst.origin_share.max(origin / ob);
    }
    worst.samples += 1;
    Ok(())
}
