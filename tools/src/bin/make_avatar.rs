//! Writes the built-in avatar: `cargo run -p posecast-tools --bin make-avatar [PATH]`
//! (default `assets/avatar.glb` at the repository root).

use anyhow::Context;
use std::path::{Path, PathBuf};

fn main() -> anyhow::Result<()> {
    let path = std::env::args_os().nth(1).map_or_else(
        || {
            let tools = Path::new(env!("CARGO_MANIFEST_DIR"));
            tools.parent().unwrap_or(tools).join("assets/avatar.glb")
        },
        PathBuf::from,
    );
    let bytes = posecast_server::builtin::try_generate()?;
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    std::fs::write(&path, &bytes).with_context(|| format!("writing {}", path.display()))?;
    println!("wrote {} ({} bytes)", path.display(), bytes.len());
    Ok(())
}
