//! posecast's assets: a file becomes a normalised, playable rig with its clips.
//!
//! - [`import`]: glTF 2.0 (skins, animations, VRM 0.x/1.0 humanoids, VRM animations), the
//!   CSE169 `.skel`/`.skin`/`.anim` formats and BVH, read into an [`asset::Asset`]
//!   (skeleton, meshes, clips) with notes of what was renamed, dropped or repaired.
//! - [`clip`]: the one clip representation (per-joint tracks, step/linear/cubic) and its
//!   samplers.
//! - [`rig`]: normalisation per seed 000 (bind matrices simplified, Y-up, metres, a neutral
//!   pose such as H-Anim's), clips converted to match, the humanoid mapping, retargeting per
//!   seed 001 (in world space), and the playable [`rig::Rig`].
//! - [`builtin`]: the built-in avatar and its clips.
//! - [`library`]: rigs by name, uploads prepared into rigs.
//! - [`export`]: rigs and clips written back out as glTF and BVH.
//!
//! Everything here is synchronous and pure: no sockets, no tasks, no clocks. It uses only
//! `posecast-core` and `posecast-proto`; `posecast-sim` and `posecast-server` build on it.

pub mod asset;
pub mod builtin;
pub mod clip;
pub mod export;
pub mod import;
pub mod library;
pub mod rig;
