//! Shared by the `render_*` tests: one GPU per test binary, and the CPU-reference comparison a
//! mesh source (random rigs, procedural figures, later the glTF importers) plugs into.
#![allow(dead_code, clippy::expect_used)]

use glam::{Mat3, Mat4, Vec3};
use posecast_client::render::gpu_types::gpu_mesh;
use posecast_client::render::{ComputeSkinner, Gpu, RenderError};
use posecast_proto::fk::PoseBuffers;
use posecast_proto::morph::morph_cpu;
use posecast_proto::skinning::{blend_matrix, skin_cpu};
use posecast_proto::{Skeleton, SkinnedMesh, Transform};
use std::path::PathBuf;
use std::sync::OnceLock;

/// The process-wide GPU, or `None` (after saying so once) when the machine has no adapter at
/// all. Any other failure is a test failure.
///
/// Run with `MESA_SHADER_CACHE_DIR=$PWD/target/mesa-shader-cache` so lavapipe's compiled
/// shaders are cached under `target/` (setting it from here would need `unsafe` `set_var`).
pub fn gpu() -> Option<&'static Gpu> {
    static GPU: OnceLock<Option<Gpu>> = OnceLock::new();
    GPU.get_or_init(|| match Gpu::headless() {
        Ok(gpu) => {
            eprintln!("GPU tests run on {}", gpu.describe());
            Some(gpu)
        }
        Err(RenderError::NoAdapter { reason }) => {
            posecast_proto::testing::skip(&format!(
                "GPU test: no GPU adapter exists on this machine ({reason})"
            ));
            None
        }
        Err(other) => panic!("GPU adapter exists but is unusable: {other}"),
    })
    .as_ref()
}

/// Where goldens live.
pub fn golden(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("tests/golden")
        .join(name)
}

/// Size used to scale position tolerances: f32 error grows with coordinate magnitude, not just
/// with the model's extent, so the larger of the bounds' diagonal and the farthest coordinate.
pub fn model_size(points: &[Vec3]) -> f32 {
    let (lo, hi) = points.iter().fold(
        (Vec3::splat(f32::MAX), Vec3::splat(f32::MIN)),
        |(lo, hi), &p| (lo.min(p), hi.max(p)),
    );
    let far = points
        .iter()
        .fold(0.0f32, |m, p| m.max(p.abs().max_element()));
    (hi - lo).length().max(far).max(1e-6)
}

/// `‖A‖_F ‖A⁻¹‖_F` of a 3×3: how much f32 rounding in the blend can turn a normal.
pub fn condition(m: &Mat3) -> f32 {
    let frob = |m: &Mat3| m.to_cols_array().iter().map(|v| v * v).sum::<f32>().sqrt();
    let det = m.determinant();
    if det.abs() < 1e-30 || !det.is_finite() {
        return f32::INFINITY;
    }
    frob(m) * frob(&m.inverse())
}

/// Result of one comparison, for reporting.
#[derive(Debug, Default)]
pub struct Agreement {
    pub vertices: usize,
    pub worst_position: f32,
    pub worst_normal: f32,
    pub normals_skipped: usize,
}

/// Skins `mesh` on the GPU (compute path) at every pose and checks it against `skin_cpu`:
/// positions within 1e-4 × model size; unit normals within 1e-3 where the blended matrix is
/// well conditioned (condition number ≤ 1e3; near-singular blends have no stable normal in any
/// precision, and both sides then just amplify rounding).
///
/// Meshes with more than four influences are compared on their four-influence reduction, which
/// is what the GPU draws (see `GPU_INFLUENCES`).
pub fn check_compute_matches_cpu(
    gpu: &Gpu,
    skeleton: &Skeleton,
    mesh: &SkinnedMesh,
    poses: &[Vec<Transform>],
) -> Result<Agreement, String> {
    check_morphed_compute_matches_cpu(gpu, skeleton, mesh, &[], poses)
}

