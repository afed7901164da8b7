//! Translation · rotation · scale transforms and the polar decomposition that splits an affine
//! matrix into them (seed 000: "If `U_i` carries scale, split it by polar decomposition").

use glam::{Mat3, Mat4, Quat, Vec3};
use serde::{Deserialize, Serialize};

/// A local transform `D = T(t) · R · S`, applied to column vectors (scale first).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Transform {
    /// `t`, in the parent's space, metres once the rig is normalised.
    pub translation: Vec3,
    /// `R`, a unit quaternion.
    pub rotation: Quat,
    /// `S`, per-axis scale in the joint's own space.
    pub scale: Vec3,
}

impl Default for Transform {
    fn default() -> Self {
        Self::IDENTITY
    }
}

/// Why an affine matrix could not be split into translation, rotation and scale.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum DecomposeError {
    /// The linear part has a negative determinant: a mirror, which no rotation can express.
    #[error("matrix is a reflection (determinant {determinant})")]
    Reflection {
        /// The determinant of the linear part (negative).
        determinant: f32,
    },
    /// The linear part is singular or not finite.
    #[error("matrix is singular or not finite (determinant {determinant})")]
    Degenerate {
        /// The determinant of the linear part (near zero, or NaN/infinite).
        determinant: f32,
    },
    /// The stretch `S` of `M = Q S` is not diagonal: the matrix shears, or scales along axes
    /// other than the joint's own, which a per-axis scale cannot hold.
    #[error("matrix has shear or off-axis scale (largest off-diagonal stretch {off_diagonal})")]
    Shear {
        /// The largest magnitude of an off-diagonal entry of `S` (absolute; more than 1e-4 of
        /// the largest diagonal entry is refused).
        off_diagonal: f32,
    },
}

/// Result of [`polar_decompose`]: `M = rotation · stretch`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Polar {
    /// `Q`, orthonormal with determinant +1.
    pub rotation: Mat3,
    /// `S = Qᵀ M`, symmetric positive definite.
    pub stretch: Mat3,
}

/// Polar decomposition `M = Q S` of a 3×3 matrix by Higham's iteration
/// `Q_{k+1} = (Q_k + Q_k⁻ᵀ) / 2`, which converges quadratically to the orthogonal factor.
///
/// Errors on a singular or non-finite matrix and on a reflection (`det M < 0`), which would give
/// an improper `Q` that no quaternion represents.
pub fn polar_decompose(m: Mat3) -> Result<Polar, DecomposeError> {
    let determinant = m.determinant();
    let scale = m.x_axis.length() + m.y_axis.length() + m.z_axis.length();
    if !determinant.is_finite() || determinant.abs() <= 1e-12 * scale.powi(3).max(f32::MIN_POSITIVE)
    {
        return Err(DecomposeError::Degenerate { determinant });
    }
    if determinant < 0.0 {
        return Err(DecomposeError::Reflection { determinant });
    }
    let mut q = m;
    for _ in 0..64 {
        let next = (q + q.inverse().transpose()) * 0.5;
        let change = (next - q)
            .to_cols_array()
            .iter()
            .fold(0.0f32, |a, v| a.max(v.abs()));
        q = next;
        if change <= 1e-7 {
            break;
        }
    }
    // Re-orthonormalise through a quaternion so `rotation` is exactly a rotation.
    let rotation = Mat3::from_quat(Quat::from_mat3(&q).normalize());
    let stretch = rotation.transpose() * m;
    Ok(Polar { rotation, stretch })
}

/// The unit quaternion in the direction of `xyzw`, or `None` when that is not a rotation:
/// a non-finite component, or a norm below `1e-6`.
///
/// The norm is taken in f64: in f32, `|q|²` overflows for components beyond ~1.8e19 (e.g.
/// `[2e19, 0, 0, 0]` or every component 3e38), and `q / |q|` then gives zeros or NaN. Every
/// finite input either normalises exactly or is refused; the result is finite and unit.
#[must_use]
pub fn unit_quat(xyzw: [f32; 4]) -> Option<Quat> {
    if !xyzw.iter().all(|c| c.is_finite()) {
        return None;
    }
    let norm = xyzw
        .iter()
        .map(|&c| f64::from(c) * f64::from(c))
        .sum::<f64>()
        .sqrt();
    if norm < 1e-6 {
        return None;
    }
    let [x, y, z, w] = xyzw.map(|c| (f64::from(c) / norm) as f32);
    // Each component is now in [-1, 1]; one f32 normalisation removes the rounding.
    let q = Quat::from_xyzw(x, y, z, w).normalize();
    q.is_finite().then_some(q)
}

impl Transform {
    /// The transform that changes nothing.
    pub const IDENTITY: Self = Self {
        translation: Vec3::ZERO,
        rotation: Quat::IDENTITY,
        scale: Vec3::ONE,
    };

    /// A pure translation `T(t)`.
    #[must_use]
    pub fn from_translation(translation: Vec3) -> Self {
        Self {
            translation,
            ..Self::IDENTITY
        }
    }

