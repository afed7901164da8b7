//! Joint types, degrees of freedom and their limits (seed 002, "Joint types" and "DOF limits").
//!
//! A joint's local matrix is built from its DOF values and its offset `r` (the rest
//! translation): `L = T(r + translation(φ)) · R(φ)`.

use crate::transform::Transform;
use glam::{EulerRot, Quat, Vec3};
use serde::{Deserialize, Serialize};

/// How a joint moves. Angles are radians, translations metres.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum JointType {
    /// 1 DOF: rotation by `φ₀` about the unit `axis` (seed 002 `L_Ra`).
    Hinge {
        /// The rotation axis, in the joint's local space (normalised when used; zero means x).
        axis: Vec3,
    },
    /// 2 DOFs: rotation about x by `φ₀`, then about y by `φ₁`: `R = R_y(φ₁) · R_x(φ₀)` (`L_Rxy`).
    Universal,
    /// 3 DOFs: Euler angles applied x, then y, then z: `R = R_z(φ₂) · R_y(φ₁) · R_x(φ₀)` (`L_Rxyz`,
    /// the CSE169 `.skel` balljoint).
    BallEuler,
    /// A free rotation held as a unit quaternion (`L_Q`); no scalar DOFs and no limits.
    BallQuaternion,
    /// 1 DOF: translation by `φ₀` along the unit `axis` (`L_Ta`).
    Prismatic {
        /// The sliding axis, in the joint's local space (normalised when used; zero means x).
        axis: Vec3,
    },
    /// 3 DOFs: translation by `(φ₀, φ₁, φ₂)` (`L_Txyz`).
    Translational,
}

impl JointType {
    /// Number of scalar DOFs.
    #[must_use]
    pub fn dof_count(&self) -> usize {
        match self {
            Self::Hinge { .. } | Self::Prismatic { .. } => 1,
            Self::Universal => 2,
            Self::BallEuler | Self::Translational => 3,
            Self::BallQuaternion => 0,
        }
    }

    /// Whether the DOFs are angles (rotational) rather than distances.
    #[must_use]
    pub fn is_rotational(&self) -> bool {
        matches!(
            self,
            Self::Hinge { .. } | Self::Universal | Self::BallEuler | Self::BallQuaternion
        )
    }
}

/// One degree of freedom: a value kept within `[min, max]`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Dof {
    /// The current value, within `[min, max]`: radians for a rotational joint, metres for a
    /// translational one.
    pub value: f32,
    /// The lower limit, same units (`-∞` when free).
    pub min: f32,
    /// The upper limit, same units (`+∞` when free).
    pub max: f32,
}

impl Dof {
    /// An unlimited DOF at zero.
    pub const FREE: Self = Self {
        value: 0.0,
        min: f32::NEG_INFINITY,
        max: f32::INFINITY,
    };
}

/// Why a DOF could not be set.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum DofError {
    /// The DOF index is past the joint's DOFs.
    #[error("DOF {index} does not exist: this joint has {count}")]
    NoSuchDof {
        /// The index asked for.
        index: usize,
        /// How many DOFs the joint has.
        count: usize,
    },
    /// The value given is NaN or infinite (for [`JointDofs::set_rotation`], a quaternion that is
    /// not finite or has near-zero length).
    #[error("DOF value {value} is not finite")]
    NotFinite {
        /// The value given (for a quaternion, its length).
        value: f32,
    },
    /// The limits have `min > max` or a NaN.
    #[error("limits [{min}, {max}] are empty or not numbers")]
    BadLimits {
        /// The lower limit given.
        min: f32,
        /// The upper limit given.
        max: f32,
    },
}

/// A joint's type, its DOFs and, for [`JointType::BallQuaternion`], its rotation.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct JointDofs {
    /// How the joint moves; fixes how many DOFs it has.
    pub joint_type: JointType,
    dofs: Vec<Dof>,
    quaternion: Quat,
}

impl Default for JointDofs {
    fn default() -> Self {
        Self::new(JointType::BallQuaternion)
    }
}

impl JointDofs {
    /// A joint of this type with every DOF free and at zero.
    #[must_use]
    pub fn new(joint_type: JointType) -> Self {
        Self {
            joint_type,
            dofs: vec![Dof::FREE; joint_type.dof_count()],
            quaternion: Quat::IDENTITY,
        }
    }

    /// The scalar DOFs, [`JointType::dof_count`] of them, in the order the type names them.
    #[must_use]
    pub fn dofs(&self) -> &[Dof] {
        &self.dofs
    }

    /// Whether any DOF has a finite limit.
    #[must_use]
    pub fn is_limited(&self) -> bool {
        self.dofs
            .iter()
            .any(|d| d.min.is_finite() || d.max.is_finite())
    }

    /// Sets DOF `index`'s limits, clamping its current value into them.
    pub fn set_limits(&mut self, index: usize, min: f32, max: f32) -> Result<(), DofError> {
        if min.is_nan() || max.is_nan() || min > max {
            return Err(DofError::BadLimits { min, max });
        }
        let count = self.dofs.len();
        let dof = self
            .dofs
            .get_mut(index)
            .ok_or(DofError::NoSuchDof { index, count })?;
        dof.min = min;
        dof.max = max;
        dof.value = dof.value.clamp(min, max);
        Ok(())
    }

