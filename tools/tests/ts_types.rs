//! The checked-in TypeScript declarations of the wire (`server/sdk/protocol.d.ts`, which the
//! SDK and the dashboard type-check against) are what the Rust types generate today.

use std::path::Path;

#[test]
fn the_checked_in_typescript_declarations_are_up_to_date() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("tools/ is in the workspace");
    let path = root.join("server/sdk/protocol.d.ts");
    let checked_in = std::fs::read_to_string(&path)
        .unwrap_or_else(|e| panic!("cannot read {}: {e}", path.display()));
    let generated = posecast_proto::ts::declarations();
    if checked_in != generated {
        let line = checked_in
            .lines()
            .zip(generated.lines())
            .position(|(a, b)| a != b)
            .unwrap_or_else(|| checked_in.lines().count().min(generated.lines().count()));
        panic!(
            "{} is out of date (first difference at line {}): run \
             `cargo run -p posecast-tools --bin gen-ts` and commit it",
            path.display(),
            line + 1
        );
    }
}
