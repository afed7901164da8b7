//! Golden image of the procedural figure at a fixed pose, with the ground grid and the
//! auto-framed camera. Bless with `POSECAST_BLESS=1 cargo test -p posecast-client --test
//! render_golden`; on failure `figure-actual.png` and `figure-difference.png` are written next
//! to the golden (git-ignored).
// Helpers outside #[test] functions are test code too.
#![allow(clippy::unwrap_used)]

mod render_support;

use posecast_client::render::image::check_golden;
use posecast_client::render::procedural::{TubeOptions, figure_pose, figure_skeleton, tube_mesh};
use posecast_client::render::{Offscreen, Renderer, RendererOptions, Tolerance};
use render_support::{golden, gpu};

/// The golden was made on lavapipe (llvmpipe, Vulkan). Other GPUs rasterise triangles by the
/// same rules (the grid is shaded per pixel on a ground quad, not drawn as line primitives,
/// whose rasterisation varies far more) but with their own rounding in lighting (fused
/// multiply-add, `pow`, sRGB encoding) and in the derivatives that anti-alias the grid: most
/// pixels then differ by a few 8-bit steps, which the mean limit of 1 step per channel absorbs.
/// Larger differences only arise where a pixel centre lies within sub-pixel precision of a
/// triangle edge; 0.4 % of the image (about 300 pixels, a third of the figure's silhouette) may
/// be off by more than 32 steps. Turning the figure's stride by 0.1 rad already breaks both
/// limits (mean 1.6, 0.48 % outliers), so posing, skinning or camera regressions show.
const ACROSS_GPUS: Tolerance = Tolerance {
    mean: 1.0,
    outlier_threshold: 32,
    outlier_fraction: 0.004,
};

#[test]
fn figure_matches_golden() {
    let Some(gpu) = gpu() else { return };
    let (width, height) = (320, 240);
    let skeleton = figure_skeleton();
    let mesh = tube_mesh(&skeleton, &TubeOptions::default()).unwrap();
    let target = Offscreen::new(gpu, width, height).unwrap();
    let mut renderer = Renderer::new(
        gpu,
        Offscreen::FORMAT,
        width,
        height,
        RendererOptions::default(),
    )
    .unwrap();
    let handle = renderer.add_avatar(&skeleton, &mesh).unwrap();
    renderer
        .set_pose(handle, &figure_pose(&skeleton, 0.8))
        .unwrap();
    let image = target.render(&mut renderer).unwrap();
    check_golden(&image, &golden("figure.png"), &ACROSS_GPUS).unwrap();
}
