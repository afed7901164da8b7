//! Forward kinematics and skinning matrices (DESIGN.md "Conventions"; seed 001).

use crate::skeleton::Skeleton;
use crate::transform::Transform;
use glam::{Mat4, Vec4};

/// World (model-space) matrices from local transforms: `W_j = W_parent(j) · D_j`, `W_root = D_root`,
/// with `D_j = T(t_j) · R_j · S_j`.
///
/// One forward loop over joints (parents precede children by construction of [`Skeleton`]),
/// the local matrices `D_j` computed four joints at a time (bit for bit what
/// [`Transform::to_mat4`] gives); writes into `world` and allocates nothing.
///
/// # Panics
/// When `locals` or `world` does not have one entry per joint: that is a bug in the caller,
/// whose buffers are sized from the same skeleton.
pub fn forward_kinematics(skeleton: &Skeleton, locals: &[Transform], world: &mut [Mat4]) {
    let n = skeleton.len();
    assert!(
        locals.len() == n && world.len() == n,
        "pose buffers must have {n} joints"
    );
    let parents = skeleton.parents();
    for (base, group) in locals.chunks(4).enumerate() {
        let base = base * 4;
        for (k, local) in local_matrices(group)
            .into_iter()
            .take(group.len())
            .enumerate()
        {
            let j = base + k;
            world[j] = match parents[j] {
                Some(p) => world[p] * local,
                None => local,
            };
        }
    }
}

/// `D = T(t) · R · S` of up to four transforms (missing ones are the identity), computed four
/// lanes at a time with, per lane, exactly the operations of [`Transform::to_mat4`] (glam's
/// `Mat4::from_scale_rotation_translation`), so every matrix has the same bits as one by one.
#[inline]
fn local_matrices(group: &[Transform]) -> [Mat4; 4] {
    let at = |k: usize| group.get(k).copied().unwrap_or(Transform::IDENTITY);
    let [a, b, c, d] = [at(0), at(1), at(2), at(3)];
    // Columns a..d in, lanes a..d out: row r holds component r of the four.
    let q = Mat4::from_cols(
        a.rotation.into(),
        b.rotation.into(),
        c.rotation.into(),
        d.rotation.into(),
    )
    .transpose();
    let s = Mat4::from_cols(
        a.scale.extend(0.0),
        b.scale.extend(0.0),
        c.scale.extend(0.0),
        d.scale.extend(0.0),
    )
    .transpose();
    let (x, y, z, w) = (q.x_axis, q.y_axis, q.z_axis, q.w_axis);
    let x2 = x + x;
    let y2 = y + y;
    let z2 = z + z;
    let xx = x * x2;
    let xy = x * y2;
    let xz = x * z2;
    let yy = y * y2;
    let yz = y * z2;
    let zz = z * z2;
    let wx = w * x2;
    let wy = w * y2;
    let wz = w * z2;
    let one = Vec4::ONE;
    let zero = Vec4::ZERO;
    // Rows of each column (x, y, z, w components), scaled as `axis * scale`.
    let x_axis = Mat4::from_cols(
        (one - (yy + zz)) * s.x_axis,
        (xy + wz) * s.x_axis,
        (xz - wy) * s.x_axis,
        zero * s.x_axis,
    )
    .transpose();
    let y_axis = Mat4::from_cols(
        (xy - wz) * s.y_axis,
        (one - (xx + zz)) * s.y_axis,
        (yz + wx) * s.y_axis,
        zero * s.y_axis,
    )
    .transpose();
    let z_axis = Mat4::from_cols(
        (xz + wy) * s.z_axis,
        (yz - wx) * s.z_axis,
        (one - (xx + yy)) * s.z_axis,
        zero * s.z_axis,
    )
    .transpose();
    let t = |v: &Transform| v.translation.extend(1.0);
    [
        Mat4::from_cols(x_axis.x_axis, y_axis.x_axis, z_axis.x_axis, t(&a)),
        Mat4::from_cols(x_axis.y_axis, y_axis.y_axis, z_axis.y_axis, t(&b)),
        Mat4::from_cols(x_axis.z_axis, y_axis.z_axis, z_axis.z_axis, t(&c)),
        Mat4::from_cols(x_axis.w_axis, y_axis.w_axis, z_axis.w_axis, t(&d)),
    ]
}

/// Skinning matrices `M_j = W_j · B_j⁻¹` (seed 001's `T_j`), into `skinning`.
///
/// # Panics
/// When a buffer does not have one entry per joint (a caller bug, as above).
pub fn skinning_matrices(skeleton: &Skeleton, world: &[Mat4], skinning: &mut [Mat4]) {
    let n = skeleton.len();
    assert!(
        world.len() == n && skinning.len() == n,
        "pose buffers must have {n} joints"
    );
    for ((m, w), ib) in skinning.iter_mut().zip(world).zip(skeleton.inverse_bind()) {
        *m = *w * *ib;
    }
}

/// Reusable buffers for posing one skeleton: world and skinning matrices.
#[derive(Clone, Debug)]
pub struct PoseBuffers {
    /// World (model-space) matrices `W_j`, one per joint.
    pub world: Vec<Mat4>,
    /// Skinning matrices `M_j = W_j · B_j⁻¹`, one per joint.
    pub skinning: Vec<Mat4>,
}

impl PoseBuffers {
    /// Buffers sized for `skeleton`, every matrix the identity.
    #[must_use]
    pub fn new(skeleton: &Skeleton) -> Self {
        Self {
            world: vec![Mat4::IDENTITY; skeleton.len()],
            skinning: vec![Mat4::IDENTITY; skeleton.len()],
        }
    }

    /// Runs FK then the skinning matrices for `locals`.
    pub fn update(&mut self, skeleton: &Skeleton, locals: &[Transform]) {
        forward_kinematics(skeleton, locals, &mut self.world);
        skinning_matrices(skeleton, &self.world, &mut self.skinning);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::{arb_skeleton, arb_transforms, mat_close};
    use proptest::prelude::*;

    /// Independent reference: recursion from each joint up to its root.
    fn world_recursive(s: &Skeleton, locals: &[Transform], j: usize) -> Mat4 {
        let local = locals[j].to_mat4();
        match s.parents()[j] {
            Some(p) => world_recursive(s, locals, p) * local,
            None => local,
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]
        #[test]
        fn grouped_locals_are_to_mat4_bit_for_bit(locals in arb_transforms(7)) {
            for group in locals.chunks(4) {
                for (m, t) in local_matrices(group).iter().zip(group) {
                    let expected = t.to_mat4();
                    prop_assert_eq!(
                        m.to_cols_array().map(f32::to_bits),
                        expected.to_cols_array().map(f32::to_bits)
                    );
                }
            }
        }

        #[test]
        fn fk_matches_recursive((s, locals) in arb_skeleton(1..200).prop_flat_map(|s| {
            let n = s.len();
            (Just(s), arb_transforms(n))
        })) {
            let mut world = vec![Mat4::IDENTITY; s.len()];
            forward_kinematics(&s, &locals, &mut world);
            for (j, w) in world.iter().enumerate() {
                let expected = world_recursive(&s, &locals, j);
                prop_assert!(mat_close(w, &expected, 1e-4), "joint {j}: {w:?} vs {expected:?}");
            }
        }
    }
}
