//! glTF meshes of one skin: triangle primitives with their joints and weights, remapped to
//! the skeleton's joint order (of the rig its skin is merged into, see [`super::skins`]).

use std::collections::HashMap;

use glam::{Mat4, Vec3};
use gltf::accessor::Dimensions;
use gltf::mesh::{Mode, Semantic};
use posecast_proto::SkinnedMesh;
use posecast_proto::morph::MorphTarget;

use super::Context;
use crate::asset::AssetMesh;
use crate::import::ImportError;

impl Context<'_> {
    /// The primitives of the nodes skinned by `skin`, their vertices stored as `bake · v` (the
    /// skin's `C_s` in its merged rig) and their joints mapped by `skin_to_skel`.
    pub(super) fn meshes(
        &self,
        skin: &gltf::Skin<'_>,
        skin_to_skel: &[usize],
        bake: Mat4,
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
                let Some((positions, normals, indices)) = self.geometry(&prim, &label, notes)?
                else {
                    continue;
                };
                let targets =
                    self.morph_targets(&mesh, &prim, &label, (positions.len(), &normals), bake)?;
                let (positions, normals) = if bake == Mat4::IDENTITY {
                    (positions, normals)
                } else {
                    let normal_matrix = glam::Mat3::from_mat4(bake).inverse().transpose();
                    (
                        positions
                            .iter()
                            .map(|p| bake.transform_point3(*p))
                            .collect(),
                        normals
                            .iter()
                            .map(|v| (normal_matrix * *v).normalize_or(Vec3::Y))
                            .collect(),
                    )
                };
                let n = positions.len();
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
                        .and_then(|m| m.with_targets(targets))
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

    /// A triangle primitive's positions, normals (empty when absent) and indices; `None`, with
    /// a note, for a primitive that is not triangles or has no positions.
    fn geometry(
        &self,
        prim: &gltf::Primitive<'_>,
        label: &str,
        notes: &mut Vec<String>,
    ) -> Result<Option<Geometry>, ImportError> {
        if prim.mode() != Mode::Triangles {
            notes.push(format!("{label}: {:?} primitive skipped", prim.mode()));
            return Ok(None);
        }
        let Some(pos) = prim.get(&Semantic::Positions) else {
            notes.push(format!("{label}: primitive without POSITION skipped"));
            return Ok(None);
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
        Ok(Some((positions, normals, indices)))
    }

    /// Meshes on nodes without a skin that hang from one of `joints` (the node itself or its
    /// nearest ancestor that is one: each mesh once, however many skins were merged): imported rigidly skinned to that joint, weight 1, their
    /// vertices moved into the joint's bind space, `v_bind = B_j · L · v` with `L` the rest
    /// transforms from the joint down to the mesh node, so that at any pose
    /// `W_j · B_j⁻¹ · v_bind = W_j · L · v`, where the node hierarchy puts them.
    pub(super) fn rigid_meshes(
        &self,
        joints: &[usize],
        skel_of_node: &HashMap<usize, usize>,
        inverse_bind: &[Mat4],
        notes: &mut Vec<String>,
    ) -> Result<Vec<AssetMesh>, ImportError> {
        let joints: std::collections::HashSet<usize> = joints.iter().copied().collect();
        let mut out = Vec::new();
        for node in self.doc.nodes() {
            let (None, Some(mesh)) = (node.skin(), node.mesh()) else {
                continue;
            };
            // From the mesh node up to the nearest joint of this skin: L = L_child … L_node.
            let mut local = Mat4::IDENTITY;
            let mut cur = node.index();
            let mut animated = Vec::new();
            let mut steps = 0;
            let joint = loop {
                if joints.contains(&cur) {
                    break Some(cur);
                }
                if self.animated.get(cur).copied().unwrap_or(false) {
                    animated.push(self.nodes.names[cur].clone());
                }
                local = self.nodes.local[cur].to_mat4() * local;
                match self.nodes.parent[cur] {
                    Some(p) if steps <= self.nodes.parent.len() => cur = p,
                    _ => break None,
                }
                steps += 1;
            };
            let Some(s) = joint.and_then(|j| skel_of_node.get(&j).copied()) else {
                continue;
            };
            let Some(bind) = inverse_bind
                .get(s)
                .filter(|m| m.determinant().abs() > f32::MIN_POSITIVE)
                .map(Mat4::inverse)
            else {
                continue;
            };
            let to_bind = bind * local;
            let normal_matrix = glam::Mat3::from_mat4(to_bind).inverse().transpose();
            let joint_name = &self.nodes.names[joint.unwrap_or_default()];
            if !animated.is_empty() {
                notes.push(format!(
                    "mesh {} hangs from joint {joint_name} through animated nodes {animated:?}: \
                     it follows their rest transforms",
                    mesh.name().unwrap_or("(unnamed)")
                ));
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
                let Some((positions, normals, indices)) = self.geometry(&prim, &label, notes)?
                else {
                    continue;
                };
                let n = positions.len();
                let targets = self.morph_targets(&mesh, &prim, &label, (n, &normals), to_bind)?;
                let positions = positions
                    .iter()
                    .map(|p| to_bind.transform_point3(*p))
                    .collect();
                let normals = normals
                    .iter()
                    .map(|v| (normal_matrix * *v).normalize_or(Vec3::Y))
                    .collect();
                let joint_index = u16::try_from(s).unwrap_or(0);
                let mesh = SkinnedMesh::new(
                    positions,
                    normals,
                    indices,
                    1,
                    vec![joint_index; n],
                    vec![1.0; n],
                    inverse_bind.len(),
                )
                .and_then(|m| m.with_targets(targets))
                .map_err(|source| ImportError::Mesh {
                    file: self.file.to_owned(),
                    mesh: label.clone(),
                    source,
                })?;
                out.push(AssetMesh {
                    name: format!("{label} (rigid on {joint_name})"),
                    mesh,
                });
            }
        }
        Ok(out)
    }
}

impl Context<'_> {
    /// A primitive's morph targets, displacements taken through `to_bind`'s linear part `L`
    /// (positions: `L·Δp`), named by `mesh.extras.targetNames` (else `target<k>`). Normals are
    /// stored normalised after `N = L⁻ᵀ` (`n' = N·n / |N·n|`), so a normal displacement
    /// becomes `N·Δn / |N·n|`: `n' + Δn'` then points where `N·(n + Δn)` does, whatever
    /// `to_bind`'s scale (a 0.01 armature). `vertices` is the primitive's vertex count,
    /// `normals` its own normals (unit, file space; empty: none given). Dense and sparse accessors alike (the accessor reader
    /// expands sparse ones).
    fn morph_targets(
        &self,
        mesh: &gltf::Mesh<'_>,
        prim: &gltf::Primitive<'_>,
        label: &str,
        (vertices, normals): (usize, &[Vec3]),
        to_bind: Mat4,
    ) -> Result<Vec<MorphTarget>, ImportError> {
        let names = target_names(mesh);
        let linear = glam::Mat3::from_mat4(to_bind);
        let normal_matrix = linear.inverse().transpose();
        let mut out = Vec::new();
        for (k, target) in prim.morph_targets().enumerate() {
            let read = |a: Option<gltf::Accessor<'_>>,
                        what: &str|
             -> Result<Vec<Vec3>, ImportError> {
                let Some(a) = a else {
                    return Ok(Vec::new());
                };
                let v: Vec<Vec3> = self
                    .buffers
                    .read_as(&a, Dimensions::Vec3, what)?
                    .chunks_exact(3)
                    .map(Vec3::from_slice)
                    .collect();
                if v.len() == vertices {
                    Ok(v)
                } else {
                    Err(ImportError::Accessor {
                        file: self.file.to_owned(),
                        accessor: a.index(),
                        message: format!(
                            "{label}: morph target {k} {what} has {} entries for {vertices} vertices",
                            v.len()
                        ),
                    })
                }
            };
            let mut positions = read(target.positions(), "POSITION")?;
            if positions.is_empty() {
                positions = vec![Vec3::ZERO; vertices];
            }
            let normal_deltas = read(target.normals(), "NORMAL")?;
            let normal_deltas = normal_deltas
                .iter()
                .enumerate()
                .map(|(v, d)| {
                    let scale = normals
                        .get(v)
                        .map(|n| (normal_matrix * *n).length())
                        .filter(|l| l.is_finite() && *l > f32::MIN_POSITIVE)
                        .map_or(1.0, |l| 1.0 / l);
                    let d = normal_matrix * *d * scale;
                    if d.is_finite() { d } else { Vec3::ZERO }
                })
                .collect();
            out.push(MorphTarget {
                name: names
                    .get(k)
                    .filter(|n| !n.is_empty())
                    .cloned()
                    .unwrap_or_else(|| format!("target{k}")),
                positions: positions.iter().map(|d| linear * *d).collect(),
                normals: normal_deltas,
            });
        }
        Ok(out)
    }
}

/// `mesh.extras.targetNames` (the de-facto convention for morph target names), when present.
pub(super) fn target_names(mesh: &gltf::Mesh<'_>) -> Vec<String> {
    let Some(raw) = mesh.extras() else {
        return Vec::new();
    };
    #[derive(serde::Deserialize)]
    struct Extras {
        #[serde(rename = "targetNames", default)]
        target_names: Vec<serde_json::Value>,
    }
    serde_json::from_str::<Extras>(raw.get())
        .map(|e| {
            e.target_names
                .into_iter()
                .map(|v| v.as_str().unwrap_or_default().to_owned())
                .collect()
        })
        .unwrap_or_default()
}

/// A primitive's positions, normals and triangle indices.
type Geometry = (Vec<Vec3>, Vec<Vec3>, Vec<u32>);
