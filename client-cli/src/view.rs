//! `view`: the scene live in a window.

use super::Connection;
use clap::Args;
use posecast_client::render::glb_mesh::GlbMesh;
use posecast_client::render::{SkinningPath, ViewerOptions, run_viewer};
use posecast_client::view_source::ClientSource;
use std::path::PathBuf;
use std::sync::Arc;

#[derive(Debug, Args)]
pub struct ViewArgs {
    #[command(flatten)]
    connection: Connection,
    /// A `.glb` with the avatar's skinned mesh, used when the server serves none.
    #[arg(long, env = "POSECAST_MESH")]
    mesh: Option<PathBuf>,
    /// Window width, physical pixels.
    #[arg(long, env = "POSECAST_WIDTH", default_value_t = 1280)]
    width: u32,
    /// Window height, physical pixels.
    #[arg(long, env = "POSECAST_HEIGHT", default_value_t = 720)]
    height: u32,
    /// Skin in a compute pass instead of the vertex shader.
    #[arg(long, env = "POSECAST_COMPUTE_SKINNING")]
    compute: bool,
    /// Draw the skeleton over the mesh.
    #[arg(long, env = "POSECAST_SKELETON")]
    skeleton: bool,
}

pub fn run(args: ViewArgs, runtime: &tokio::runtime::Runtime) -> anyhow::Result<()> {
    let fallback = args
        .mesh
        .as_deref()
        .map(super::render::read_mesh)
        .transpose()?;
    let client = runtime.block_on(args.connection.connect(true))?;
    let source = ClientSource::new(
        Arc::new(client),
        runtime.handle().clone(),
        args.connection.url.clone(),
        fallback.map(Arc::<GlbMesh>::new),
    );
    let mut options = ViewerOptions {
        title: format!("posecast — {}", args.connection.scene),
        size: (args.width, args.height),
        ..ViewerOptions::default()
    };
    options.renderer.skeleton_overlay = args.skeleton;
    if args.compute {
        options.renderer.skinning = SkinningPath::Compute;
    }
    run_viewer(source, options)?;
    Ok(())
}
