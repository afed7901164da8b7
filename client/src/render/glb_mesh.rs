//! Reads an avatar's skinned mesh from `.glb` bytes: the format of the server's mesh endpoint
//! (`GET /api/assets/{name}/mesh.glb`, the rig's skinned mesh in the description's bind space),
//! and of `--mesh` files given to the CLI.
//!
//! Only what the renderer draws is read: `POSITION`, `NORMAL` (computed when absent),
//! `JOINTS_0`/`WEIGHTS_0`, the indices and the morph targets (`POSITION`/`NORMAL`
//! displacements, named by `mesh.extras.targetNames`, else `target<k>`) of every triangle
//! primitive of the meshes bound to the file's first skin, merged into one [`SkinnedMesh`]:
//! targets of the same name on several primitives become one target (zero on the vertices of
//! primitives without it), as the server's morph channels are. Vertices stay in mesh space (the
//! skinned node's own transform is ignored, as the glTF spec requires). Joint indices in the
//! file refer to the skin's joint list; [`GlbMesh::for_joints`] maps them onto a description's
//! joint order by name. This is not an importer: skeletons and clips come from the server.

use glam::Vec3;
use posecast_proto::morph::MorphTarget;
use posecast_proto::{MeshError, SkinnedMesh};
use std::collections::HashMap;

/// Why a `.glb` gave no mesh.
#[derive(Debug, thiserror::Error)]
pub enum GlbMeshError {
    /// The bytes are not a glTF/GLB document, or its buffers cannot be loaded.
    #[error("not a readable glTF/GLB file: {source}")]
    Parse {
        /// What the glTF reader reported.
        #[source]
        source: gltf::Error,
    },
    /// The file has no skin, or no triangle primitive with `JOINTS_0` on a mesh bound to its
    /// first skin.
    #[error("the file has no skinned triangle mesh")]
    NoSkinnedMesh,
    /// A primitive lacks an attribute the renderer needs (`POSITION`, `JOINTS_0`, …).
    #[error("mesh {mesh}: {message}")]
    Accessor {
        /// The primitive's label (mesh name and primitive index).
        mesh: String,
        /// What is missing.
        message: String,
    },
    /// A primitive, or the merged mesh, does not make a valid [`SkinnedMesh`].
    #[error("mesh {mesh}: {source}")]
    Mesh {
        /// The primitive's label, or `"merged"` for the merged mesh.
        mesh: String,
        /// Why the mesh was refused.
        #[source]
        source: MeshError,
    },
    /// A skin joint's name is not among the avatar's joints (or a weighted vertex names a
    /// skin joint past the skin's list).
    #[error("the mesh's skin joint {joint} ({name:?}) is not a joint of the avatar")]
    UnknownJoint {
        /// Index of the joint in the skin's joint list.
        joint: usize,
        /// Its node's name, if it has one.
        name: Option<String>,
    },
    /// The skin's joints are unnamed and more than the avatar has, so they cannot be taken
    /// in order.
    #[error("the mesh's skin has {mesh} joints without names; the avatar has {avatar}")]
    JointCount {
        /// Joints in the skin.
        mesh: usize,
        /// Joints in the avatar.
        avatar: usize,
    },
    /// The glTF reader panicked on malformed input (caught and turned into this error).
    #[error("the glTF reader failed on malformed input")]
    Malformed,
}

/// A skinned mesh as stored in a `.glb`: joint indices into the skin's joint list.
#[derive(Clone, Debug)]
pub struct GlbMesh {
    /// Bind-pose mesh (mesh space); joint indices refer to [`GlbMesh::joint_names`].
    pub mesh: SkinnedMesh,
    /// Name of each skin joint's node, when it has one.
    pub joint_names: Vec<Option<String>>,
}