    /// `T(t) · R`.
    #[must_use]
    pub fn from_translation_rotation(translation: Vec3, rotation: Quat) -> Self {
        Self {
            translation,
            rotation,
            scale: Vec3::ONE,
        }
    }

    /// The matrix `T(t) · R · S`.
    #[must_use]
    pub fn to_mat4(&self) -> Mat4 {
        Mat4::from_scale_rotation_translation(self.scale, self.rotation, self.translation)
    }

    /// Splits an affine matrix into `T(t) · R · S` by polar decomposition of its linear part.
    ///
    /// Errors when the matrix mirrors, is singular, or shears (a stretch that is not diagonal
    /// within a relative tolerance of 1e-4); [`polar_decompose`] gives the full stretch then.
    pub fn try_from_mat4(m: &Mat4) -> Result<Self, DecomposeError> {
        let linear = Mat3::from_mat4(*m);
        let polar = polar_decompose(linear)?;
        let s = polar.stretch;
        let diag = Vec3::new(s.x_axis.x, s.y_axis.y, s.z_axis.z);
        let off = [
            s.x_axis.y, s.x_axis.z, s.y_axis.x, s.y_axis.z, s.z_axis.x, s.z_axis.y,
        ]
        .iter()
        .fold(0.0f32, |a, v| a.max(v.abs()));
        if off > 1e-4 * diag.abs().max_element() {
            return Err(DecomposeError::Shear { off_diagonal: off });
        }
        Ok(Self {
            translation: m.w_axis.truncate(),
            rotation: Quat::from_mat3(&polar.rotation).normalize(),
            scale: diag,
        })
    }

    /// `self` at `w = 0`, `other` at `w = 1`: translations and scales interpolated linearly,
    /// rotations by slerp along the shortest arc (`q ≡ −q`: `other`'s rotation is negated when
    /// `r_self · r_other < 0`), so the result turns by `w · θ` where `θ ≤ π` is the angle
    /// between the two rotations. Cross-fades on the server and jitter-buffer playout on the
    /// client both blend this way.
    #[must_use]
    pub fn blend(&self, other: &Transform, w: f32) -> Transform {
        let target = if self.rotation.dot(other.rotation) < 0.0 {
            -other.rotation
        } else {
            other.rotation
        };
        Transform {
            translation: self.translation.lerp(other.translation, w),
            rotation: self.rotation.slerp(target, w).normalize(),
            scale: self.scale.lerp(other.scale, w),
        }
    }

