//! Faces on the GPU: morph targets (blend shapes) applied before skinning, on both paths,
//! against the CPU reference `posecast_proto::morph::morph_cpu` then `skin_cpu`, on the Ready
//! Player Me avatar of ../shared/testdata as the server serves it (normalised, its `mesh.glb`
//! read by the client's own reader).
// Helpers outside #[test] functions are test code too.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod render_support;

use glam::{Mat4, Quat, Vec3};
use posecast_client::render::glb_mesh::GlbMesh;
use posecast_client::render::image::check_images;
use posecast_client::render::{
    Aabb, Camera, Gpu, Offscreen, RenderError, Renderer, RendererOptions, RgbaImage, SkinningPath,
    Tolerance,
};
use posecast_proto::fk::PoseBuffers;
use posecast_proto::skinning::skin_cpu;
use posecast_proto::testing::require_testdata;
use posecast_proto::{Skeleton, SkinnedMesh, Transform};
use posecast_server::export::mesh_glb;
use posecast_server::import;
use posecast_server::rig::{PipelineOptions, normalise};
use render_support::{check_morphed_compute_matches_cpu, golden, gpu, morphed};

const RPM: &str = "gltf/ReadyPlayerMe/PreviewMesh.glb";
const SIZE: (u32, u32) = (256, 256);

/// As render_images.rs: the same triangles up to f32 rounding rasterise to the same pixels but
/// for edge pixels and 8-bit shading steps.
const SAME_GEOMETRY: Tolerance = Tolerance {
    mean: 0.5,
    outlier_threshold: 24,
    outlier_fraction: 0.005,
};

/// Weights for the avatar's five channels (mouthOpen, mouthSmile, eyesClosed, eyesLookUp,
/// eyesLookDown): every target active, at different strengths.
const WEIGHTS: [f32; 5] = [0.9, 0.6, 1.0, 0.3, 0.2];

/// The normalised Ready Player Me rig and the mesh the client reads from its `mesh.glb`
/// (every primitive merged, one target per channel).
fn rpm() -> Option<(posecast_server::asset::Asset, SkinnedMesh)> {
    let path = require_testdata(RPM)?;
    let asset = import::load_path(&path).unwrap().remove(0);
    let asset = normalise(asset, &PipelineOptions::default()).unwrap().asset;
    let bytes = mesh_glb(&asset.skeleton, &asset.meshes).unwrap();
    let mesh = GlbMesh::from_slice(&bytes)
        .unwrap()
        .for_joints(asset.skeleton.names())
        .unwrap();
    Some((asset, mesh))
}

/// The rest pose and one with the head and spine turned, so morphing happens before skinning
/// moves the face (a morph applied after skinning would displace the wrong way).
fn poses(skeleton: &Skeleton) -> Vec<Vec<Transform>> {
    let rest = skeleton.rest().to_vec();
    let mut turned = rest.clone();
    for (j, name) in skeleton.names().iter().enumerate() {
        if name.contains("Head") || name.contains("Neck") || name.contains("Spine") {
            turned[j].rotation =
                Quat::from_euler(glam::EulerRot::YXZ, 0.5, 0.3, -0.2) * turned[j].rotation;
        }
    }
    vec![rest, turned]
}

/// The client's reader keeps the served targets: for each channel, the displacements of every
/// mesh of the rig that has it, in merge order, and zero on the meshes without it.
#[test]
fn glb_reader_keeps_the_served_morph_targets() {
    let Some((asset, mesh)) = rpm() else { return };
    let names: Vec<&str> = mesh.targets().iter().map(|t| t.name.as_str()).collect();
    assert_eq!(
        names,
        [
            "mouthOpen",
            "mouthSmile",
            "eyesClosed",
            "eyesLookUp",
            "eyesLookDown"
        ]
    );
    for target in mesh.targets() {
        let mut expected = Vec::new();
        for m in &asset.meshes {
            match m.mesh.targets().iter().find(|t| t.name == target.name) {
                Some(t) => expected.extend_from_slice(&t.positions),
                None => expected.extend(std::iter::repeat_n(Vec3::ZERO, m.mesh.vertex_count())),
            }
        }
        assert_eq!(target.positions.len(), expected.len(), "{}", target.name);
        for (v, (a, b)) in target.positions.iter().zip(&expected).enumerate() {
            assert!(
                a.abs_diff_eq(*b, 1e-7),
                "{} vertex {v}: read {a}, rig {b}",
                target.name
            );
        }
        assert!(!target.is_empty(), "{} displaces nothing", target.name);
    }
}

