//! Sampling and forward kinematics per tick: posecast against a Rust port of ozz-animation's
//! runtime, on CMU 01_01 (31 joints, 2,752 frames at 120 fps) played forwards at 60 Hz.
//!
//! The port (`ozz/*.rs`; x86-64 only, as it uses the SSE estimates ozz's SSE build compiles
//! to) follows ozz-animation's sources (github.com/guillaumeblanc/ozz-animation at commits
//! 05a6e6b8 and, for `local_to_model_job.cc`, 5b82a1c7: the 0.15 animation layout):
//! - `src/animation/runtime/sampling_job.cc` and `include/ozz/animation/runtime/sampling_job.h`
//!   ([`sampling_job`]): the `Context` key cache, `UpdateCacheCursor`,
//!   `UpdateInterpKeyframes`, `DecompressFloat3`, `DecompressQuaternion`, `Interpolates`;
//! - `include/ozz/animation/runtime/animation.h`, `src/animation/runtime/animation_keyframe.h`
//!   ([`animation`]): keys of all tracks sorted by when they are first needed, time point
//!   indices, offsets to the previous key, half-float translations and scales, rotations as
//!   the three smallest components on 15 bits with the largest's index and sign (48 bits);
//! - `src/animation/runtime/local_to_model_job.cc` ([`local_to_model_job`]): SoA
//!   transforms to SoA matrices (`SoaFloat4x4::FromAffine`), `Transpose16x16` to four AoS
//!   matrices, then `M_i = M_parent(i) · L_i` in joint order;
//! - `src/animation/offline/animation_builder.cc` ([`builder`]): `CopyRaw`,
//!   `FixupQuaternions`, `Sort`, `BuildTimePoints`, `CopyToAnimation`, `CompressFloat3`,
//!   `CompressQuaternion`; without key reduction (every key of the clip is kept);
//! - the SSE maths they use (`include/ozz/base/maths/internal/simd_math_sse-inl.h`,
//!   `soa_float.h`, `soa_quaternion.h`, `soa_float4x4.h`; [`simd`]).
//!
//! Ours is what the server runs per tick for a playing clip (`sim/src/avatar/playback.rs`:
//! `Layer::sample` → `Sampler::sample` at `start + clip_time`; then
//! `posecast_proto::fk::forward_kinematics` for world matrices), on the clip as the server
//! holds it (the rig normalised by `Rig::from_asset`, channel maps applied at sampling time)
//! and, for reference, on the clip as imported (no channel maps).
//!
//! Before timing, the port is checked against ours at every 60 Hz tick of a loop and at 2,000
//! scrambled times ([`check`] states the bounds), and the check is shown to fail on a
//! pose with two quaternion components swapped. Under `cargo test --benches` only the checks run.
//!
//! Run: `cargo bench -p posecast-rigs --bench ozz` (needs ../shared/testdata; under `CI=true` a
//! missing file fails).

#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]
// The port keeps ozz's function signatures and index loops, so it reads against the C++.
#![allow(clippy::too_many_arguments, clippy::needless_range_loop)]

#[cfg(target_arch = "x86_64")]
#[path = "ozz/animation.rs"]
mod animation;
#[cfg(target_arch = "x86_64")]
#[path = "ozz/builder.rs"]
mod builder;
#[cfg(target_arch = "x86_64")]
#[path = "ozz/check.rs"]
mod check;
#[cfg(target_arch = "x86_64")]
#[path = "ozz/local_to_model_job.rs"]
mod local_to_model_job;
#[cfg(target_arch = "x86_64")]
#[path = "ozz/run.rs"]
mod run;
#[cfg(target_arch = "x86_64")]
#[path = "ozz/sampling_job.rs"]
mod sampling_job;
#[cfg(target_arch = "x86_64")]
#[path = "ozz/simd.rs"]
mod simd;

#[cfg(target_arch = "x86_64")]
fn main() {
    run::main();
}

#[cfg(not(target_arch = "x86_64"))]
fn main() {
    posecast_proto::testing::skip("the ozz port uses SSE intrinsics: x86-64 only");
}
