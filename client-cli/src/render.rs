//! `render`: connect, take each avatar's streamed pose — or, with `--clip`/`--seek`, the pose of
//! a private copy playing that clip at that time (`sample_pose`, which changes nothing others
//! see) — render offscreen and write a PNG.

use super::Connection;
use anyhow::{Context as _, bail};
use clap::Args;
use posecast_client::render::glb_mesh::GlbMesh;
use posecast_client::render::{Gpu, Offscreen, Renderer, RendererOptions, RgbaImage, SkinningPath};
use posecast_client::view_source::{fresh_pose, resolve_mesh, target_weights, wait_for_avatars};
use posecast_proto::Transform;
use posecast_proto::command::{Command, CommandResult};
use posecast_proto::msg::{AvatarId, AvatarPoseJson};
use posecast_proto::placement::Placement;
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

#[derive(Debug, Args)]
pub struct RenderArgs {
    #[command(flatten)]
    connection: Connection,
    /// The avatar to show at `--clip`/`--seek` (default: every avatar of the scene).
    #[arg(long, env = "POSECAST_AVATAR")]
    avatar: Option<String>,
    /// Show this clip (at `--seek`, default its start) instead of the streamed pose; sampled
    /// on a private copy of the avatar, so other viewers see no change.
    #[arg(long, env = "POSECAST_CLIP")]
    clip: Option<String>,
    /// Show the clip (`--clip`, default the avatar's current one) at this time, seconds from
    /// its start, on a private copy of the avatar.
    #[arg(long, env = "POSECAST_SEEK")]
    seek: Option<f32>,
    /// Image width, pixels.
    #[arg(long, env = "POSECAST_WIDTH", default_value_t = 640)]
    width: u32,
    /// Image height, pixels.
    #[arg(long, env = "POSECAST_HEIGHT", default_value_t = 480)]
    height: u32,
    /// Where to write the PNG.
    #[arg(long, env = "POSECAST_OUT", default_value = "out.png")]
    out: PathBuf,
    /// A `.glb` with the avatar's skinned mesh, used when the server serves none.
    #[arg(long, env = "POSECAST_MESH")]
    mesh: Option<PathBuf>,
    /// Skin in a compute pass instead of the vertex shader.
    #[arg(long, env = "POSECAST_COMPUTE_SKINNING")]
    compute: bool,
    /// Frames rendered for the frame-time figure (after the first, which compiles pipelines).
    #[arg(long, env = "POSECAST_TIMED_FRAMES", default_value_t = 10)]
    timed_frames: u32,
}

/// Reads a `--mesh` file.
pub fn read_mesh(path: &Path) -> anyhow::Result<GlbMesh> {
    let bytes = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
    GlbMesh::from_slice(&bytes).with_context(|| format!("reading a mesh from {}", path.display()))
}

const WAIT: Duration = Duration::from_secs(10);

pub async fn run(args: RenderArgs) -> anyhow::Result<()> {
    let fallback = args.mesh.as_deref().map(read_mesh).transpose()?;
    // Fail before connecting when there is no GPU at all.
    let gpu = Gpu::headless()?;
    let client = args.connection.connect(false).await?;
    let wanted = args.avatar.clone().map(AvatarId);
    let views = wait_for_avatars(&client, wanted.as_ref(), WAIT)
        .await
        .context("waiting for the scene's avatars")?;
    let targets: Vec<AvatarId> = match &wanted {
        Some(id) => vec![id.clone()],
        None => views.iter().map(|v| v.description.id.clone()).collect(),
    };
    // `--clip`/`--seek` render a private copy of each target (`sample_pose`, read-only): what
    // other viewers see does not change, and a view token is enough.
    let mut sampled: HashMap<AvatarId, (Vec<Transform>, Placement, Vec<f32>)> = HashMap::new();
    if args.clip.is_some() || args.seek.is_some() {
        for avatar in &targets {
            let command = Command::SamplePose {
                avatar: avatar.clone(),
                clip: args.clip.clone(),
                from_asset: None,
                time: args.seek.unwrap_or(0.0),
            };
            let result = client
                .command(command)
                .await
                .with_context(|| format!("sampling {avatar}"))?;
            let CommandResult::Pose(pose) = result else {
                bail!("sample_pose of {avatar} answered {result:?}, not a pose");
            };
            let pose: AvatarPoseJson = *pose;
            let view = views
                .iter()
                .find(|v| &v.description.id == avatar)
                .with_context(|| format!("no description of {avatar}"))?;
            let locals = view
                .locals_of(&pose)
                .with_context(|| format!("the pose of {avatar} does not fit its description"))?;
            let weights = view
                .description
                .morph_targets
                .iter()
                .map(|c| pose.weights.get(c).copied().unwrap_or(0.0))
                .collect();
            sampled.insert(avatar.clone(), (locals, pose.placement, weights));
        }
    }
    let mut renderer = Renderer::new(
        &gpu,
        Offscreen::FORMAT,
        args.width,
        args.height,
        RendererOptions {
            skinning: if args.compute {
                SkinningPath::Compute
            } else {
                SkinningPath::VertexShader
            },
            ..RendererOptions::default()
        },
    )?;
    let target = Offscreen::new(&gpu, args.width, args.height)?;
    for view in &views {
        let id = &view.description.id;
        let (locals, placement, weights, what) = match sampled.remove(id) {
            Some((locals, placement, weights)) => {
                (locals, placement, weights, "sampled privately".to_owned())
            }
            None => {
                let seen = client.latest(id).map_or(0, |s| s.seq);
                let pose = fresh_pose(&client, id, seen, WAIT)
                    .await
                    .with_context(|| format!("waiting for a pose of {id}"))?;
                (
                    pose.locals,
                    pose.placement,
                    pose.weights,
                    format!("pose of tick {}", pose.seq),
                )
            }
        };
        let (mesh, origin) = resolve_mesh(view, &args.connection.url, fallback.as_ref()).await;
        eprintln!(
            "{id}: {} joints, {} vertices from {origin}, {what}",
            view.skeleton.len(),
            mesh.vertex_count(),
        );
        let handle = renderer.add_avatar(&view.skeleton, &mesh)?;
        renderer.set_placed_pose(handle, &placement, &locals)?;
        let channels = &view.description.morph_targets;
        renderer.set_morph_weights(handle, &target_weights(&mesh, channels, &weights))?;
    }
    let (image, first, steady) = timed_render(&gpu, &target, &mut renderer, args.timed_frames)?;
    image
        .write_png(&args.out)
        .with_context(|| format!("writing {}", args.out.display()))?;
    println!(
        "wrote {} ({}×{}, {} avatars) on {}: first frame {:.2} ms (pipeline compilation \
         included), then {:.2} ms per frame (render + read-back, mean of {})",
        args.out.display(),
        args.width,
        args.height,
        views.len(),
        gpu.describe(),
        first.as_secs_f64() * 1e3,
        steady.as_secs_f64() * 1e3,
        args.timed_frames,
    );
    Ok(())
}

/// Renders once (timed: includes shader compilation on first use), then `frames` more times
/// and returns the image with both times.
fn timed_render(
    gpu: &Gpu,
    target: &Offscreen,
    renderer: &mut Renderer,
    frames: u32,
) -> anyhow::Result<(RgbaImage, Duration, Duration)> {
    let start = Instant::now();
    let image = target.render(renderer)?;
    let first = start.elapsed();
    let start = Instant::now();
    for _ in 0..frames {
        target.render(renderer)?;
    }
    gpu.wait_idle()?;
    let steady = start.elapsed() / frames.max(1);
    Ok((image, first, steady))
}
