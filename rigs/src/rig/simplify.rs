//! Simplifying bind matrices (seed 000, "Simplifying bind poses"): the bind adjustment with
//! `V_i = U_i`, the rotation of `B_i = T(C_i) U_i`, so every inverse bind becomes `T(−C_i)`.

use glam::{Mat3, Mat4, Quat};
use posecast_proto::DecomposeError;
use posecast_proto::transform::polar_decompose;

use super::adjust::{adjust_bind, rebuild};
use super::{JointMaps, RigError};
use crate::asset::Asset;

/// Largest deviation of the residual stretch from the identity that is snapped to it, so that a
/// rigid bind gives an exact translation (the skinned mesh moves by at most this, relatively).
const SNAP: f32 = 1e-5;

/// Simplifies every bind matrix: `V_i = U_i` in [`adjust_bind`], so `B'_i⁻¹ = T(−C_i)` and,
/// where the rest pose is the bind pose, `t'_i = C_i − C_parent(i)` and the rest rotations are
/// the identity.
///
/// A bind carrying scale or shear, `U_i = Q_i S_i` by polar decomposition, is adjusted by
/// `V_i = Q_i` only: its inverse bind keeps the world-frame stretch, `B'_i⁻¹ = P_i⁻¹ T(−C_i)`
/// with `P_i = Q_i S_i Q_i⁻¹` (symmetric), unless no vertex is weighted to the joint (glTF
/// helper joints), whose inverse bind then is `T(−C_i)` too. Mirrored or degenerate binds are
/// refused.
pub fn simplify(asset: Asset) -> Result<(Asset, JointMaps, Vec<String>), RigError> {
    let sk = &asset.skeleton;
    let mut v = Vec::with_capacity(sk.len());
    for (j, ib) in sk.inverse_bind().iter().enumerate() {
        let bind = ib.inverse();
        let name = || sk.names()[j].clone();
        let polar = polar_decompose(Mat3::from_mat4(bind)).map_err(|e| match e {
            DecomposeError::Reflection { determinant } => RigError::MirroredBind {
                joint: j,
                name: name(),
                determinant,
            },
            DecomposeError::Degenerate { .. } | DecomposeError::Shear { .. } => {
                RigError::DegenerateBind {
                    joint: j,
                    name: name(),
                    determinant: determinant_of(&e),
                }
            }
        })?;
        v.push(Quat::from_mat3(&polar.rotation).normalize());
    }
    let (mut asset, maps, notes) = adjust_bind(asset, &v)?;
    // Snap the residual of rigid binds to an exact `T(−C_i)`.
    let sk = &asset.skeleton;
    let mut weighted = vec![false; sk.len()];
    for m in &asset.meshes {
        for (&j, &w) in m.mesh.joints().iter().zip(m.mesh.weights()) {
            if w > 0.0
                && let Some(x) = weighted.get_mut(usize::from(j))
            {
                *x = true;
            }
        }
    }
    let mut stretched = 0;
    let inverse_bind: Vec<Mat4> = sk
        .inverse_bind()
        .iter()
        .zip(&weighted)
        .map(|(ib, &weighted)| {
            let linear = Mat3::from_mat4(*ib);
            let deviation = (linear - Mat3::IDENTITY)
                .to_cols_array()
                .iter()
                .fold(0.0f32, |a, x| a.max(x.abs()));
            // A joint no vertex is weighted to can take any inverse bind: drop its stretch.
            if deviation <= SNAP || !weighted {
                // ib = L · T(−C) with L ≈ I, so its translation column is −L·C ≈ −C.
                let c = -(linear.inverse() * ib.w_axis.truncate());
                Mat4::from_translation(-c)
            } else {
                stretched += 1;
                *ib
            }
        })
        .collect();
    asset.skeleton = rebuild(sk, sk.rest().to_vec(), inverse_bind)?;
    let mut notes = notes;
    if stretched > 0 {
        notes.push(format!(
            "{stretched} bind matrices carry scale or shear; their inverse binds keep it"
        ));
    }
    Ok((asset, maps, notes))
}

fn determinant_of(e: &DecomposeError) -> f32 {
    match e {
        DecomposeError::Reflection { determinant } | DecomposeError::Degenerate { determinant } => {
            *determinant
        }
        DecomposeError::Shear { .. } => f32::NAN,
    }
}
