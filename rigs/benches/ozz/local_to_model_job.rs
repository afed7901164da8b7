//! ozz's `LocalToModelJob` (`src/animation/runtime/local_to_model_job.cc`): SoA local
//! transforms to model-space matrices, `M_i = M_parent(i) · L_i` (`M_root = root · L_root`), in
//! joint order; parents precede children.

use glam::Mat4;

use super::simd::{SoaFloat4x4, SoaTransform, mul_mat4, transpose16x16};

/// `Skeleton::kNoParent`.
pub const NO_PARENT: i16 = -1;

/// `LocalToModelJob::Run` over the whole skeleton (`from = kNoParent`, `to = kMaxJoints`,
/// `from_excluded = false`, no root matrix). `parents[i]` is joint `i`'s parent or
/// [`NO_PARENT`]; `input` holds one SoA transform per four joints. False when a buffer is too
/// small (`Validate`).
pub fn run(parents: &[i16], input: &[SoaTransform], output: &mut [Mat4]) -> bool {
    let num_joints = parents.len();
    if input.len() < num_joints.div_ceil(4) || output.len() < num_joints {
        return false;
    }
    let root_matrix = Mat4::IDENTITY;
    let from = i32::from(NO_PARENT);
    let end = num_joints;
    let mut i = 0usize;
    let mut process = i < end;
    while process {
        let transform = &input[i / 4];
        let local_soa_matrices = SoaFloat4x4::from_affine(
            &transform.translation,
            &transform.rotation,
            &transform.scale,
        );
        let local_aos_matrices = transpose16x16(&local_soa_matrices);
        let soa_end = (i + 4) & !3;
        while i < soa_end && process {
            let parent = parents[i];
            let parent_matrix = if parent == NO_PARENT {
                root_matrix
            } else {
                output[parent as usize]
            };
            output[i] = mul_mat4(&parent_matrix, &local_aos_matrices[i & 3]);
            i += 1;
            process = i < end && i32::from(parents[i]) >= from;
        }
    }
    true
}
