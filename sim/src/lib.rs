//! posecast's simulation: one avatar's pose at a clock.
//!
//! - [`avatar`]: an avatar plays clip layers with cross-fades (a fade stack, so a `play`
//!   during any fade is continuous), follows a live driver's pose retargeted from the
//!   driver's rig, applies joint overrides, places itself and moves its root, and records a
//!   live drive into a clip.
//! - [`bake`]: clips retargeted from one rig onto another, baked off the tick (a blocking
//!   task, bounded) and cached by size.
//!
//! It knows nothing of sockets or scenes: the server's scenes tick avatars under their lock
//! and publish the poses. It uses `posecast-rigs`, `posecast-core` and `posecast-proto`.

pub mod avatar;
pub mod bake;