/// As [`check_compute_matches_cpu`] with the mesh's morph targets at `weights` (mesh order):
/// the GPU morphs and skins the mesh; the reference is `morph_cpu`'s vertices skinned by
/// `skin_cpu`.
pub fn check_morphed_compute_matches_cpu(
    gpu: &Gpu,
    skeleton: &Skeleton,
    mesh: &SkinnedMesh,
    weights: &[f32],
    poses: &[Vec<Transform>],
) -> Result<Agreement, String> {
    let mut skinner = ComputeSkinner::new(gpu, &gpu_mesh(mesh)).map_err(|e| e.to_string())?;
    skinner
        .set_morph_weights(weights)
        .map_err(|e| e.to_string())?;
    let morphed = morphed(mesh, weights);
    let mesh = gpu_mesh(&morphed);
    let mut buffers = PoseBuffers::new(skeleton);
    let n = mesh.vertex_count();
    let mut cpu_p = vec![Vec3::ZERO; n];
    let mut cpu_n = vec![Vec3::ZERO; n];
    let mut agreement = Agreement {
        vertices: n,
        ..Agreement::default()
    };
    for (pose_index, pose) in poses.iter().enumerate() {
        buffers.update(skeleton, pose);
        skin_cpu(&mesh, &buffers.skinning, &mut cpu_p, &mut cpu_n);
        let (gpu_p, gpu_n) = skinner.skin(&buffers.skinning).map_err(|e| e.to_string())?;
        if gpu_p.len() != n || gpu_n.len() != n {
            return Err(format!(
                "GPU returned {} vertices, expected {n}",
                gpu_p.len()
            ));
        }
        let size = model_size(&cpu_p);
        for v in 0..n {
            let error = (gpu_p[v] - cpu_p[v]).length();
            agreement.worst_position = agreement.worst_position.max(error / size);
            if error.is_nan() || error > 1e-4 * size {
                return Err(format!(
                    "pose {pose_index}, vertex {v}: GPU {} vs CPU {} (error {error:e}, model size \
                     {size})",
                    gpu_p[v], cpu_p[v]
                ));
            }
            let blend = Mat3::from_mat4(blend_matrix(&mesh, &buffers.skinning, v));
            if condition(&blend) > 1e3 {
                agreement.normals_skipped += 1;
                continue;
            }
            let error = (gpu_n[v] - cpu_n[v]).length();
            agreement.worst_normal = agreement.worst_normal.max(error);
            if error.is_nan() || error > 1e-3 {
                return Err(format!(
                    "pose {pose_index}, vertex {v}: GPU normal {} vs CPU {}",
                    gpu_n[v], cpu_n[v]
                ));
            }
        }
    }
    Ok(agreement)
}

/// The mesh's bind-pose vertices morphed by `morph_cpu` at `weights`, as a mesh without
/// targets (what the GPU must draw when it morphs the original).
pub fn morphed(mesh: &SkinnedMesh, weights: &[f32]) -> SkinnedMesh {
    let n = mesh.vertex_count();
    let (mut p, mut normals) = (vec![Vec3::ZERO; n], vec![Vec3::ZERO; n]);
    morph_cpu(mesh, weights, &mut p, &mut normals);
    SkinnedMesh::new(
        p,
        normals,
        mesh.indices().to_vec(),
        mesh.influences(),
        mesh.joints().to_vec(),
        mesh.weights().to_vec(),
        mesh.joints()
            .iter()
            .map(|&j| usize::from(j) + 1)
            .max()
            .unwrap_or(1),
    )
    .expect("a morphed mesh is a mesh")
}

/// Skinning matrices of a pose.
pub fn skinning_of(skeleton: &Skeleton, pose: &[Transform]) -> Vec<Mat4> {
    let mut buffers = PoseBuffers::new(skeleton);
    buffers.update(skeleton, pose);
    buffers.skinning
}
