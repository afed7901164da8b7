//! Writes `server/sdk/protocol.d.ts`, the TypeScript declarations of the wire's JSON, from the
//! Rust types of posecast-proto ([`posecast_proto::ts::declarations`]). Run it after changing a
//! message, command or result type: `cargo run -p posecast-tools --bin gen-ts`
//! (`tools/tests/ts_types.rs` fails until the checked-in file matches).

use std::path::Path;

fn main() -> anyhow::Result<()> {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../server/sdk/protocol.d.ts");
    std::fs::write(&path, posecast_proto::ts::declarations())?;
    println!("wrote {}", path.display());
    Ok(())
}
