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
/// same rules but with their own sub-pixel precision, and evaluate lighting with their own
/// rounding (fused multiply-add, `pow`, sRGB encoding): interior pixels then differ by a few
/// 8-bit steps, and pixels on silhouettes and grid lines can change a lot. So: a mean under 1.5
/// steps per channel, and at most 1.5 % of the pixels off by more than 32 steps (the figure's
/// silhouette alone is about 3 % of this image). Moving a limb, a wrong normal, or a shifted
/// camera each break both limits.
const ACROSS_GPUS: Tolerance = Tolerance {
    mean: 1.5,
    outlier_threshold: 32,
    outlier_fraction: 0.015,
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
