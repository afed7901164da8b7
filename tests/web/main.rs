//! The dashboard's JavaScript against the Rust side, without a browser:
//! - `server/web/check/samples.js` holds what the Rust protocol types serialise (this test
//!   writes it with `POSECAST_UPDATE_WEB_SAMPLES=1` and fails when it is out of date); each
//!   sample `@satisfies` its JSDoc type in `server/web/protocol.js`, so the type check (tsc,
//!   run here and by `scripts/check-web` in `.ci/run`) fails when a field is missing, extra or
//!   of another type on either side;
//! - the page's forward kinematics (`server/web/fk.js`, run by node through
//!   `server/web/check/fk.mjs`) gives the world matrices `posecast_proto::fk` gives, on random
//!   skeletons and the built-in rig with random poses and placements.
//!
//! node and the TypeScript compiler (`scripts/test` installs it under `target/npm`) missing:
//! the test is skipped, or fails under `CI=true`.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use posecast_proto::testing::skip;
use std::path::Path;
use std::process::Command as Process;

mod fk;
mod samples;

fn root() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

/// The dashboard's JavaScript type-checks (`// @ts-check`, JSDoc types, the samples above).
#[test]
fn the_dashboards_javascript_type_checks() {
    let tsc = root().join("target/npm/node_modules/.bin/tsc");
    if !tsc.exists() {
        skip(
            "the TypeScript compiler is not installed (scripts/test installs it under target/npm)",
        );
        return;
    }
    let out = Process::new(&tsc)
        .args(["-p", "server/web/tsconfig.json"])
        .current_dir(root())
        .output()
        .expect("run tsc");
    assert!(
        out.status.success(),
        "tsc found errors:\n{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
}
