//! The posecast server: it imports rigs and clips, normalises them, plays them in scenes and
//! streams each avatar's local joint rotations to websocket clients.
//!
//! It builds on four crates of its own, each a layer cargo keeps below this one:
//! `posecast-core` ([`error`], [`quota`]), `posecast-rigs` (the assets: [`asset`],
//! [`import`], [`clip`], [`rig`], [`builtin`], [`library`], [`export`]), `posecast-sim`
//! (the simulation: [`avatar`], [`bake`]) and `posecast-stream` (publication: [`stream`]).
//! They are re-exported here under their old paths.
//!
//! This crate's own modules are layered; each uses only the layers above it
//! (`scripts/check-layers` fails CI otherwise):
//!
//! 1. **World** — [`scene`] (avatars and their feed under one lock, the tick task),
//!    [`world`] (every scene, ids, quotas; [`world::command`]: one handler per command —
//!    what it needs, where it runs, what it announces, its change to the world).
//! 2. **Services** — [`auth`] (tokens), [`store`] (the data folder), [`config`], [`state`]
//!    ([`state::Services`], what the services share: the world, the store, takes, start-up
//!    progress, watchers, counters, the cluster; [`state::AppState`], the transport's: the
//!    services plus the connections), [`control`] (commands for
//!    clients: counted, and acknowledged once stored), [`ingest`] (uploads imported,
//!    normalised and stored; an upload normalised again with new options), [`changes`] (what
//!    commands changed, pushed to subscribers and scene-list watchers), live drivers of a
//!    connection, the VMC gateway ([`vmc`]: UDP performers as live drivers, avatars sent to
//!    VMC receivers), start-up loading ([`readiness`]), scale-out through NATS ([`cluster`]:
//!    scene ownership by lease, frames relayed between servers, commands forwarded to a
//!    scene's owner), takes of whole scenes ([`takes`]: recorded as the scene streams,
//!    replayed as scenes, exported).
//! 3. **Transport** — [`service`]: the axum router, accept loop and limits, websocket
//!    sessions, REST, uploads, dashboard, health.
//! 4. **Entry** — [`startup`]: [`startup::Server`] listens at once, restores in the
//!    background, shuts down gracefully.
//!
//! Used by all of them: [`metrics`] (counters).

// The lower layers are crates of their own (cargo enforces that they never reach up); they
// are re-exported so that `posecast_server::rig` and the like stay one path for users.
#![warn(missing_docs)]

pub use posecast_core::{error, quota};
pub use posecast_rigs::{asset, builtin, clip, export, import, library, rig};
pub use posecast_sim::{avatar, bake};
pub use posecast_stream as stream;

pub mod auth;
pub mod changes;
pub mod cluster;
pub mod config;
pub mod control;
pub mod ingest;
mod live;
pub mod metrics;
pub mod readiness;
mod restore;
pub mod scene;
pub mod service;
pub mod startup;
pub mod state;
pub mod store;
pub mod takes;
pub mod vmc;
pub mod world;
