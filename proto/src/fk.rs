//! Forward kinematics and skinning matrices (DESIGN.md "Conventions"; seed 001).

use crate::skeleton::Skeleton;
use crate::transform::Transform;
use glam::Mat4;

/// World (model-space) matrices from local transforms: `W_j = W_parent(j) · D_j`, `W_root = D_root`,
/// with `D_j = T(t_j) · R_j · S_j`.
///
/// One forward loop over joints (parents precede children by construction of [`Skeleton`]);
/// writes into `world` and allocates nothing.
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
    for j in 0..n {
        let local = locals[j].to_mat4();
        world[j] = match skeleton.parents()[j] {
            Some(p) => world[p] * local,
            None => local,
        };
    }
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
