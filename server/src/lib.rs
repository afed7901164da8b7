//! The posecast server: it imports rigs and clips, normalises them, plays them in scenes and
//! streams each avatar's local joint rotations to websocket clients.
//!
//! - [`asset`]: what an import produces (skeleton, skinned meshes, clips, source conventions).
//! - [`import`]: one importer per format (glTF, CSE169 `.skel/.skin/.anim`, BVH).
//! - [`clip`]: the one in-memory clip representation and its samplers.
//! - [`builtin`]: the generator of the built-in avatar shipped in `assets/`.

pub mod asset;
pub mod builtin;
pub mod clip;
pub mod import;
pub mod rig;
