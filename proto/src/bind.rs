//! Seed 001's identities between rest-local (`L_j`), user (`Ul_j`), world (`W_j`), bind (`B_j`)
//! and skinning (`T_j`) matrices, with `W_j = W_parent(j) · L_j · Ul_j` and `B_j = B_parent(j) · L_j`.
//!
//! `W_parent(root)` and `B_parent(root)` are the identity; pass `Mat4::IDENTITY` for roots.

use glam::{Mat4, Quat, Vec3};

/// Local bind transform from world bind matrices: `L_j = B_parent(j)⁻¹ · B_j`.
#[must_use]
pub fn local_bind(bind_parent: Mat4, bind: Mat4) -> Mat4 {
    bind_parent.inverse() * bind
}

/// World matrix from the skinning matrix: `W_j = T_j · B_j`.
#[must_use]
pub fn world_from_skinning(skinning: Mat4, bind: Mat4) -> Mat4 {
    skinning * bind
}

/// User local transform recovered from world matrices: `Ul_j = (W_parent(j) · L_j)⁻¹ · W_j`.
#[must_use]
pub fn user_local(world_parent: Mat4, local_bind: Mat4, world: Mat4) -> Mat4 {
    (world_parent * local_bind).inverse() * world
}

/// New user transform for a world-space increment `U` (so that `W'_j = U · W_j`):
/// `Ul'_j = L_j⁻¹ · W_parent(j)⁻¹ · U · W_j`.
#[must_use]
pub fn world_increment(local_bind: Mat4, world_parent: Mat4, increment: Mat4, world: Mat4) -> Mat4 {
    local_bind.inverse() * world_parent.inverse() * increment * world
}

/// The same increment for a rig whose local transform is one matrix `D_j = L_j · Ul_j` (as
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
    use crate::testing::{
        arb_quat, arb_rigid_skeleton, arb_rigid_transforms, arb_skeleton, arb_transforms, mat_close,
    };
    use crate::transform::Transform;
    use proptest::prelude::*;

    fn parent_world(world: &[Mat4], parent: Option<usize>) -> Mat4 {
        parent.map_or(Mat4::IDENTITY, |p| world[p])
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(48))]

        /// `L_j = B_p⁻¹ B_j` recovers the rest locals, and `W_j = T_j B_j` the world matrices.
        #[test]
        fn local_bind_and_world_from_skinning(
            (s, pose) in arb_skeleton(1..100).prop_flat_map(|s| { let n = s.len(); (Just(s), arb_transforms(n)) }),
        ) {
            let binds = s.bind_matrices();
            let mut world = vec![Mat4::IDENTITY; s.len()];
            forward_kinematics(&s, &pose, &mut world);
            for j in 0..s.len() {
                let l = local_bind(parent_world(&binds, s.parents()[j]), binds[j]);
                prop_assert!(mat_close(&l, &s.rest()[j].to_mat4(), 2e-3));
                let t = world[j] * s.inverse_bind()[j];
                prop_assert!(mat_close(&world_from_skinning(t, binds[j]), &world[j], 2e-3));
            }
        }

        /// `Ul_j = (W_p L_j)⁻¹ W_j` round-trips the user transforms that built `W`.
        #[test]
        fn user_local_round_trips(
            (s, user) in arb_rigid_skeleton(1..100).prop_flat_map(|s| { let n = s.len(); (Just(s), arb_rigid_transforms(n)) }),
        ) {
            let locals: Vec<Transform> = s.rest().iter().zip(&user)
                .map(|(l, u)| Transform::try_from_mat4(&(l.to_mat4() * u.to_mat4())).unwrap())
                .collect();
            let mut world = vec![Mat4::IDENTITY; s.len()];
            forward_kinematics(&s, &locals, &mut world);
            for j in 0..s.len() {
                let ul = user_local(parent_world(&world, s.parents()[j]), s.rest()[j].to_mat4(), world[j]);
                prop_assert!(mat_close(&ul, &user[j].to_mat4(), 2e-3), "joint {j}");
            }
        }

        /// Applying `Ul'_j = L⁻¹ W_p⁻¹ U W_j` gives `W'_j = U W_j`, and moves the subtree rigidly.
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
            let l = s.rest()[j].to_mat4();
            let new_user = world_increment(l, wp, u, world[j]);
            // Both forms agree: D' = L Ul'.
            prop_assert!(mat_close(&(l * new_user), &world_increment_local(wp, u, world[j]), 2e-3));
            let mut locals2 = locals.clone();
            locals2[j] = Transform::try_from_mat4(&(l * new_user)).unwrap();
            let mut world2 = vec![Mat4::IDENTITY; s.len()];
            forward_kinematics(&s, &locals2, &mut world2);
            prop_assert!(mat_close(&world2[j], &(u * world[j]), 2e-3));
        }
    }
}
