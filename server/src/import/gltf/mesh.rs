//! glTF meshes of one skin: triangle primitives with their joints and weights, remapped to
//! the skeleton's joint order.

use glam::Vec3;
use gltf::accessor::Dimensions;
use gltf::mesh::{Mode, Semantic};
use posecast_proto::SkinnedMesh;

use super::Context;
use crate::asset::AssetMesh;
use crate::import::ImportError;

impl Context<'_> {
    pub(super) fn meshes(
        &self,
        skin: &gltf::Skin<'_>,
        skin_to_skel: &[usize],
        joint_count: usize,
        notes: &mut Vec<String>,
    ) -> Result<Vec<AssetMesh>, ImportError> {
        let mut out = Vec::new();
        for node in self.doc.nodes() {
            let (Some(s), Some(mesh)) = (node.skin(), node.mesh()) else {
                continue;
            };
            if s.index() != skin.index() {
                continue;
            }
            let prims = mesh.primitives().len();
            for prim in mesh.primitives() {
                let mut label = match mesh.name() {
                    Some(n) if !n.is_empty() => n.to_owned(),
                    _ => format!("mesh{}", mesh.index()),
                };
                if prims > 1 {
                    label = format!("{label}#{}", prim.index());
                }
                if prim.mode() != Mode::Triangles {
                    notes.push(format!("{label}: {:?} primitive skipped", prim.mode()));
                    continue;
                }
                let Some(pos) = prim.get(&Semantic::Positions) else {
                    notes.push(format!("{label}: primitive without POSITION skipped"));
                    continue;
                };
                let positions: Vec<Vec3> = self
                    .buffers
                    .read_as(&pos, Dimensions::Vec3, "POSITION")?
                    .chunks_exact(3)
                    .map(Vec3::from_slice)
                    .collect();
                let n = positions.len();
                let normals = match prim.get(&Semantic::Normals) {
                    Some(a) => self
                        .buffers
                        .read_as(&a, Dimensions::Vec3, "NORMAL")?
                        .chunks_exact(3)
                        .map(|c| Vec3::from_slice(c).normalize_or(Vec3::Y))
                        .collect(),
                    None => Vec::new(),
                };
                let indices = match prim.indices() {
                    Some(a) => self.buffers.read_indices(&a)?,
                    None => (0..u32::try_from(n).unwrap_or(u32::MAX)).collect(),
                };
                let mut sets = Vec::new();
                for set in 0..2 {
                    match (
                        prim.get(&Semantic::Joints(set)),
                        prim.get(&Semantic::Weights(set)),
                    ) {
                        (Some(j), Some(w)) => sets.push((j, w)),
                        (None, None) => {}
                        _ => {
                            return Err(ImportError::Mesh {
                                file: self.file.to_owned(),
                                mesh: label,
                                source: posecast_proto::MeshError::NoInfluences,
                            });
                        }
                    }
                }
                if sets.is_empty() {
                    notes.push(format!("{label}: primitive without JOINTS_0 skipped"));
                    continue;
                }
                let influences = 4 * sets.len();
                let mut js = vec![0u16; n * influences];
                let mut ws = vec![0.0f32; n * influences];
                for (s, (ja, wa)) in sets.iter().enumerate() {
                    let jv = self.buffers.read_as(ja, Dimensions::Vec4, "JOINTS")?;
                    let wv = self.buffers.read_as(wa, Dimensions::Vec4, "WEIGHTS")?;
                    if jv.len() != n * 4 || wv.len() != n * 4 {
                        return Err(ImportError::Accessor {
                            file: self.file.to_owned(),
                            accessor: ja.index(),
                            message: format!("JOINTS/WEIGHTS counts differ from {n} vertices"),
                        });
                    }
                    for v in 0..n {
                        for c in 0..4 {
                            let j = jv[v * 4 + c];
                            let w = wv[v * 4 + c];
                            let slot = v * influences + s * 4 + c;
                            ws[slot] = w;
                            if w == 0.0 {
                                continue;
                            }
                            let skel = skin_to_skel
                                .get(j as usize)
                                .filter(|_| j >= 0.0 && j.fract() == 0.0)
                                .ok_or_else(|| ImportError::Accessor {
                                    file: self.file.to_owned(),
                                    accessor: ja.index(),
                                    message: format!(
                                        "vertex {v} uses joint {j}, the skin has {}",
                                        skin_to_skel.len()
                                    ),
                                })?;
                            js[slot] = u16::try_from(*skel).unwrap_or(0);
                        }
                    }
                }
                let mesh =
                    SkinnedMesh::new(positions, normals, indices, influences, js, ws, joint_count)
                        .map_err(|source| ImportError::Mesh {
                            file: self.file.to_owned(),
                            mesh: label.clone(),
                            source,
                        })?;
                out.push(AssetMesh { name: label, mesh });
            }
        }
        Ok(out)
    }
}