impl GlbMesh {
    /// Reads the meshes bound to the first skin of a `.glb` (or a `.gltf` with embedded
    /// buffers).
    pub fn from_slice(bytes: &[u8]) -> Result<Self, GlbMeshError> {
        let gltf =
            gltf::Gltf::from_slice(bytes).map_err(|source| GlbMeshError::Parse { source })?;
        let buffers = gltf::import_buffers(&gltf.document, None, gltf.blob.clone())
            .map_err(|source| GlbMeshError::Parse { source })?;
        // The gltf crate's readers slice buffers after its own validation; a gap in that
        // validation must not take the client down, so a panic becomes an error.
        std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            read_document(&gltf.document, &buffers)
        }))
        .unwrap_or(Err(GlbMeshError::Malformed))
    }

    /// The mesh with joint indices into `joints`, an avatar's joint names in description
    /// order. Skin joints are matched by name; a skin without names is taken to list the
    /// avatar's joints in order (the mesh endpoint writes them so).
    pub fn for_joints(&self, joints: &[String]) -> Result<SkinnedMesh, GlbMeshError> {
        let by_name: HashMap<&str, usize> = joints
            .iter()
            .enumerate()
            .map(|(i, n)| (n.as_str(), i))
            .collect();
        let named = self.joint_names.iter().all(Option::is_some);
        let map: Vec<usize> = if named {
            self.joint_names
                .iter()
                .enumerate()
                .map(|(joint, name)| {
                    name.as_deref()
                        .and_then(|n| by_name.get(n).copied())
                        .ok_or_else(|| GlbMeshError::UnknownJoint {
                            joint,
                            name: name.clone(),
                        })
                })
                .collect::<Result<_, _>>()?
        } else if self.joint_names.len() <= joints.len() {
            (0..self.joint_names.len()).collect()
        } else {
            return Err(GlbMeshError::JointCount {
                mesh: self.joint_names.len(),
                avatar: joints.len(),
            });
        };
        let mesh = &self.mesh;
        let remapped = mesh
            .joints()
            .iter()
            .zip(mesh.weights())
            .map(|(&j, &w)| match map.get(usize::from(j)) {
                Some(&to) => u16::try_from(to).map_err(|_| GlbMeshError::JointCount {
                    mesh: map.len(),
                    avatar: joints.len(),
                }),
                // Unused slots (weight zero) may hold any index.
                None if w == 0.0 => Ok(0),
                None => Err(GlbMeshError::UnknownJoint {
                    joint: usize::from(j),
                    name: None,
                }),
            })
            .collect::<Result<Vec<u16>, _>>()?;
        SkinnedMesh::new(
            mesh.positions().to_vec(),
            mesh.normals().to_vec(),
            mesh.indices().to_vec(),
            mesh.influences(),
            remapped,
            mesh.weights().to_vec(),
            joints.len(),
        )
        .and_then(|m| m.with_targets(mesh.targets().to_vec()))
        .map_err(|source| GlbMeshError::Mesh {
            mesh: "merged".into(),
            source,
        })
    }
}

/// Appends every triangle primitive of the nodes using the first skin (by node order).
fn read_document(
    doc: &gltf::Document,
    buffers: &[gltf::buffer::Data],
) -> Result<GlbMesh, GlbMeshError> {
    let skin = doc
        .nodes()
        .find(|n| n.skin().is_some() && n.mesh().is_some())
        .and_then(|n| n.skin())
        .ok_or(GlbMeshError::NoSkinnedMesh)?;
    let joint_names: Vec<Option<String>> =
        skin.joints().map(|n| n.name().map(str::to_owned)).collect();
    let mut merged = Merged::default();
    for node in doc.nodes() {
        let (Some(s), Some(mesh)) = (node.skin(), node.mesh()) else {
            continue;
        };
        if s.index() != skin.index() {
            continue;
        }
        for prim in mesh.primitives() {
            if prim.mode() != gltf::mesh::Mode::Triangles {
                continue;
            }
            let label = format!("{}#{}", mesh.name().unwrap_or("mesh"), prim.index());
            let part = read_primitive(&prim, buffers, &label, joint_names.len())?;
            let targets = read_targets(&mesh, &prim, buffers, &label, part.vertex_count())?;
            merged.append(&part, targets);
        }
    }
    if merged.positions.is_empty() {
        return Err(GlbMeshError::NoSkinnedMesh);
    }
    let mesh = SkinnedMesh::new(
        merged.positions,
        merged.normals,
        merged.indices,
        4,
        merged.joints,
        merged.weights,
        joint_names.len(),
    )
    .and_then(|m| m.with_targets(merged.targets))
    .map_err(|source| GlbMeshError::Mesh {
        mesh: "merged".into(),
        source,
    })?;
    Ok(GlbMesh { mesh, joint_names })
}

#[derive(Default)]
struct Merged {
    positions: Vec<Vec3>,
    normals: Vec<Vec3>,
    indices: Vec<u32>,
    joints: Vec<u16>,
    weights: Vec<f32>,
    targets: Vec<MorphTarget>,
}

impl Merged {
    /// Appends a primitive and its targets: a target name seen before continues that target,
    /// a new one starts with zeros for the vertices already merged; targets this primitive
    /// lacks get zeros for its vertices.
    fn append(&mut self, part: &SkinnedMesh, targets: Vec<MorphTarget>) {
        let before = self.positions.len();
        let after = before + part.vertex_count();
        for target in targets {
            let index = match self.targets.iter().position(|t| t.name == target.name) {
                Some(i) => i,
                None => {
                    self.targets.push(MorphTarget {
                        name: target.name.clone(),
                        positions: vec![Vec3::ZERO; before],
                        normals: vec![Vec3::ZERO; before],
                    });
                    self.targets.len() - 1
                }
            };
            let merged = &mut self.targets[index];
            if merged.positions.len() == before {
                merged.positions.extend_from_slice(&target.positions);
                if target.normals.is_empty() {
                    merged.normals.resize(after, Vec3::ZERO);
                } else {
                    merged.normals.extend_from_slice(&target.normals);
                }
            }
        }
        for merged in &mut self.targets {
            merged.positions.resize(after, Vec3::ZERO);
            merged.normals.resize(after, Vec3::ZERO);
        }
        let base = before as u32;
        self.positions.extend_from_slice(part.positions());
        self.normals.extend_from_slice(part.normals());
        self.indices.extend(part.indices().iter().map(|i| i + base));
        self.joints.extend_from_slice(part.joints());
        self.weights.extend_from_slice(part.weights());
    }
}

