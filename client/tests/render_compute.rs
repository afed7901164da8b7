//! Compute skinning against the CPU reference `posecast_proto::skinning::skin_cpu`.
//!
//! Mesh sources plug into `render_support::check_compute_matches_cpu(gpu, skeleton, mesh,
//! poses)`: random rigs with tube meshes, the procedural figure, a mesh with more than four
//! influences; the glTF rigs of ../shared/testdata and the built-in avatar join once the
//! importers land.
// Helpers outside #[test] functions are test code too.
#![allow(clippy::unwrap_used)]

mod render_support;

use glam::{Quat, Vec3};
use posecast_client::render::procedural::{TubeOptions, figure_pose, figure_skeleton, tube_mesh};
use posecast_client::render::{ComputeSkinner, Gpu, RenderError};
use posecast_proto::testing::{arb_skeleton, arb_transforms};
use posecast_proto::{SkinnedMesh, Transform};
use proptest::prelude::*;
use render_support::{check_compute_matches_cpu, gpu, skinning_of};

proptest! {
    #![proptest_config(ProptestConfig::with_cases(24))]
    /// Random trees (forests, long chains, scaled joints) with a tube around every bone, three
    /// random poses each (rotations anywhere, non-uniform scale 0.8–1.25).
    #[test]
    fn compute_matches_cpu_on_random_rigs(
        (skeleton, poses) in arb_skeleton(2..48).prop_flat_map(|s| {
            let n = s.len();
            (Just(s), prop::collection::vec(arb_transforms(n), 3))
        }),
    ) {
        let Some(gpu) = gpu() else { return Ok(()) };
        let mesh = tube_mesh(&skeleton, &TubeOptions { sides: 6, rings: 4, radius: 0.2 }).unwrap();
        prop_assume!(mesh.vertex_count() > 0);
        let agreement = check_compute_matches_cpu(gpu, &skeleton, &mesh, &poses);
        prop_assert!(agreement.is_ok(), "{}", agreement.unwrap_err());
    }
}

/// The procedural figure: every vertex has four non-zero influences near joints; poses along
/// a stride plus the rest pose.
#[test]
fn compute_matches_cpu_on_figure() {
    let Some(gpu) = gpu() else { return };
    let skeleton = figure_skeleton();
    let mesh = tube_mesh(&skeleton, &TubeOptions::default()).unwrap();
    let four = mesh
        .weights()
        .chunks_exact(4)
        .filter(|w| w.iter().all(|&x| x > 0.0))
        .count();
    assert!(
        four > 0,
        "the figure should have vertices with four real influences"
    );
    let mut poses = vec![skeleton.rest().to_vec()];
    poses.extend((0..5).map(|i| figure_pose(&skeleton, i as f32 * 1.3)));
    let agreement = check_compute_matches_cpu(gpu, &skeleton, &mesh, &poses).unwrap();
    eprintln!("figure: {agreement:?}");
}

/// Six influences per vertex: the GPU gets the four heaviest, renormalised, and must match the
/// CPU skinning of that same reduction; the reduction itself stays close to the full blend
/// when the dropped weights are small.
#[test]
fn more_than_four_influences_are_reduced() {
    let Some(gpu) = gpu() else { return };
    let skeleton = figure_skeleton();
    let base = tube_mesh(&skeleton, &TubeOptions::default()).unwrap();
    let n = skeleton.len() as u16;
    let mut joints = Vec::new();
    let mut weights = Vec::new();
    for (v, (j, w)) in base
        .joints()
        .chunks_exact(4)
        .zip(base.weights().chunks_exact(4))
        .enumerate()
    {
        joints.extend_from_slice(j);
        joints.extend([(v as u16 * 7) % n, (v as u16 * 11 + 3) % n]);
        weights.extend_from_slice(w);
        weights.extend([0.01, 0.005]);
    }
    let six = SkinnedMesh::new(
        base.positions().to_vec(),
        base.normals().to_vec(),
        base.indices().to_vec(),
        6,
        joints,
        weights,
        skeleton.len(),
    )
    .unwrap();
    let poses: Vec<Vec<Transform>> = (0..3).map(|i| figure_pose(&skeleton, i as f32)).collect();
    check_compute_matches_cpu(gpu, &skeleton, &six, &poses).unwrap();
}

/// A pose with non-uniform scale on a joint: normals must follow the inverse-transpose, not the
/// matrix itself (the two differ only under non-uniform scale or blending).
#[test]
fn normals_follow_the_inverse_transpose_under_scale() {
    let Some(gpu) = gpu() else { return };
    let skeleton = figure_skeleton();
    let mesh = tube_mesh(&skeleton, &TubeOptions::default()).unwrap();
    let mut pose = figure_pose(&skeleton, 0.7);
    for (j, local) in pose.iter_mut().enumerate() {
        local.scale = Vec3::new(1.0 + 0.1 * (j % 3) as f32, 0.7, 1.3);
        local.rotation = Quat::from_rotation_z(0.1 * j as f32) * local.rotation;
    }
    check_compute_matches_cpu(gpu, &skeleton, &mesh, &[pose]).unwrap();
}

/// Too few skinning matrices is an error, not a panic or an out-of-bounds read.
#[test]
fn too_few_matrices_is_an_error() {
    let Some(gpu) = gpu() else { return };
    let skeleton = figure_skeleton();
    let mesh = tube_mesh(&skeleton, &TubeOptions::default()).unwrap();
    let mut skinner = ComputeSkinner::new(gpu, &mesh).unwrap();
    let skinning = skinning_of(&skeleton, skeleton.rest());
    let result = skinner.skin(&skinning[..3]);
    assert!(
        matches!(result, Err(RenderError::Length { actual: 3, .. })),
        "{result:?}"
    );
    // The skinner still works afterwards.
    assert_eq!(
        skinner.skin(&skinning).unwrap().0.len(),
        mesh.vertex_count()
    );
}

/// An instance with no backends finds no adapter: a typed error, not a panic.
#[test]
fn no_adapter_is_a_typed_error() {
    let instance = wgpu::Instance::new(wgpu::InstanceDescriptor {
        backends: wgpu::Backends::empty(),
        ..wgpu::InstanceDescriptor::new_without_display_handle()
    });
    let result = pollster::block_on(Gpu::with_instance(instance, None));
    assert!(
        matches!(result, Err(RenderError::NoAdapter { .. })),
        "{result:?}"
    );
    let message = result.unwrap_err().to_string();
    assert!(message.contains("mesa-vulkan-drivers"), "{message}");
}