/// Compute path: `morph()` then `skin()` on the GPU against `morph_cpu` then `skin_cpu`, all
/// five targets active, rest and turned poses; the weights move the face by far more than the
/// tolerance, so a GPU that ignored them (or morphed after skinning) fails.
#[test]
fn compute_morphing_matches_cpu() {
    let Some((asset, mesh)) = rpm() else { return };
    let Some(gpu) = gpu() else { return };
    let skeleton = &asset.skeleton;
    let poses = poses(skeleton);
    let moved = max_displacement(&mesh, &WEIGHTS);
    let size = render_support::model_size(mesh.positions());
    assert!(
        moved > 20.0 * 1e-4 * size,
        "the weights move the face only {moved} m"
    );
    let agreement =
        check_morphed_compute_matches_cpu(gpu, skeleton, &mesh, &WEIGHTS, &poses).unwrap();
    eprintln!("morphed compute vs CPU: {agreement:?}, face moved up to {moved} m");
    // Weights change per call: zero again gives the unmorphed mesh.
    check_morphed_compute_matches_cpu(gpu, skeleton, &mesh, &[0.0; 5], &poses).unwrap();
}

/// Bad weights: more than the mesh has are refused; non-finite ones count as 0 (no NaN
/// vertex); targets that could not be uploaded take weights that change nothing; a mesh
/// without targets takes an empty list.
#[test]
fn weights_the_mesh_cannot_take() {
    let Some((asset, mesh)) = rpm() else { return };
    let Some(gpu) = gpu() else { return };
    let mut skinner =
        posecast_client::render::ComputeSkinner::new(gpu, &mesh.with_influences(4)).unwrap();
    assert!(matches!(
        skinner.set_morph_weights(&[0.5; 6]),
        Err(RenderError::Length {
            expected: 5,
            actual: 6,
            ..
        })
    ));
    skinner
        .set_morph_weights(&[f32::NAN, f32::INFINITY, 0.0, 0.0, 0.0])
        .unwrap();
    let skinning = skinning_of(&asset.skeleton, asset.skeleton.rest());
    let (p, _) = skinner.skin(&skinning).unwrap();
    assert!(p.iter().all(|v| v.is_finite()));
    // Targets a device cannot hold (too large for one binding) are drawn without: their
    // weights are still taken, and change nothing.
    let mut ignored = posecast_client::render::GpuMorph::ignoring(&gpu.device, "big", &mesh);
    assert_eq!(ignored.targets(), 5);
    ignored.set_weights(&gpu.queue, &[1.0; 5]).unwrap();
    let bare = mesh.clone().without_targets();
    let mut renderer = renderer(gpu, SkinningPath::VertexShader);
    let handle = renderer.add_avatar(&asset.skeleton, &bare).unwrap();
    assert_eq!(renderer.morph_targets(handle).unwrap(), 0);
    renderer.set_morph_weights(handle, &[]).unwrap();
    assert!(renderer.set_morph_weights(handle, &[1.0]).is_err());
}

/// Vertex-shader path and compute drawing path, with the camera on the face: the morphed
/// avatar drawn by the GPU against the CPU-morphed, CPU-skinned twin drawn with an identity
/// skin; and the negative control that the expression is visible at this framing.
#[test]
fn drawn_faces_match_the_cpu_morphed_mesh() {
    let Some((asset, mesh)) = rpm() else { return };
    let Some(gpu) = gpu() else { return };
    let skeleton = &asset.skeleton;
    // The head turned a little (morphing happens in bind space, before the head's skinning).
    let mut pose = skeleton.rest().to_vec();
    let head = skeleton.names().iter().position(|n| n == "Head").unwrap();
    pose[head].rotation =
        Quat::from_euler(glam::EulerRot::YXZ, 0.35, 0.1, 0.0) * pose[head].rotation;
    let twin = cpu_skinned(skeleton, &morphed(&mesh, &WEIGHTS), &pose);
    let camera = face_camera(skeleton, &mesh, &pose);
    let identity = identity_skeleton();
    let reference = draw(
        gpu,
        SkinningPath::VertexShader,
        camera,
        &identity,
        &twin,
        identity.rest(),
        &[],
    );
    for path in [SkinningPath::VertexShader, SkinningPath::Compute] {
        let drawn = draw(gpu, path, camera, skeleton, &mesh, &pose, &WEIGHTS);
        let diff = check_images(
            &drawn,
            &reference,
            &golden(&format!("morph-{path:?}-vs-cpu.png")),
            &SAME_GEOMETRY,
        )
        .unwrap();
        eprintln!(
            "{path:?} morphing vs CPU: mean {:.4}, max {}",
            diff.mean, diff.max
        );
    }
    let neutral = draw(
        gpu,
        SkinningPath::VertexShader,
        camera,
        skeleton,
        &mesh,
        &pose,
        &[],
    );
    let diff = neutral
        .compare(&reference, SAME_GEOMETRY.outlier_threshold)
        .unwrap();
    if let Ok(dir) = std::env::var("POSECAST_MORPH_IMAGES") {
        let dir = std::path::Path::new(&dir);
        neutral.write_png(&dir.join("neutral.png")).unwrap();
        reference.write_png(&dir.join("expression.png")).unwrap();
    }
    eprintln!(
        "neutral vs expression: mean {:.4}, outliers {:.3}%",
        diff.mean,
        diff.outlier_fraction * 100.0
    );
    assert!(
        diff.mean > SAME_GEOMETRY.mean && diff.outlier_fraction > SAME_GEOMETRY.outlier_fraction,
        "the expression should be visible at this framing: mean {}, outliers {}",
        diff.mean,
        diff.outlier_fraction
    );
}

