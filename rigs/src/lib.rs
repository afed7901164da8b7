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
//!
//! # Example
//!
//! A two-joint BVH pendulum, in centimetres as BVH files usually are, made playable:
//!
//! ```rust
//! use posecast_rigs::import::bvh;
//! use posecast_rigs::rig::{PipelineOptions, Rig};
//!
//! let text = "HIERARCHY
//! ROOT base
//! {
//!   OFFSET 0 0 0
//!   CHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation
//!   JOINT bob
//!   {
//!     OFFSET 0 -120 0
//!     CHANNELS 3 Zrotation Yrotation Xrotation
//!     End Site
//!     {
//!       OFFSET 0 -10 0
//!     }
//!   }
//! }
//! MOTION
//! Frames: 2
//! Frame Time: 0.5
//! 0 0 0 0 0 0 0 0 0
//! 0 0 0 0 0 0 30 0 0
//! ";
//! let asset = bvh::parse("pendulum.bvh", text)?;
//! assert_eq!(asset.skeleton.names(), ["base", "bob"]);
//!
//! let rig = Rig::from_asset(asset, &PipelineOptions::default())?;
//! // Not a humanoid: no joint maps to H-Anim, so its pose is kept as authored.
//! assert!(!rig.humanoid);
//! // BVH does not say its units: 120 units tall reads as centimetres, so the bob hangs
//! // 1.2 m below the base in the normalised rig.
//! assert_eq!(rig.units.metres_per_unit, 0.01);
//! let bob = rig.skeleton().rest()[1].translation;
//! assert!((bob - glam::Vec3::new(0.0, -1.2, 0.0)).length() < 1e-5);
//! // The motion is one clip named after the file's stem: two frames 0.5 s apart.
//! let clip = rig.clip("pendulum").ok_or("no clip")?;
//! assert_eq!(clip.duration(), 0.5);
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

#![warn(missing_docs)]
pub mod asset;
pub mod builtin;
pub mod clip;
pub mod export;
pub mod import;
pub mod library;
pub mod rig;
