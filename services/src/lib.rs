//! posecast's services: what runs a client's command, upload or live pose, below the sockets.
//!
//! - [`auth`] (tokens, rights, minted tokens), [`config`] (how the server runs),
//!   [`store`] (the data folder), [`readiness`] (start-up progress).
//! - [`state`]: [`state::Services`], what every service shares — the world, the store, takes,
//!   watchers, counters, the cluster. No service sees a socket or the connection table.
//! - [`control`] (commands for clients: counted, answered once for a retried key,
//!   acknowledged once stored), [`ingest`] (uploads imported, normalised and stored),
//!   [`changes`] (what a command changed, pushed to subscribers and scene-list watchers),
//!   [`live`] (a connection's live drives), [`vmc`] (the VMC gateway), [`restore`] (start-up
//!   loading), [`takes`] (takes of whole scenes), [`cluster`] (scale-out through NATS).
//!
//! Below: `posecast-world` (scenes and the world) and the asset, simulation and publication
//! crates; above: `posecast-server` (HTTP, websockets, WebTransport, start-up), which hands
//! the services what its sockets receive.

#![warn(missing_docs)]

// The layers below, under the paths the server has always used for them.
pub use posecast_core::{error, quota};
pub use posecast_rigs::{asset, builtin, clip, export, import, library, rig};
pub use posecast_sim::{avatar, bake};
pub use posecast_stream as stream;
pub use posecast_world::{metrics, scene, world};

pub mod auth;
pub mod changes;
pub mod cluster;
pub mod config;
pub mod control;
pub mod ingest;
pub mod live;
pub mod readiness;
pub mod restore;
pub mod state;
pub mod store;
pub mod takes;
pub mod vmc;
