//! The posecast server: it imports rigs and clips, normalises them, plays them in scenes and
//! streams each avatar's local joint rotations to websocket and WebTransport clients.
//!
//! It is the top of a stack of crates, each a layer cargo keeps below the next
//! (`ARCHITECTURE.md`):
//!
//! - `posecast-core` ([`error`], [`quota`]); `posecast-rigs`, the assets ([`asset`],
//!   [`import`], [`clip`], [`rig`], [`builtin`], [`library`], [`export`]); `posecast-sim`, the
//!   simulation ([`avatar`], [`bake`]); `posecast-stream`, publication ([`stream`]).
//! - `posecast-world`: [`scene`] (avatars and their feed under one lock, the tick task),
//!   [`world`] (every scene, ids, quotas; [`world::command`]: one handler per command) and
//!   [`metrics`] (counters).
//! - `posecast-services`: [`auth`], [`config`], [`store`], [`readiness`], [`state`] (the
//!   [`state::Services`] every service shares), [`control`], [`ingest`], [`changes`], live
//!   drives, [`vmc`], start-up restore, [`takes`], [`cluster`].
//! - this crate, the transport and the entry: [`app`] ([`app::AppState`]: the services plus
//!   the connection table, paths, probe clock and QUIC endpoint), [`service`] (the axum
//!   router, accept loop and limits, websocket sessions, REST, uploads, dashboard, health,
//!   WebTransport) and [`startup`] ([`startup::Server`]: listens at once, restores in the
//!   background, shuts down gracefully).
//!
//! The crates below are re-exported under the paths the server has always used for them
//! (`posecast_server::rig`, `posecast_server::world`, …).

#![warn(missing_docs)]

pub use posecast_core::{error, quota};
pub use posecast_rigs::{asset, builtin, clip, export, import, library, rig};
pub use posecast_services::{
    auth, changes, cluster, config, control, ingest, readiness, state, store, takes, vmc,
};
pub(crate) use posecast_services::{live, restore};
pub use posecast_sim::{avatar, bake};
pub use posecast_stream as stream;
pub use posecast_world::{metrics, scene, world};

pub mod app;
pub mod service;
pub mod startup;
