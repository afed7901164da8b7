//! The dashboard's JavaScript against the Rust side, without a browser:
//! - `server/web/check/samples.js` holds what the Rust protocol types serialise (this test
//!   writes it with `POSECAST_UPDATE_WEB_SAMPLES=1` and fails when it is out of date); each
//!   sample `@satisfies` its JSDoc type in `server/web/protocol.js`, so the type check (tsc,
//!   run here and by `scripts/check-web` in `.ci/run`) fails when a field is missing, extra or
//!   of another type on either side;
//! - the JavaScript client's forward kinematics and skinning matrices (`server/sdk/fk.js`, run
//!   by node through `server/web/check/fk.mjs`) give the matrices `posecast_proto::fk` gives,
//!   on random skeletons and the built-in rig with random poses and placements;
//! - the client's binary decoders, jitter buffer and clock estimator (`server/sdk/frames.js`,
//!   `frames2.js`, `jitter.js`, `clock.js`, through `server/web/check/stream.mjs`) match
//!   posecast-proto's `FrameDecoder` and `Frame2Decoder` (packed deltas, protocol version 7,
//!   too: levels and server times exactly) and posecast-client's `JitterBuffer` and
//!   `ClockEstimator` on shared vectors;
//! - the client's decoder for datagrams (protocol version 8: deltas of kind 4 naming the frames
//!   they refer to, `Frame2Decoder.forDatagrams()`) reads a lossy, reordered, cut stream and
//!   hand-made frames to exactly the levels `Frame2Decoder::for_datagrams` reads
//!   (`datagrams.rs`);
//! - the client's modules type-check against its declarations (`server/sdk/posecast.d.ts`),
//!   and a TypeScript user's file (`server/sdk/check/usage.ts`) against the declarations alone.
//!
//! node and the TypeScript compiler (`scripts/test` installs it under `target/npm`) missing:
//! the test is skipped, or fails under `CI=true`.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use posecast_proto::testing::skip;
use std::path::Path;
use std::process::Command as Process;

mod datagrams;
mod fk;
mod samples;
mod stream;

fn root() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

/// The dashboard's and the client's JavaScript type-check (`// @ts-check`, JSDoc types, the
/// samples above), and so does a TypeScript user's file against `posecast.d.ts` alone.
#[test]
fn the_dashboards_and_the_clients_javascript_type_check() {
    let tsc = root().join("target/npm/node_modules/.bin/tsc");
    if !tsc.exists() {
        skip(
            "the TypeScript compiler is not installed (scripts/test installs it under target/npm)",
        );
        return;
    }
    for project in [
        "server/web/tsconfig.json",
        "server/sdk/tsconfig.json",
        "server/sdk/check/tsconfig.json",
    ] {
        let out = Process::new(&tsc)
            .args(["--noEmit", "-p", project])
            .current_dir(root())
            .output()
            .expect("run tsc");
        assert!(
            out.status.success(),
            "tsc found errors in {project}:\n{}{}",
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        );
    }
}
