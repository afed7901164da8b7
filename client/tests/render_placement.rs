//! Placement in the renderer: three built-in avatars placed 1 m apart along X, drawn offscreen
//! from the front, are three separate silhouettes, each centred where its placement projects.
//! The same avatars with identity placements overlap into one: the count sees the difference.
// Helpers outside #[test] functions are test code too.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod render_support;

use glam::{Mat4, Quat, Vec3};
use posecast_client::render::glb_mesh::GlbMesh;
use posecast_client::render::{Camera, Offscreen, Renderer, RendererOptions, RgbaImage};
use posecast_proto::placement::Placement;
use posecast_server::builtin::AVATAR_GLB;
use render_support::{golden, gpu};

const SIZE: (u32, u32) = (384, 192);
const XS: [f32; 3] = [-1.0, 0.0, 1.0];

/// From the front (+Z, where avatars face), level with the hips: X maps to image columns.
fn camera() -> Camera {
    Camera {
        eye: Vec3::new(0.0, 0.9, 4.5),
        target: Vec3::new(0.0, 0.9, 0.0),
        fov_y: 40f32.to_radians(),
        near: 0.5,
        far: 20.0,
    }
}

/// The built-in avatar at the start of `idle` (arms down: its rest pose is a T-pose spanning
/// more than the 1 m between placements), once per placement.
fn render(placements: &[Placement]) -> RgbaImage {
    let gpu = gpu().expect("checked by the caller");
    let rig = posecast_server::builtin::rig().unwrap();
    let skeleton = rig.skeleton();
    let mesh = GlbMesh::from_slice(AVATAR_GLB)
        .unwrap()
        .for_joints(skeleton.names())
        .unwrap();
    let idle = rig
        .clip("idle")
        .expect("the built-in avatar has an idle clip");
    let mut pose = skeleton.rest().to_vec();
    idle.sample(idle.start(), skeleton.rest(), &mut pose);
    let options = RendererOptions {
        grid: false,
        auto_frame: false,
        ..RendererOptions::default()
    };
    let target = Offscreen::new(gpu, SIZE.0, SIZE.1).unwrap();
    let mut renderer = Renderer::new(gpu, Offscreen::FORMAT, SIZE.0, SIZE.1, options).unwrap();
    for placement in placements {
        let handle = renderer.add_avatar(skeleton, &mesh).unwrap();
        renderer.set_placed_pose(handle, placement, &pose).unwrap();
    }
    renderer.set_camera(camera());
    target.render(&mut renderer).unwrap()
}

/// Connected runs of image columns holding any non-background pixel (the background is the
/// top-left pixel: the grid is off), as `(first, last)` column.
fn silhouettes(image: &RgbaImage) -> Vec<(u32, u32)> {
    let bg = image.pixel(0, 0).unwrap();
    let covered = |x: u32| {
        (0..image.height()).any(|y| {
            let p = image.pixel(x, y).unwrap();
            (0..3).any(|c| p[c].abs_diff(bg[c]) > 4)
        })
    };
    let mut runs: Vec<(u32, u32)> = Vec::new();
    for x in 0..image.width() {
        if !covered(x) {
            continue;
        }
        match runs.last_mut() {
            Some(run) if run.1 + 1 == x => run.1 = x,
            _ => runs.push((x, x)),
        }
    }
    runs
}

/// Image column of a world point through [`camera`].
fn column(view_proj: Mat4, p: Vec3) -> f32 {
    let c = view_proj * p.extend(1.0);
    (c.x / c.w + 1.0) * 0.5 * SIZE.0 as f32
}

#[test]
fn avatars_placed_apart_render_apart() {
    if gpu().is_none() {
        return;
    }
    // Each turned a different way about Y: the rotation is composed too, and a figure with
    // its arms down seen from any side is still centred over where it stands.
    let placements: Vec<Placement> = XS
        .iter()
        .enumerate()
        .map(|(i, &x)| Placement {
            position: Vec3::new(x, 0.0, 0.0),
            rotation: Quat::from_rotation_y(i as f32 * 0.4),
        })
        .collect();
    let image = render(&placements);
    let runs = silhouettes(&image);
    let view_proj = camera().view_proj(SIZE.0 as f32 / SIZE.1 as f32);
    // Hip height: the figure's middle, so perspective moves its silhouette's centre least.
    let expected: Vec<f32> = XS
        .iter()
        .map(|&x| column(view_proj, Vec3::new(x, 0.9, 0.0)))
        .collect();
    eprintln!("silhouettes {runs:?}, placements project to columns {expected:?}");
    let failed = || {
        let path = golden("placement-actual.png");
        image.write_png(&path).ok();
        format!("picture written to {}", path.display())
    };
    assert_eq!(runs.len(), 3, "silhouettes {runs:?}; {}", failed());
    // A tenth of the 1 m spacing on screen: far tighter than a neighbour's place.
    let spacing = expected[1] - expected[0];
    for (run, want) in runs.iter().zip(&expected) {
        let centre = (run.0 + run.1) as f32 * 0.5 + 0.5;
        assert!(
            (centre - want).abs() < 0.1 * spacing,
            "silhouette {run:?} centred at column {centre}, its placement at {want}; {}",
            failed()
        );
    }
}

/// The counterpart: with placement ignored (identity), the three avatars stand in one spot
/// and the same count finds one silhouette.
#[test]
fn unplaced_avatars_overlap_into_one_silhouette() {
    if gpu().is_none() {
        return;
    }
    let runs = silhouettes(&render(&[Placement::IDENTITY; 3]));
    assert_eq!(runs.len(), 1, "silhouettes {runs:?}");
}