    /// Whether every component is finite.
    #[must_use]
    pub fn is_finite(&self) -> bool {
        self.translation.is_finite() && self.rotation.is_finite() && self.scale.is_finite()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::{f32s, finite_f32s};

    #[test]
    fn unit_quat_normalises_extreme_finite_input_and_refuses_the_rest() {
        for big in [
            [2e19, 0.0, 0.0, 0.0],
            [3e38; 4],
            [-f32::MAX, f32::MAX, 0.0, 1.0],
        ] {
            let q = unit_quat(big).unwrap();
            assert!(
                q.is_finite() && (q.length() - 1.0).abs() < 1e-6,
                "{big:?} → {q:?}"
            );
        }
        let q = unit_quat([3e38; 4]).unwrap();
        assert!(
            q.abs_diff_eq(Quat::from_xyzw(0.5, 0.5, 0.5, 0.5), 1e-6),
            "{q:?}"
        );
        assert!(unit_quat([f32::NAN, 0.0, 0.0, 1.0]).is_none());
        assert!(unit_quat([f32::INFINITY, 0.0, 0.0, 1.0]).is_none());
        assert!(unit_quat([0.0; 4]).is_none());
        assert!(unit_quat([1e-30, 0.0, 0.0, 0.0]).is_none());
    }

    proptest! {
        #[test]
        fn unit_quat_is_unit_and_keeps_the_direction(
            x in finite_f32s(), y in finite_f32s(),
            z in finite_f32s(), w in finite_f32s(),
        ) {
            let norm = [x, y, z, w].iter().map(|&c| f64::from(c).powi(2)).sum::<f64>().sqrt();
            match unit_quat([x, y, z, w]) {
                Some(q) => {
                    prop_assert!(q.is_finite() && (q.length() - 1.0).abs() < 1e-6);
                    for (got, c) in q.to_array().iter().zip([x, y, z, w]) {
                        prop_assert!((f64::from(*got) - f64::from(c) / norm).abs() < 1e-6);
                    }
                }
                None => prop_assert!(norm < 1e-6),
            }
        }
    }
    use proptest::prelude::*;

    fn quat_strategy() -> impl Strategy<Value = Quat> {
        (
            f32s(-1.0..1.0),
            f32s(-1.0..1.0),
            f32s(-1.0..1.0),
            f32s(-1.0..1.0),
        )
            .prop_filter("non-zero", |(x, y, z, w)| {
                x * x + y * y + z * z + w * w > 0.01
            })
            .prop_map(|(x, y, z, w)| Quat::from_xyzw(x, y, z, w).normalize())
    }

    proptest! {
        #[test]
        fn decomposition_round_trips(
            t in prop::array::uniform3(f32s(-10.0..10.0)),
            r in quat_strategy(),
            s in prop::array::uniform3(f32s(0.1..5.0)),
        ) {
            let original = Transform {
                translation: Vec3::from(t), rotation: r, scale: Vec3::from(s),
            };
            let m = original.to_mat4();
            let back = Transform::try_from_mat4(&m).unwrap();
            prop_assert!(back.to_mat4().abs_diff_eq(m, 1e-4 * (1.0 + m.abs().to_cols_array()
                .iter().cloned().fold(0.0, f32::max))));
            prop_assert!((back.scale - original.scale).abs().max_element() < 1e-3);
        }

        #[test]
        fn polar_factor_is_a_rotation(
            cols in prop::array::uniform9(f32s(-3.0..3.0)),
        ) {
            let m = Mat3::from_cols_array(&cols);
            if let Ok(p) = polar_decompose(m) {
                let qtq = p.rotation.transpose() * p.rotation;
                prop_assert!(qtq.abs_diff_eq(Mat3::IDENTITY, 1e-4));
                prop_assert!((p.rotation.determinant() - 1.0).abs() < 1e-4);
                prop_assert!((p.rotation * p.stretch).abs_diff_eq(m, 1e-3 * (1.0 + m.abs()
                    .to_cols_array().iter().cloned().fold(0.0, f32::max))));
                // S symmetric
                prop_assert!(p.stretch.abs_diff_eq(p.stretch.transpose(), 2e-3));
            } else {
                prop_assert!(m.determinant() <= 1e-9 || m.determinant() < 0.0);
            }
        }
    }

    /// The angle (radians, in `[0, π]`) of the rotation taking `a` to `b`.
    fn angle_between(a: Quat, b: Quat) -> f32 {
        2.0 * a.dot(b).abs().min(1.0).acos()
    }

    #[test]
    fn blend_takes_the_shortest_arc() {
        // +270° about Y is −90° the short way: halfway is −45°, not +135°.
        let a = Transform::IDENTITY;
        let b = Transform {
            translation: Vec3::new(2.0, 0.0, -4.0),
            rotation: Quat::from_rotation_y(270f32.to_radians()),
            scale: Vec3::new(1.0, 3.0, 1.0),
        };
        let half = a.blend(&b, 0.5);
        let expected = Quat::from_rotation_y(-45f32.to_radians());
        assert!(
            angle_between(half.rotation, expected) < 1e-5,
            "{:?}",
            half.rotation
        );
        assert!(
            half.translation
                .abs_diff_eq(Vec3::new(1.0, 0.0, -2.0), 1e-6)
        );
        assert!(half.scale.abs_diff_eq(Vec3::new(1.0, 2.0, 1.0), 1e-6));
        assert_eq!(a.blend(&b, 0.0), a);
        assert!(angle_between(a.blend(&b, 1.0).rotation, b.rotation) < 1e-5);
    }

    proptest! {
        /// `blend(a, b, w)` lies on the shortest arc: `w · θ` from `a` and `(1 − w) · θ` from `b`.
        #[test]
        fn blend_divides_the_shortest_arc(
            a in quat_strategy(), b in quat_strategy(), w in f32s(0.0..1.0),
        ) {
            let theta = angle_between(a, b);
            let r = Transform::from_translation_rotation(Vec3::ZERO, a)
                .blend(&Transform::from_translation_rotation(Vec3::ZERO, b), w)
                .rotation;
            prop_assert!((r.length() - 1.0).abs() < 1e-5);
            prop_assert!((angle_between(a, r) - w * theta).abs() < 2e-3, "θ {theta}, w {w}");
            prop_assert!((angle_between(r, b) - (1.0 - w) * theta).abs() < 2e-3, "θ {theta}, w {w}");
        }
    }

    #[test]
    fn mirror_is_reported() {
        let m = Mat4::from_scale(Vec3::new(-1.0, 1.0, 1.0));
        assert!(matches!(
            Transform::try_from_mat4(&m),
            Err(DecomposeError::Reflection { .. })
        ));
    }

    #[test]
    fn shear_is_reported() {
        let m = Mat4::from_cols_array(&[
            1.0, 0.0, 0.0, 0.0, 0.5, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0,
        ]);
        assert!(matches!(
            Transform::try_from_mat4(&m),
            Err(DecomposeError::Shear { .. })
        ));
    }

    #[test]
    fn singular_is_reported() {
        let m = Mat4::from_scale(Vec3::new(1.0, 0.0, 1.0));
        assert!(matches!(
            Transform::try_from_mat4(&m),
            Err(DecomposeError::Degenerate { .. })
        ));
        let nan = Mat4::from_translation(Vec3::X) * Mat4::from_scale(Vec3::splat(f32::NAN));
        assert!(Transform::try_from_mat4(&nan).is_err());
    }
}
