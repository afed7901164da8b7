//! `posecast`: starts the server.

fn main() -> anyhow::Result<()> {
    Ok(())
}
