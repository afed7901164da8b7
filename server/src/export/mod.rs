//! Writing rigs and clips out: binary glTF for render clients and tools, BVH for motion
//! capture tools.
//!
//! - [`glb`]: the one `.glb` writer — skeleton nodes, skinned mesh, skin, animations. It
//!   writes the built-in avatar (`make-avatar`), the mesh endpoint's file and clip exports.
//!
//! [`mesh_glb`] is what `GET /api/assets/{name}/mesh.glb` calls.

pub mod glb;

use crate::asset::AssetMesh;
use posecast_proto::{Skeleton, SkeletonError};

/// Why an export failed: inconsistent input, named, or a file too large for its format.
#[derive(Debug, thiserror::Error)]
pub enum ExportError {
    #[error("animation {animation}, channel {channel}: {message}")]
    Channel {
        animation: String,
        channel: usize,
        message: String,
    },
    #[error("mesh {mesh}, primitive {primitive}: {message}")]
    Primitive {
        mesh: String,
        primitive: usize,
        message: String,
    },
    #[error("the .glb would be {bytes} bytes; the format's lengths stop at 4 GiB")]
    TooLarge { bytes: usize },
    #[error("the skeleton: {0}")]
    Skeleton(#[from] SkeletonError),
    #[error("serialising the glTF JSON: {0}")]
    Json(#[from] serde_json::Error),
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

fn write_glb(
    name: Option<&str>,
    skeleton: &Skeleton,
    meshes: &[AssetMesh],
    animations: &[glb::Animation],
) -> Result<Vec<u8>, ExportError> {
    let mesh = (!meshes.is_empty()).then(|| glb::Mesh {
        name: "mesh".into(),
        primitives: meshes
            .iter()
            .map(|m| glb::Primitive::from_skinned(&m.mesh))
            .collect(),
    });
    glb::write(&glb::Model {
        generator: GENERATOR,
        name,
        skeleton,
        mesh: mesh.as_ref(),
        animations,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::startup::builtin_rig;

    #[test]
    fn the_exported_mesh_imports_back_identically() {
        let rig = builtin_rig().unwrap();
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
