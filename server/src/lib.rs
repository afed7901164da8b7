//! The posecast server: it imports rigs and clips, normalises them, plays them in scenes and
//! streams each avatar's local joint rotations to websocket clients.
//!
//! Modules are layered; each uses only the layers above it:
//!
//! 1. **Assets** — [`asset`] (what an import produces), [`import`] (glTF, CSE169
//!    `.skel/.skin/.anim`, BVH), [`clip`] (the one clip representation and its samplers),
//!    [`rig`] (normalisation per seed 000, retargeting per seed 001, the playable
//!    [`rig::Rig`]), [`builtin`] (the built-in avatar), [`library`] (rigs by name, uploads
//!    prepared into rigs), [`export`] (rigs and clips written back out).
//! 2. **Simulation** — [`avatar`] (one avatar: playback, placement and root motion, a live
//!    driver's pose, joint overrides), [`bake`] (retargeted clips, baked off the tick and
//!    cached).
//! 3. **Publication** — [`stream`] (a scene's feed: each tick encoded once per encoding and
//!    fanned out into per-connection outboxes, drained by writers).
//! 4. **World** — [`scene`] (avatars and their feed under one lock, the tick task),
//!    [`world`] (every scene, ids, quotas; [`world::command`]: a command applied to it).
//! 5. **Services** — [`auth`] (tokens), [`store`] (the data folder), [`config`], [`state`]
//!    (the world plus connections, store and start-up progress), [`control`] (commands for
//!    clients: counted, and acknowledged once stored), [`ingest`] (uploads imported,
//!    normalised and stored; an upload normalised again with new options), [`changes`] (what
//!    commands changed, pushed to subscribers and scene-list watchers), live drivers of a
//!    connection, the VMC gateway ([`vmc`]: UDP performers as live drivers, avatars sent to
//!    VMC receivers), start-up loading ([`readiness`]), scale-out through NATS ([`cluster`]:
//!    scene ownership by lease, frames relayed between servers, commands forwarded to a
//!    scene's owner).
//! 6. **Transport** — [`service`]: the axum router, accept loop and limits, websocket
//!    sessions, REST, uploads, dashboard, health.
//! 7. **Entry** — [`startup`]: [`startup::Server`] listens at once, restores in the
//!    background, shuts down gracefully.
//!
//! Used by all: [`error`] (the typed [`error::Error`], turned into the wire's error in one
//! place), [`metrics`] (counters), [`quota`] (limits and rate buckets).

pub mod asset;
pub mod auth;
pub mod avatar;
pub mod bake;
pub mod builtin;
pub mod changes;
pub mod clip;
pub mod cluster;
pub mod config;
pub mod control;
pub mod error;
pub mod export;
pub mod import;
pub mod ingest;
pub mod library;
mod live;
pub mod metrics;
pub mod quota;
pub mod readiness;
mod restore;
pub mod rig;
pub mod scene;
pub mod service;
pub mod startup;
pub mod state;
pub mod store;
pub mod stream;
pub mod vmc;
pub mod world;