fn max_displacement(mesh: &SkinnedMesh, weights: &[f32]) -> f32 {
    let m = morphed(mesh, weights);
    m.positions()
        .iter()
        .zip(mesh.positions())
        .map(|(a, b)| (*a - *b).length())
        .fold(0.0, f32::max)
}

/// A camera framing the vertices `WEIGHTS` move most (a quarter of the largest displacement
/// or more: eyelids and mouth), skinned at `pose`, so a centimetre of movement is a tenth of
/// the picture and the avatar's flat colour still shows it.
fn face_camera(skeleton: &Skeleton, mesh: &SkinnedMesh, pose: &[Transform]) -> Camera {
    let skinned = cpu_skinned(skeleton, mesh, pose);
    let moved: Vec<f32> = morphed(mesh, &WEIGHTS)
        .positions()
        .iter()
        .zip(mesh.positions())
        .map(|(a, b)| (*a - *b).length())
        .collect();
    let most = moved.iter().copied().fold(0.0, f32::max);
    let points = skinned
        .positions()
        .iter()
        .zip(&moved)
        .filter(|(_, d)| **d > 0.0 * most)
        .map(|(p, _)| *p);
    let bounds = Aabb::from_points(points).unwrap();
    let mut camera = Camera::framing(&bounds, SIZE.0 as f32 / SIZE.1 as f32);
    // Face on: from in front of the head (the normalised rig faces +Z).
    let distance = (camera.eye - camera.target).length();
    camera.eye = camera.target + Vec3::new(0.15, 0.1, 1.0).normalize() * distance;
    camera
}

fn identity_skeleton() -> Skeleton {
    Skeleton::new(
        vec!["root".into()],
        vec![None],
        vec![Transform::IDENTITY],
        vec![Mat4::IDENTITY],
    )
    .unwrap()
}

fn skinning_of(skeleton: &Skeleton, pose: &[Transform]) -> Vec<Mat4> {
    let mut buffers = PoseBuffers::new(skeleton);
    buffers.update(skeleton, pose);
    buffers.skinning
}

/// The mesh skinned on the CPU, bound rigidly to one joint whose skinning matrix is exactly
/// the identity.
fn cpu_skinned(skeleton: &Skeleton, mesh: &SkinnedMesh, pose: &[Transform]) -> SkinnedMesh {
    let n = mesh.vertex_count();
    let mut p = vec![Vec3::ZERO; n];
    let mut normals = vec![Vec3::ZERO; n];
    skin_cpu(mesh, &skinning_of(skeleton, pose), &mut p, &mut normals);
    SkinnedMesh::new(
        p,
        normals,
        mesh.indices().to_vec(),
        1,
        vec![0; n],
        vec![1.0; n],
        1,
    )
    .unwrap()
}

fn renderer(gpu: &Gpu, skinning: SkinningPath) -> Renderer {
    let options = RendererOptions {
        skinning,
        grid: false,
        auto_frame: false,
        ..RendererOptions::default()
    };
    Renderer::new(gpu, Offscreen::FORMAT, SIZE.0, SIZE.1, options).unwrap()
}

fn draw(
    gpu: &Gpu,
    path: SkinningPath,
    camera: Camera,
    skeleton: &Skeleton,
    mesh: &SkinnedMesh,
    pose: &[Transform],
    weights: &[f32],
) -> RgbaImage {
    let target = Offscreen::new(gpu, SIZE.0, SIZE.1).unwrap();
    let mut renderer = renderer(gpu, path);
    let handle = renderer.add_avatar(skeleton, mesh).unwrap();
    renderer.set_pose(handle, pose).unwrap();
    renderer.set_morph_weights(handle, weights).unwrap();
    renderer.set_camera(camera);
    target.render(&mut renderer).unwrap()
}