    /// Sets DOF `index` to `value` clamped to its limits; returns the value applied.
    pub fn set(&mut self, index: usize, value: f32) -> Result<f32, DofError> {
        if !value.is_finite() {
            return Err(DofError::NotFinite { value });
        }
        let count = self.dofs.len();
        let dof = self
            .dofs
            .get_mut(index)
            .ok_or(DofError::NoSuchDof { index, count })?;
        dof.value = value.clamp(dof.min, dof.max);
        Ok(dof.value)
    }

    /// The rotation the DOFs describe (identity for translational types).
    #[must_use]
    pub fn rotation(&self) -> Quat {
        let v = |i: usize| self.dofs.get(i).map_or(0.0, |d| d.value);
        match self.joint_type {
            JointType::Hinge { axis } => Quat::from_axis_angle(axis.normalize_or(Vec3::X), v(0)),
            JointType::Universal => Quat::from_rotation_y(v(1)) * Quat::from_rotation_x(v(0)),
            JointType::BallEuler => Quat::from_euler(EulerRot::ZYX, v(2), v(1), v(0)),
            JointType::BallQuaternion => self.quaternion,
            JointType::Prismatic { .. } | JointType::Translational => Quat::IDENTITY,
        }
    }

    /// The translation the DOFs add to the offset (zero for rotational types).
    #[must_use]
    pub fn translation(&self) -> Vec3 {
        let v = |i: usize| self.dofs.get(i).map_or(0.0, |d| d.value);
        match self.joint_type {
            JointType::Prismatic { axis } => axis.normalize_or(Vec3::X) * v(0),
            JointType::Translational => Vec3::new(v(0), v(1), v(2)),
            _ => Vec3::ZERO,
        }
    }

    /// The local transform `L = T(r + translation(φ)) · R(φ)` for offset `r`.
    #[must_use]
    pub fn local_transform(&self, offset: Vec3) -> Transform {
        Transform::from_translation_rotation(offset + self.translation(), self.rotation())
    }

    /// Sets a rotational joint from any rotation `q`: `q` is projected onto the joint's DOFs
    /// (the twist about a hinge axis, Euler angles for universal and ball joints), each DOF
    /// clamped to its limits. Returns the rotation actually applied. Translational joints keep
    /// their values and return the identity.
    pub fn set_rotation(&mut self, q: Quat) -> Result<Quat, DofError> {
        if !q.is_finite() || q.length_squared() < 1e-12 {
            return Err(DofError::NotFinite { value: q.length() });
        }
        let q = q.normalize();
        match self.joint_type {
            JointType::Hinge { axis } => {
                let axis = axis.normalize_or(Vec3::X);
                // Swing-twist: the twist about `axis` is the projection of q's vector part.
                let proj = axis * q.xyz().dot(axis);
                let twist = Quat::from_xyzw(proj.x, proj.y, proj.z, q.w);
                let angle = if twist.length_squared() < 1e-12 {
                    0.0
                } else {
                    let t = twist.normalize();
                    2.0 * t.xyz().dot(axis).atan2(t.w)
                };
                self.set(0, wrap_angle(angle))?;
            }
            JointType::Universal => {
                // R_y(b) · R_x(a) is ZYX Euler with z = 0; take the nearest such rotation.
                let (_, y, x) = q.to_euler(EulerRot::ZYX);
                self.set(0, x)?;
                self.set(1, y)?;
            }
            JointType::BallEuler => {
                let (z, y, x) = q.to_euler(EulerRot::ZYX);
                self.set(0, x)?;
                self.set(1, y)?;
                self.set(2, z)?;
            }
            JointType::BallQuaternion => self.quaternion = q,
            JointType::Prismatic { .. } | JointType::Translational => return Ok(Quat::IDENTITY),
        }
        Ok(self.rotation())
    }
}