/// A primitive's morph targets, one per entry of `primitive.targets` (a target without
/// `POSITION` displaces no position, one without `NORMAL` no normal).
fn read_targets(
    mesh: &gltf::Mesh<'_>,
    prim: &gltf::Primitive<'_>,
    buffers: &[gltf::buffer::Data],
    label: &str,
    vertices: usize,
) -> Result<Vec<MorphTarget>, GlbMeshError> {
    let names = target_names(mesh);
    let reader = prim.reader(|b| buffers.get(b.index()).map(|d| &d.0[..]));
    let mut out = Vec::new();
    for (k, (positions, normals, _tangents)) in reader.read_morph_targets().enumerate() {
        let read = |list: Option<gltf::accessor::Iter<'_, [f32; 3]>>, what: &str| {
            let list: Vec<Vec3> = list
                .map(|it| it.map(Vec3::from).collect())
                .unwrap_or_default();
            if list.is_empty() || list.len() == vertices {
                Ok(list)
            } else {
                Err(GlbMeshError::Accessor {
                    mesh: label.to_owned(),
                    message: format!(
                        "morph target {k} {what} has {} entries for {vertices} vertices",
                        list.len()
                    ),
                })
            }
        };
        let mut positions = read(positions, "POSITION")?;
        positions.resize(vertices, Vec3::ZERO);
        let normals = read(normals, "NORMAL")?;
        out.push(MorphTarget {
            name: names
                .get(k)
                .filter(|n| !n.is_empty())
                .cloned()
                .unwrap_or_else(|| format!("target{k}")),
            positions,
            normals,
        });
    }
    Ok(out)
}

/// `mesh.extras.targetNames` (the de-facto convention for morph target names), when present.
fn target_names(mesh: &gltf::Mesh<'_>) -> Vec<String> {
    let extras = mesh
        .extras()
        .as_ref()
        .and_then(|raw| serde_json::from_str::<serde_json::Value>(raw.get()).ok());
    extras
        .as_ref()
        .and_then(|e| e.get("targetNames"))
        .and_then(serde_json::Value::as_array)
        .map(|names| {
            names
                .iter()
                .map(|v| v.as_str().unwrap_or_default().to_owned())
                .collect()
        })
        .unwrap_or_default()
}

/// One primitive as a mesh of its own (normals computed when absent), four influences.
fn read_primitive(
    prim: &gltf::Primitive<'_>,
    buffers: &[gltf::buffer::Data],
    label: &str,
    skin_joints: usize,
) -> Result<SkinnedMesh, GlbMeshError> {
    let missing = |what: &str| GlbMeshError::Accessor {
        mesh: label.to_owned(),
        message: format!("no {what}"),
    };
    let reader = prim.reader(|b| buffers.get(b.index()).map(|d| &d.0[..]));
    let positions: Vec<Vec3> = reader
        .read_positions()
        .ok_or_else(|| missing("POSITION"))?
        .map(Vec3::from)
        .collect();
    let n = positions.len();
    let normals: Vec<Vec3> = reader
        .read_normals()
        .map(|it| it.map(|v| Vec3::from(v).normalize_or(Vec3::Y)).collect())
        .unwrap_or_default();
    let indices: Vec<u32> = match reader.read_indices() {
        Some(i) => i.into_u32().collect(),
        None => (0..u32::try_from(n).unwrap_or(u32::MAX)).collect(),
    };
    let joints: Vec<u16> = reader
        .read_joints(0)
        .ok_or_else(|| missing("JOINTS_0"))?
        .into_u16()
        .flatten()
        .collect();
    let weights: Vec<f32> = reader
        .read_weights(0)
        .ok_or_else(|| missing("WEIGHTS_0"))?
        .into_f32()
        .flatten()
        .collect();
    SkinnedMesh::new(positions, normals, indices, 4, joints, weights, skin_joints).map_err(
        |source| GlbMeshError::Mesh {
            mesh: label.to_owned(),
            source,
        },
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn garbage_is_an_error() {
        assert!(matches!(
            GlbMesh::from_slice(b"not a glb at all"),
            Err(GlbMeshError::Parse { .. })
        ));
        assert!(GlbMesh::from_slice(b"glTF\x02\x00\x00\x00\xff\xff\xff\xff").is_err());
    }

    #[test]
    fn a_file_without_skins_has_no_skinned_mesh() {
        let json =
            br#"{"asset":{"version":"2.0"},"nodes":[{"name":"a"}],"scenes":[{"nodes":[0]}]}"#;
        assert!(matches!(
            GlbMesh::from_slice(json),
            Err(GlbMeshError::NoSkinnedMesh)
        ));
    }
}
