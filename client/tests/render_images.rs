//! Rendered pictures: vertex-shader skinning against CPU-skinned vertices drawn with an identity
//! skin, the compute drawing path against the vertex path, offscreen read-back, several
//! avatars, and the skeleton overlay.
// Helpers outside #[test] functions are test code too.
#![allow(clippy::unwrap_used)]

mod render_support;

use glam::{Mat4, Vec3};
use posecast_client::render::image::check_images;
use posecast_client::render::procedural::{TubeOptions, figure_pose, figure_skeleton, tube_mesh};
use posecast_client::render::{
    Aabb, Camera, Gpu, Offscreen, RenderError, Renderer, RendererOptions, RgbaImage, SkinningPath,
    Tolerance,
};
use posecast_proto::fk::PoseBuffers;
use posecast_proto::skinning::skin_cpu;
use posecast_proto::{Skeleton, SkinnedMesh, Transform};
use render_support::{golden, gpu};

const SIZE: (u32, u32) = (256, 256);

/// Two renders of the same triangles whose vertices differ only by f32 rounding (~1e-7 of the
/// model size, far below a pixel) rasterise to the same pixels except where a pixel centre lies
/// within that rounding of a triangle edge; shading differs by at most an 8-bit step from
/// rounding of normals. So: mean difference under 0.5 of an 8-bit step per channel, and at most
/// 0.5 % of pixels off by more than 24 steps (edge pixels flipping between figure and
/// background). A real skinning error (see `comparison_detects_a_different_pose`) moves whole
/// limbs and exceeds both limits by far.
const SAME_GEOMETRY: Tolerance = Tolerance {
    mean: 0.5,
    outlier_threshold: 24,
    outlier_fraction: 0.005,
};

fn identity_skeleton() -> Skeleton {
    Skeleton::new(
        vec!["root".into()],
        vec![None],
        vec![Transform::IDENTITY],
        vec![Mat4::IDENTITY],
    )
    .unwrap()
}