fn wrap_angle(a: f32) -> f32 {
    let tau = std::f32::consts::TAU;
    let w = (a + std::f32::consts::PI).rem_euclid(tau) - std::f32::consts::PI;
    if w.is_finite() { w } else { 0.0 }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::f32s;
    use glam::{Mat3, Mat4};
    use proptest::prelude::*;

    /// Seed 002's `L_Rxyz` written out entry by entry (row-major there; glam is column-major).
    fn seed_rxyz(x: f32, y: f32, z: f32) -> Mat3 {
        let (sx, cx, sy, cy, sz, cz) = (x.sin(), x.cos(), y.sin(), y.cos(), z.sin(), z.cos());
        Mat3::from_cols_array(&[
            cy * cz,
            cy * sz,
            -sy,
            sx * sy * cz - cx * sz,
            sx * sy * sz + cx * cz,
            sx * cy,
            cx * sy * cz + sx * sz,
            cx * sy * sz - sx * cz,
            cx * cy,
        ])
    }

    fn seed_rxy(x: f32, y: f32) -> Mat3 {
        let (sx, cx, sy, cy) = (x.sin(), x.cos(), y.sin(), y.cos());
        Mat3::from_cols_array(&[cy, 0.0, -sy, sx * sy, cx, sx * cy, cx * sy, -sx, cx * cy])
    }

    proptest! {
        #[test]
        fn ball_euler_matches_seed_matrix(x in f32s(-3.0..3.0), y in f32s(-3.0..3.0), z in f32s(-3.0..3.0)) {
            let mut j = JointDofs::new(JointType::BallEuler);
            j.set(0, x).unwrap(); j.set(1, y).unwrap(); j.set(2, z).unwrap();
            prop_assert!(Mat3::from_quat(j.rotation()).abs_diff_eq(seed_rxyz(x, y, z), 1e-5));
        }

        #[test]
        fn universal_matches_seed_matrix(x in f32s(-3.0..3.0), y in f32s(-3.0..3.0)) {
            let mut j = JointDofs::new(JointType::Universal);
            j.set(0, x).unwrap(); j.set(1, y).unwrap();
            prop_assert!(Mat3::from_quat(j.rotation()).abs_diff_eq(seed_rxy(x, y), 1e-5));
        }

        #[test]
        fn hinge_and_prismatic_match_seed(a in f32s(-3.0..3.0), axis in prop::array::uniform3(f32s(-1.0..1.0)), r in prop::array::uniform3(f32s(-1.0..1.0))) {
            let axis = Vec3::from(axis);
            prop_assume!(axis.length() > 0.1);
            let n = axis.normalize();
            let mut h = JointDofs::new(JointType::Hinge { axis });
            h.set(0, a).unwrap();
            // L_Ra written out from the seed.
            let (s, c) = a.sin_cos();
            let m = Mat3::from_cols_array(&[
                n.x * n.x + c * (1.0 - n.x * n.x), n.x * n.y * (1.0 - c) + n.z * s, n.x * n.z * (1.0 - c) - n.y * s,
                n.x * n.y * (1.0 - c) - n.z * s, n.y * n.y + c * (1.0 - n.y * n.y), n.y * n.z * (1.0 - c) + n.x * s,
                n.x * n.z * (1.0 - c) + n.y * s, n.y * n.z * (1.0 - c) - n.x * s, n.z * n.z + c * (1.0 - n.z * n.z),
            ]);
            prop_assert!(Mat3::from_quat(h.rotation()).abs_diff_eq(m, 1e-5));
            let offset = Vec3::from(r);
            prop_assert!(h.local_transform(offset).to_mat4().w_axis.truncate().abs_diff_eq(offset, 1e-6));
            let mut p = JointDofs::new(JointType::Prismatic { axis });
            p.set(0, a).unwrap();
            let t = p.local_transform(offset).to_mat4();
            prop_assert!(t.abs_diff_eq(Mat4::from_translation(offset + n * a), 1e-5));
        }

        #[test]
        fn euler_projection_round_trips(x in f32s(-1.5..1.5), y in f32s(-1.5..1.5), z in f32s(-1.5..1.5)) {
            let mut j = JointDofs::new(JointType::BallEuler);
            let q = Quat::from_euler(EulerRot::ZYX, z, y, x);
            let applied = j.set_rotation(q).unwrap();
            prop_assert!(applied.dot(q).abs() > 1.0 - 1e-5);
        }

        #[test]
        fn hinge_projection_recovers_angle(a in f32s(-3.0..3.0)) {
            let mut h = JointDofs::new(JointType::Hinge { axis: Vec3::new(0.0, 1.0, 1.0) });
            let q = Quat::from_axis_angle(Vec3::new(0.0, 1.0, 1.0).normalize(), a);
            h.set_rotation(q).unwrap();
            prop_assert!((h.dofs()[0].value - a).abs() < 1e-4);
        }
    }

    #[test]
    fn limits_clamp() {
        // test.skel's knee_r: rotxlimit -2 0, rotylimit 0 0, rotzlimit 0 0, pose -3 1 2.
        let mut j = JointDofs::new(JointType::BallEuler);
        j.set_limits(0, -2.0, 0.0).unwrap();
        j.set_limits(1, 0.0, 0.0).unwrap();
        j.set_limits(2, 0.0, 0.0).unwrap();
        assert_eq!(j.set(0, -3.0), Ok(-2.0));
        assert_eq!(j.set(1, 1.0), Ok(0.0));
        assert_eq!(j.set(2, 2.0), Ok(0.0));
        assert_eq!(
            j.set(3, 0.0),
            Err(DofError::NoSuchDof { index: 3, count: 3 })
        );
        assert!(j.set(0, f32::NAN).is_err());
        assert!(j.set_limits(0, 1.0, -1.0).is_err());
        // A rotation outside the limits is clamped per DOF.
        let applied = j.set_rotation(Quat::from_rotation_y(1.0)).unwrap();
        assert!(applied.abs_diff_eq(Quat::IDENTITY, 1e-6));
        let applied = j.set_rotation(Quat::from_rotation_x(-2.5)).unwrap();
        assert!(applied.abs_diff_eq(Quat::from_rotation_x(-2.0), 1e-5));
    }
}
