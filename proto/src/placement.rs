//! An avatar's world placement: where it stands, separate from its clip's root motion.
//!
//! Clients compose `placement · root` before forward kinematics: the world matrix of a root
//! joint is `P · D_root` with `P = T(position) · R(rotation)` (metres, Y up, glTF conventions).

use crate::Transform;
use glam::{Mat4, Quat, Vec3};
use serde::{Deserialize, Serialize};

/// Largest accepted absolute value of a placement coordinate, in metres. Far beyond any
/// scene, and small enough that f32 positions still resolve millimetres (ulp(1e6) ≈ 0.06 m is
/// the coarsest step; scenes that large should re-centre).
pub const MAX_PLACEMENT_METRES: f32 = 1.0e6;

/// Position and rotation of an avatar in its scene.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "ts", derive(ts_rs::TS))]
pub struct Placement {
    /// World position of the avatar's origin, metres `[x, y, z]`.
    #[cfg_attr(feature = "ts", ts(as = "[f32; 3]"))]
    pub position: Vec3,
    /// World rotation of the avatar `[x, y, z, w]` (unit).
    #[cfg_attr(feature = "ts", ts(as = "[f32; 4]"))]
    pub rotation: Quat,
}

impl Default for Placement {
    fn default() -> Self {
        Self::IDENTITY
    }
}

/// Why a position or rotation is not a placement.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
pub enum PlacementError {
    /// A non-finite coordinate or one beyond [`MAX_PLACEMENT_METRES`].
    #[error("position {0:?} must be finite and within ±{MAX_PLACEMENT_METRES} m")]
    Position([f32; 3]),
    /// Not a finite non-zero quaternion.
    #[error("rotation {0:?} is not a finite non-zero quaternion")]
    Rotation([f32; 4]),
}

impl Placement {
    /// At the origin, unrotated.
    pub const IDENTITY: Self = Self {
        position: Vec3::ZERO,
        rotation: Quat::IDENTITY,
    };

    /// A validated placement: every coordinate finite and within [`MAX_PLACEMENT_METRES`],
    /// the rotation normalised ([`crate::unit_quat`]).
    ///
    /// # Errors
    /// [`PlacementError`] naming the offending value.
    pub fn try_new(position: [f32; 3], rotation: [f32; 4]) -> Result<Self, PlacementError> {
        if !position
            .iter()
            .all(|c| c.is_finite() && c.abs() <= MAX_PLACEMENT_METRES)
        {
            return Err(PlacementError::Position(position));
        }
        let rotation = crate::unit_quat(rotation).ok_or(PlacementError::Rotation(rotation))?;
        Ok(Self {
            position: Vec3::from_array(position),
            rotation,
        })
    }

    /// `P = T(position) · R(rotation)`, the world transform of the avatar's frame.
    #[must_use]
    pub fn to_mat4(&self) -> Mat4 {
        Mat4::from_rotation_translation(self.rotation, self.position)
    }

    /// Position lerped and rotation slerped (shortest arc) from `self` (`w = 0`) to `to`
    /// (`w = 1`).
    #[must_use]
    pub fn interpolate(&self, to: &Self, w: f32) -> Self {
        let w = w.clamp(0.0, 1.0);
        Self {
            position: self.position.lerp(to.position, w),
            rotation: self.rotation.slerp(to.rotation, w).normalize(),
        }
    }

    /// Composes `placement · D_root` into every root joint's local transform (joints without a
    /// parent), so forward kinematics gives world matrices of the placed avatar:
    /// `T(p) R(P) · T(t) R S = T(p + P t) (P R) S`. The identity changes nothing (bit for bit).
    pub fn place_roots(&self, parents: &[Option<usize>], locals: &mut [Transform]) {
        if self.is_identity() {
            return;
        }
        for (l, p) in locals.iter_mut().zip(parents) {
            if p.is_none() {
                l.translation = self.position + self.rotation * l.translation;
                l.rotation = (self.rotation * l.rotation).normalize();
            }
        }
    }

    /// Whether it is exactly [`Placement::IDENTITY`].
    #[must_use]
    pub fn is_identity(&self) -> bool {
        *self == Self::IDENTITY
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn validation_refuses_non_finite_huge_and_zero() {
        assert!(Placement::try_new([1.0, 0.0, -2.0], [0.0, 0.0, 0.0, 2.0]).is_ok());
        assert!(Placement::try_new([f32::NAN, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]).is_err());
        assert!(Placement::try_new([2.0e6, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]).is_err());
        assert!(Placement::try_new([0.0; 3], [0.0; 4]).is_err());
        let p = Placement::try_new([0.0; 3], [0.0, 0.0, 0.0, 3.0]).unwrap();
        assert!(p.is_identity());
    }

    #[test]
    fn placing_the_roots_equals_premultiplying_the_world_matrices() {
        let p = Placement {
            position: Vec3::new(1.0, 0.5, -3.0),
            rotation: Quat::from_rotation_y(0.7),
        };
        let parents = [None, Some(0)];
        let mut locals = [
            Transform {
                translation: Vec3::new(0.1, 0.9, 0.2),
                rotation: Quat::from_rotation_x(0.3),
                scale: Vec3::ONE,
            },
            Transform::from_translation(Vec3::new(0.0, 0.5, 0.0)),
        ];
        let before = [
            locals[0].to_mat4(),
            locals[0].to_mat4() * locals[1].to_mat4(),
        ];
        p.place_roots(&parents, &mut locals);
        let after = [
            locals[0].to_mat4(),
            locals[0].to_mat4() * locals[1].to_mat4(),
        ];
        for (b, a) in before.iter().zip(&after) {
            assert!((p.to_mat4() * *b).abs_diff_eq(*a, 1e-5));
        }
    }

    #[test]
    fn serialises_as_arrays_and_interpolates_half_way() {
        let a = Placement::IDENTITY;
        let b = Placement {
            position: Vec3::new(2.0, 0.0, 0.0),
            rotation: Quat::from_rotation_y(std::f32::consts::FRAC_PI_2),
        };
        let text = serde_json::to_string(&a).unwrap();
        assert_eq!(
            text,
            r#"{"position":[0.0,0.0,0.0],"rotation":[0.0,0.0,0.0,1.0]}"#
        );
        let m = a.interpolate(&b, 0.5);
        assert!((m.position - Vec3::new(1.0, 0.0, 0.0)).length() < 1e-6);
        let angle = m.rotation.angle_between(Quat::IDENTITY);
        assert!((angle - std::f32::consts::FRAC_PI_4).abs() < 1e-5);
    }
}
