//! The posecast server: it imports rigs and clips, normalises them, plays them in scenes and
//! streams each avatar's local joint rotations to websocket clients.
//!
//! - [`asset`]: what an import produces (skeleton, skinned meshes, clips, source conventions).
//! - [`import`]: one importer per format (glTF, CSE169 `.skel/.skin/.anim`, BVH).
//! - [`clip`]: the one in-memory clip representation and its samplers.
//! - [`builtin`]: the generator of the built-in avatar shipped in `assets/`.
//! - [`rig`]: rig normalisation (seed 000) and cross-rig retargeting.
//! - [`library`]: the rigs the server can put in scenes; [`bake`]: retargeted clips, baked
//!   off the tick and cached.
//! - [`scene`]: scenes, avatars, playback and the tick task; [`live`]: avatars driven live.
//! - [`stream`]: per-connection outboxes (bounded fan-out).
//! - [`control`]: control commands (shared by REST and websocket); [`auth`]: tokens.
//! - [`export`]: a rig's normalised mesh as .glb for render clients.
//! - [`service`]: the axum router (`app`), websocket and HTTP endpoints.
//! - [`state`]: configuration and shared state; [`metrics`]: counters; [`quota`]: limits.
//! - [`startup`]: [`startup::Server`] — listen and serve at once; [`restore`]: rigs and
//!   stored scenes loaded in the background meanwhile; [`readiness`]: how far that has got.

pub mod asset;
pub mod auth;
pub mod avatar;
pub mod bake;
pub mod builtin;
pub mod clip;
pub mod config;
pub mod control;
pub mod error;
pub mod export;
pub mod import;
pub mod library;
pub mod live;
pub mod metrics;
pub mod quota;
pub mod readiness;
pub mod restore;
pub mod rig;
pub mod scene;
pub mod service;
pub mod startup;
pub mod state;
pub mod store;
pub mod stream;
pub mod world;
