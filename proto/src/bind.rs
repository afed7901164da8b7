//! Seed 001's world-space increment of a joint. With `W_j = W_parent(j) · D_j`, where the local
//! transform `D_j = L_j · Ul_j` is the rest-local times the user transform, turning joint `j` by
//! a world-space `U` (`W'_j = U · W_j`) means the local `D'_j = W_parent(j)⁻¹ · U · W_j`.
//!
//! `W_parent(root)` is the identity; pass `Mat4::IDENTITY` for roots.

use glam::{Mat4, Quat, Vec3};

/// The local transform that applies the world-space increment `U` to a joint (so that
/// `W'_j = U · W_j`), for a rig whose local transform is one matrix `D_j = L_j · Ul_j` (as
/// posecast's poses are): `D'_j = W_parent(j)⁻¹ · U · W_j`.
#[must_use]
pub fn world_increment_local(world_parent: Mat4, increment: Mat4, world: Mat4) -> Mat4 {
    world_parent.inverse() * increment * world
}

/// A world-space rotation `q` about the point `pivot` (e.g. a joint's world position):
/// `U = T(pivot) · R(q) · T(−pivot)`. Used with [`world_increment_local`] this rotates a joint
/// in place without moving it.
#[must_use]
pub fn rotation_about(pivot: Vec3, q: Quat) -> Mat4 {
    Mat4::from_translation(pivot) * Mat4::from_quat(q) * Mat4::from_translation(-pivot)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fk::forward_kinematics;
    use crate::testing::f32s;
    use crate::testing::{arb_quat, arb_rigid_skeleton, arb_rigid_transforms, mat_close};
    use crate::transform::Transform;
    use proptest::prelude::*;

    fn parent_world(world: &[Mat4], parent: Option<usize>) -> Mat4 {
        parent.map_or(Mat4::IDENTITY, |p| world[p])
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(48))]

        /// Applying `D'_j = W_p⁻¹ U W_j` gives `W'_j = U W_j`, and moves the subtree rigidly.
        #[test]
        fn world_increment_gives_u_w(
            (s, user) in arb_rigid_skeleton(1..100).prop_flat_map(|s| { let n = s.len(); (Just(s), arb_rigid_transforms(n)) }),
            pick in 0usize..1000,
            q in arb_quat(),
            pivot in prop::array::uniform3(f32s(-1.0..1.0)),
        ) {
            let j = pick % s.len();
            let locals: Vec<Transform> = s.rest().iter().zip(&user)
                .map(|(l, u)| Transform::try_from_mat4(&(l.to_mat4() * u.to_mat4())).unwrap())
                .collect();
            let mut world = vec![Mat4::IDENTITY; s.len()];
            forward_kinematics(&s, &locals, &mut world);
            let u = rotation_about(Vec3::from(pivot), q);
            let wp = parent_world(&world, s.parents()[j]);
            let mut locals2 = locals.clone();
            locals2[j] = Transform::try_from_mat4(&world_increment_local(wp, u, world[j])).unwrap();
            let mut world2 = vec![Mat4::IDENTITY; s.len()];
            forward_kinematics(&s, &locals2, &mut world2);
            prop_assert!(mat_close(&world2[j], &(u * world[j]), 2e-3));
            // The subtree moves rigidly with it: every descendant's W' = U W too.
            for k in j + 1..s.len() {
                let mut a = Some(k);
                while let Some(i) = a.filter(|&i| i != j) {
                    a = s.parents()[i];
                }
                if a == Some(j) {
                    prop_assert!(mat_close(&world2[k], &(u * world[k]), 2e-3), "joint {k}");
                }
            }
        }
    }
}
