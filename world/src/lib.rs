//! posecast's world: the scenes and the world of scenes, the layer every service acts on.
//!
//! - [`scene`]: one scene — its avatars under the scene lock, their feed under its own, the
//!   ticker that wakes at absolute deadlines, the answers of keyed commands, a take's replay.
//! - [`world`]: every scene, ids, quotas, the rigs by name; [`world::command`]: one handler per
//!   command — what it needs, where it runs, what it announces, its change to the world.
//! - [`metrics`]: the server's counters (used by every layer above too).
//!
//! It knows nothing of files, tokens, sockets or other servers: the services
//! (`posecast-services`) and the transport (`posecast-server`) sit above it, and cargo keeps
//! them there.

#![warn(missing_docs)]

// The layers below, under the paths the server has always used for them.
pub use posecast_core::{error, quota};
pub use posecast_rigs::{asset, builtin, clip, export, import, library, rig};
pub use posecast_sim::{avatar, bake};
pub use posecast_stream as stream;

pub mod metrics;
pub mod scene;
pub mod world;