/// The mesh skinned on the CPU (`skin_cpu`), bound rigidly to one joint whose skinning matrix
/// is exactly the identity.
fn cpu_skinned(skeleton: &Skeleton, mesh: &SkinnedMesh, pose: &[Transform]) -> SkinnedMesh {
    let mut buffers = PoseBuffers::new(skeleton);
    buffers.update(skeleton, pose);
    let n = mesh.vertex_count();
    let mut p = vec![Vec3::ZERO; n];
    let mut normals = vec![Vec3::ZERO; n];
    skin_cpu(mesh, &buffers.skinning, &mut p, &mut normals);
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

fn options(skinning: SkinningPath) -> RendererOptions {
    RendererOptions {
        skinning,
        // The grid follows the scene's conservative bounds, which differ between a skinned
        // avatar and its pre-skinned copy; these comparisons are about the avatar.
        grid: false,
        auto_frame: false,
        ..RendererOptions::default()
    }
}

fn render(
    gpu: &Gpu,
    options: RendererOptions,
    camera: Camera,
    avatars: &[(Skeleton, SkinnedMesh, Vec<Transform>)],
) -> RgbaImage {
    let target = Offscreen::new(gpu, SIZE.0, SIZE.1).unwrap();
    let mut renderer = Renderer::new(gpu, Offscreen::FORMAT, SIZE.0, SIZE.1, options).unwrap();
    for (skeleton, mesh, pose) in avatars {
        let handle = renderer.add_avatar(skeleton, mesh).unwrap();
        renderer.set_pose(handle, pose).unwrap();
    }
    renderer.set_camera(camera);
    target.render(&mut renderer).unwrap()
}

/// The figure mid-stride, its CPU-skinned twin, and a camera framing the exact skinned bounds.
fn figure_scene(phase: f32) -> (Skeleton, SkinnedMesh, Vec<Transform>, SkinnedMesh, Camera) {
    let skeleton = figure_skeleton();
    let mesh = tube_mesh(&skeleton, &TubeOptions::default()).unwrap();
    let pose = figure_pose(&skeleton, phase);
    let twin = cpu_skinned(&skeleton, &mesh, &pose);
    let bounds = Aabb::from_points(twin.positions().iter().copied()).unwrap();
    let camera = Camera::framing(&bounds, SIZE.0 as f32 / SIZE.1 as f32);
    (skeleton, mesh, pose, twin, camera)
}

fn failure_path(name: &str) -> std::path::PathBuf {
    golden(name)
}

#[test]
fn vertex_shader_skinning_matches_cpu_skinned_mesh() {
    let Some(gpu) = gpu() else { return };
    let (skeleton, mesh, pose, twin, camera) = figure_scene(0.9);
    let gpu_skinned = render(
        gpu,
        options(SkinningPath::VertexShader),
        camera,
        &[(skeleton, mesh, pose)],
    );
    let identity = identity_skeleton();
    let rest = identity.rest().to_vec();
    let cpu = render(
        gpu,
        options(SkinningPath::VertexShader),
        camera,
        &[(identity, twin, rest)],
    );
    let background = gpu_skinned.pixel(0, 0).unwrap();
    let coverage = cpu.coverage([background[0], background[1], background[2]], 8);
    assert!(
        coverage > 0.05,
        "the figure covers only {:.1}% of the image",
        coverage * 100.0
    );
    let diff = check_images(
        &gpu_skinned,
        &cpu,
        &failure_path("vertex-vs-cpu.png"),
        &SAME_GEOMETRY,
    )
    .unwrap();
    eprintln!(
        "vertex vs CPU: mean {:.4}, max {}, outliers {:.4}%",
        diff.mean,
        diff.max,
        diff.outlier_fraction * 100.0
    );
}

#[test]
fn compute_drawing_matches_vertex_drawing() {
    let Some(gpu) = gpu() else { return };
    let (skeleton, mesh, pose, _, camera) = figure_scene(2.1);
    let scene = [(skeleton, mesh, pose)];
    let vertex = render(gpu, options(SkinningPath::VertexShader), camera, &scene);
    let compute = render(gpu, options(SkinningPath::Compute), camera, &scene);
    let diff = check_images(
        &compute,
        &vertex,
        &failure_path("compute-vs-vertex.png"),
        &SAME_GEOMETRY,
    )
    .unwrap();
    eprintln!("compute vs vertex: mean {:.4}, max {}", diff.mean, diff.max);
}

/// Negative control: the comparison above is sharp enough to see a different pose.
#[test]
fn comparison_detects_a_different_pose() {
    let Some(gpu) = gpu() else { return };
    let (skeleton, mesh, pose, _, camera) = figure_scene(0.9);
    let other = figure_pose(&skeleton, 1.4);
    let a = render(
        gpu,
        options(SkinningPath::VertexShader),
        camera,
        &[(skeleton.clone(), mesh.clone(), pose)],
    );
    let b = render(
        gpu,
        options(SkinningPath::VertexShader),
        camera,
        &[(skeleton, mesh, other)],
    );
    let diff = a.compare(&b, SAME_GEOMETRY.outlier_threshold).unwrap();
    assert!(
        diff.mean > SAME_GEOMETRY.mean && diff.outlier_fraction > SAME_GEOMETRY.outlier_fraction,
        "a different pose should fail the tolerance: {diff:?}"
    );
}

/// sRGB encoding of a linear value, as the sRGB render target does it.
fn srgb_byte(linear: f32) -> u8 {
    let s = if linear <= 0.003_130_8 {
        12.92 * linear
    } else {
        1.055 * linear.powf(1.0 / 2.4) - 0.055
    };
    (s * 255.0).round() as u8
}

/// Odd sizes need padded rows on read-back (256-byte alignment); every pixel must come back
/// as the background colour, with no padding bytes or shifted rows.
#[test]
fn offscreen_readback_removes_row_padding() {
    let Some(gpu) = gpu() else { return };
    let background = Vec3::new(0.2, 0.5, 0.8);
    for (w, h) in [(77, 33), (64, 1), (1, 9)] {
        let target = Offscreen::new(gpu, w, h).unwrap();
        let mut renderer = Renderer::new(
            gpu,
            Offscreen::FORMAT,
            w,
            h,
            RendererOptions {
                grid: false,
                background,
                ..RendererOptions::default()
            },
        )
        .unwrap();
        let image = target.render(&mut renderer).unwrap();
        assert_eq!((image.width(), image.height()), (w, h));
        let expected = [srgb_byte(0.2), srgb_byte(0.5), srgb_byte(0.8), 255];
        for (i, px) in image.pixels().chunks_exact(4).enumerate() {
            let close = px.iter().zip(expected).all(|(a, b)| a.abs_diff(b) <= 1);
            assert!(close, "{w}×{h} pixel {i}: {px:?}, expected {expected:?}");
        }
    }
    assert!(matches!(
        Offscreen::new(gpu, 0, 10),
        Err(RenderError::ImageSize { .. })
    ));
}

/// Two avatars side by side; removing one leaves the other; bad handles and pose lengths are
/// errors.
#[test]
fn avatars_are_added_posed_and_removed() {
    let Some(gpu) = gpu() else { return };
    let skeleton = figure_skeleton();
    let mesh = tube_mesh(&skeleton, &TubeOptions::default()).unwrap();
    let target = Offscreen::new(gpu, SIZE.0, SIZE.1).unwrap();
    let mut renderer = Renderer::new(
        gpu,
        Offscreen::FORMAT,
        SIZE.0,
        SIZE.1,
        RendererOptions {
            grid: false,
            auto_frame: false,
            ..RendererOptions::default()
        },
    )
    .unwrap();
    let left = renderer.add_avatar(&skeleton, &mesh).unwrap();
    let right = renderer.add_avatar(&skeleton, &mesh).unwrap();
    let mut pose = figure_pose(&skeleton, 0.0);
    pose[0].translation.x -= 0.6;
    renderer.set_pose(left, &pose).unwrap();
    pose[0].translation.x += 1.2;
    renderer.set_pose(right, &pose).unwrap();
    renderer.frame_all();
    let bounds = renderer.scene_bounds().unwrap();
    assert!(bounds.min.x < -0.6 && bounds.max.x > 0.6, "{bounds:?}");
    let both = target.render(&mut renderer).unwrap();
    let bg = both.pixel(0, 0).unwrap();
    let bg = [bg[0], bg[1], bg[2]];
    renderer.remove_avatar(right).unwrap();
    let one = target.render(&mut renderer).unwrap();
    let (c2, c1) = (both.coverage(bg, 8), one.coverage(bg, 8));
    assert!(
        c1 > 0.01 && c2 > 1.6 * c1,
        "coverage with two avatars {c2}, with one {c1}"
    );
    assert!(matches!(
        renderer.set_pose(right, &pose),
        Err(RenderError::UnknownAvatar { .. })
    ));
    assert!(matches!(
        renderer.set_pose(left, &pose[..3]),
        Err(RenderError::Length {
            expected: 21,
            actual: 3,
            ..
        })
    ));
    assert!(renderer.remove_avatar(right).is_err());
    assert_eq!(renderer.avatars().collect::<Vec<_>>(), vec![left]);
}

/// With the overlay on, bone-coloured pixels appear; without it, none.
#[test]
fn skeleton_overlay_draws_bones() {
    let Some(gpu) = gpu() else { return };
    let (skeleton, mesh, pose, _, camera) = figure_scene(0.5);
    let scene = [(skeleton, mesh, pose)];
    let bones = |image: &RgbaImage| {
        image
            .pixels()
            .chunks_exact(4)
            .filter(|p| p[0] > 240 && p[1] > 220 && p[2] < 100)
            .count()
    };
    let plain = render(gpu, options(SkinningPath::VertexShader), camera, &scene);
    let overlay = render(
        gpu,
        RendererOptions {
            skeleton_overlay: true,
            ..options(SkinningPath::VertexShader)
        },
        camera,
        &scene,
    );
    assert_eq!(bones(&plain), 0);
    assert!(
        bones(&overlay) > 200,
        "only {} bone pixels",
        bones(&overlay)
    );
}
