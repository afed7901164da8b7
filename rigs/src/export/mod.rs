//! Writing rigs and clips out: binary glTF for render clients and tools, BVH for motion
//! capture tools.
//!
//! - [`glb`]: the one `.glb` writer — skeleton nodes, skinned mesh, skin, animations. It
//!   writes the built-in avatar (`make-avatar`), the mesh endpoint's file and clip exports.
//! - [`animation`]: a [`Clip`] as glTF animation channels.
//! - [`bvh`]: a clip on its rig as BVH text.
//! - [`take`]: several avatars, each its own rig, and one animation of them all as `.glb`.
//!
//! The functions below are what the HTTP routes call: [`mesh_glb`] for
//! `GET /api/assets/{name}/mesh.glb`, [`clip_glb`] and [`clip_bvh`] for a clip's exports;
//! [`take_glb`] writes a take of several avatars.

pub mod animation;
pub mod bvh;
pub mod glb;
pub mod take;

pub use take::{TakeAvatar, take_glb};

use crate::asset::AssetMesh;
use crate::clip::Clip;
use crate::rig::Rig;
use posecast_proto::{Skeleton, SkeletonError};

/// Why an export failed. Exports of a rig's own clips are not expected to fail; these name
/// the inconsistency when one does.
#[derive(Debug, thiserror::Error)]
pub enum ExportError {
    /// The clip has more joint slots than the skeleton it is written with has joints.
    #[error("clip {clip} has {clip_joints} joint slots; the rig has {rig_joints} joints")]
    JointCount {
        /// The clip's name.
        clip: String,
        /// Its number of joint slots.
        clip_joints: usize,
        /// The skeleton's number of joints.
        rig_joints: usize,
    },
    /// The clip has no channel on any joint, and a glTF animation needs at least one.
    #[error("clip {clip} animates nothing: there is no channel to write")]
    NothingAnimated {
        /// The clip's name.
        clip: String,
    },
    /// An animation channel given to the `.glb` writer is inconsistent (joint out of range,
    /// no keys, bad or unordered times, value count not matching the keys).
    #[error("animation {animation}, channel {channel}: {message}")]
    Channel {
        /// The animation's name.
        animation: String,
        /// The channel's index in the animation.
        channel: usize,
        /// What is wrong with it.
        message: String,
    },
    /// A mesh primitive given to the `.glb` writer is inconsistent (attribute lengths differ,
    /// an index out of range, …).
    #[error("mesh {mesh}, primitive {primitive}: {message}")]
    Primitive {
        /// The mesh's name.
        mesh: String,
        /// The primitive's index in the mesh.
        primitive: usize,
        /// What is wrong with it.
        message: String,
    },
    /// The BVH frame time asked for is zero, negative or not finite.
    #[error("frame time {frame_time} s is not a positive number")]
    FrameTime {
        /// The frame time given, seconds.
        frame_time: f64,
    },
    /// The BVH motion would hold more than [`bvh::MAX_VALUES`] numbers.
    #[error("{frames} frames of {channels} channels: more than {max_values} values")]
    TooManyFrames {
        /// Frames the clip would need.
        frames: usize,
        /// Channels per frame (6 for a translated joint, 3 for the others).
        channels: usize,
        /// The limit, [`bvh::MAX_VALUES`].
        max_values: usize,
    },
    /// A take export was given no avatar ([`take_glb`]).
    #[error("a take export needs at least one avatar")]
    NoAvatars,
    /// The `.glb` would pass the 4 GiB its `u32` lengths can address.
    #[error("the .glb would be {bytes} bytes; the format's lengths stop at 4 GiB")]
    TooLarge {
        /// The size it would have, bytes.
        bytes: usize,
    },
    /// The skeleton the built-in avatar's writer builds was refused ([`crate::builtin::glb::write`]).
    #[error("the skeleton: {0}")]
    Skeleton(#[from] SkeletonError),
    /// The glTF JSON could not be serialised.
    #[error("serialising the glTF JSON: {0}")]
    Json(#[from] serde_json::Error),
    /// The GLB container could not be written.
    #[error("writing the GLB container: {0}")]
    Glb(#[from] gltf::Error),
}

/// The generator name written into exported glTF files.
const GENERATOR: &str = "posecast";

/// `GET /api/assets/{name}/mesh.glb`: a rig's normalised skinned mesh, without animation —
/// joints as nodes `0..n` at their rest transforms in the description's order and with its
/// names, one skin with the inverse bind matrices, every mesh as a primitive of mesh 0
/// (four influences per vertex: the heaviest, renormalised). See [`glb`] for the layout.
///
/// # Errors
/// Only on inconsistent input ([`ExportError::Primitive`]) or a file over 4 GiB.
pub fn mesh_glb(skeleton: &Skeleton, meshes: &[AssetMesh]) -> Result<Vec<u8>, ExportError> {
    write_glb(None, skeleton, meshes, &[])
}

/// A clip of `rig` as `.glb` (for `GET /api/assets/{name}/clips/{clip}.glb`): the rig's mesh
/// and skin as [`mesh_glb`] writes them, plus the clip as one animation named after it, its
/// time shifted so it starts at 0 (see [`animation::animation`] for how channels are keyed).
///
/// # Errors
/// The clip has more joint slots than the rig has joints, or animates nothing
/// ([`ExportError::JointCount`], [`ExportError::NothingAnimated`]).
pub fn clip_glb(rig: &Rig, clip: &Clip) -> Result<Vec<u8>, ExportError> {
    rig_glb(
        Some(&rig.name),
        rig.skeleton(),
        &rig.asset.meshes,
        std::slice::from_ref(clip),
    )
}

/// A clip of `rig` as BVH text (for `GET /api/assets/{name}/clips/{clip}.bvh`): the rig's
/// rest translations as offsets in centimetres, local rotations as `Zrotation Yrotation
/// Xrotation` degrees, one frame per clip key when the clip is uniformly keyed, else at
/// [`bvh::RESAMPLE_RATE`] or a little faster. See [`bvh`] for the conventions.
///
/// # Errors
/// The clip has more joint slots than the rig has joints ([`ExportError::JointCount`]), or
/// is too long for [`bvh::MAX_VALUES`] ([`ExportError::TooManyFrames`]).
pub fn clip_bvh(rig: &Rig, clip: &Clip) -> Result<String, ExportError> {
    bvh::write(rig.skeleton(), clip, None)
}

/// A skeleton, its meshes and any clips of it as `.glb`; `name` names the skin and the scene.
///
/// # Errors
/// As [`clip_glb`], for each clip.
pub fn rig_glb(
    name: Option<&str>,
    skeleton: &Skeleton,
    meshes: &[AssetMesh],
    clips: &[Clip],
) -> Result<Vec<u8>, ExportError> {
    let targets = posecast_proto::morph::channels(meshes.iter().map(|m| &m.mesh));
    let animations = clips
        .iter()
        .map(|clip| animation::animation(clip, skeleton.len(), &targets))
        .collect::<Result<Vec<_>, _>>()?;
    write_glb(name, skeleton, meshes, &animations)
}

fn write_glb(
    name: Option<&str>,
    skeleton: &Skeleton,
    meshes: &[AssetMesh],
    animations: &[glb::Animation],
) -> Result<Vec<u8>, ExportError> {
    let channels = posecast_proto::morph::channels(meshes.iter().map(|m| &m.mesh));
    let mesh = skinned_mesh("mesh".into(), meshes, &channels);
    glb::write(&glb::Model {
        generator: GENERATOR,
        name,
        skeleton,
        mesh: mesh.as_ref(),
        animations,
    })
}

/// A rig's meshes as one skinned glTF mesh named `name`, one primitive per mesh with morph
/// targets after `channels` (the meshes' morph channels); `None` without meshes.
fn skinned_mesh(name: String, meshes: &[AssetMesh], channels: &[String]) -> Option<glb::Mesh> {
    (!meshes.is_empty()).then(|| glb::Mesh {
        name,
        primitives: meshes
            .iter()
            .map(|m| glb::Primitive::from_skinned(&m.mesh, channels))
            .collect(),
        target_names: channels.to_vec(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_exported_mesh_imports_back_identically() {
        let rig = crate::builtin::rig().unwrap();
        let bytes = mesh_glb(rig.skeleton(), &rig.asset.meshes).unwrap();
        let back = crate::import::gltf::from_slice("export.glb", &bytes)
            .unwrap()
            .remove(0);
        assert_eq!(back.skeleton.names(), rig.skeleton().names());
        assert_eq!(back.skeleton.parents(), rig.skeleton().parents());
        for (a, b) in back
            .skeleton
            .inverse_bind()
            .iter()
            .zip(rig.skeleton().inverse_bind())
        {
            assert!(a.abs_diff_eq(*b, 1e-6));
        }
        let (m0, m1) = (&back.meshes[0].mesh, &rig.asset.meshes[0].mesh);
        assert_eq!(m0.positions(), m1.positions());
        assert_eq!(m0.indices(), m1.indices());
        assert_eq!(m0.vertex_count(), m1.vertex_count());
    }
}
