//! The CPU linear-blend-skinning reference (seed 001) and the skinned mesh it works on.
//!
//! GPU paths are tested against [`skin_cpu`]; keep it simple and exact rather than fast.

use glam::{Mat3, Mat4, Vec3};
use serde::{Deserialize, Serialize};

/// Why mesh data was refused.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum MeshError {
    /// A per-vertex list does not have the length the vertex count asks for.
    #[error("{what} has {actual} entries, expected {expected}")]
    Length {
        /// Which list is wrong (`"joint indices"`, `"weights"` or `"normals"`).
        what: &'static str,
        /// The length it should have (vertices, or vertices × influences).
        expected: usize,
        /// Its actual length.
        actual: usize,
    },
    /// `influences` was 0: every vertex needs at least one (joint, weight) slot.
    #[error("influences per vertex must be at least 1")]
    NoInfluences,
    /// A vertex gives a non-zero weight to a joint the skeleton does not have.
    #[error("vertex {vertex} refers to joint {joint}, but the skeleton has {joints} joints")]
    JointOutOfRange {
        /// Index of the vertex.
        vertex: usize,
        /// The joint index it names.
        joint: u16,
        /// The number of joints in the skeleton.
        joints: usize,
    },
    /// A triangle index names a vertex past the end of the positions.
    #[error("triangle index {index} at position {at} is past the {vertices} vertices")]
    IndexOutOfRange {
        /// Position of the bad entry in the index list.
        at: usize,
        /// The vertex index it holds.
        index: u32,
        /// The number of vertices.
        vertices: usize,
    },
    /// The index list's length is not a whole number of triangles.
    #[error("index count {count} is not a multiple of 3")]
    NotTriangles {
        /// The length of the index list.
        count: usize,
    },
    /// A vertex has a weight that is negative, NaN or infinite.
    #[error("vertex {vertex} has a negative or non-finite weight {weight}")]
    BadWeight {
        /// Index of the vertex.
        vertex: usize,
        /// The offending weight.
        weight: f32,
    },
    /// All of a vertex's weights are zero, so it cannot be renormalised.
    #[error("vertex {vertex}'s weights sum to zero, so no joint moves it")]
    Unweighted {
        /// Index of the vertex.
        vertex: usize,
    },
    /// A vertex's position or normal has a NaN or infinite component.
    #[error("vertex {vertex} has a non-finite {what}")]
    NotFinite {
        /// Index of the vertex.
        vertex: usize,
        /// Which attribute (`"position"` or `"normal"`).
        what: &'static str,
    },
}

/// A triangle mesh bound to a skeleton: `influences` (joint, weight) pairs per vertex, weights
/// summing to one.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SkinnedMesh {
    positions: Vec<Vec3>,
    normals: Vec<Vec3>,
    indices: Vec<u32>,
    influences: usize,
    joints: Vec<u16>,
    weights: Vec<f32>,
    /// Morph targets in glTF order (none for most meshes).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    targets: Vec<MorphTarget>,
}

impl SkinnedMesh {
    /// Checks and builds a mesh in bind pose (model space). `joints` and `weights` hold
    /// `influences` entries per vertex; weights are renormalised to sum to one. `normals` may be
    /// empty, in which case area-weighted vertex normals are computed from the triangles.
    pub fn new(
        positions: Vec<Vec3>,
        normals: Vec<Vec3>,
        indices: Vec<u32>,
        influences: usize,
        joints: Vec<u16>,
        mut weights: Vec<f32>,
        joint_count: usize,
    ) -> Result<Self, MeshError> {
        let n = positions.len();
        if influences == 0 {
            return Err(MeshError::NoInfluences);
        }
        check_len("joint indices", n * influences, joints.len())?;
        check_len("weights", n * influences, weights.len())?;
        if !indices.len().is_multiple_of(3) {
            return Err(MeshError::NotTriangles {
                count: indices.len(),
            });
        }
        if let Some((at, &index)) = indices.iter().enumerate().find(|(_, i)| **i as usize >= n) {
            return Err(MeshError::IndexOutOfRange {
                at,
                index,
                vertices: n,
            });
        }
        for (vertex, p) in positions.iter().enumerate() {
            if !p.is_finite() {
                return Err(MeshError::NotFinite {
                    vertex,
                    what: "position",
                });
            }
        }
        let normals = if normals.is_empty() {
            compute_normals(&positions, &indices)
        } else {
            check_len("normals", n, normals.len())?;
            if let Some(vertex) = normals.iter().position(|v| !v.is_finite()) {
                return Err(MeshError::NotFinite {
                    vertex,
                    what: "normal",
                });
            }
            normals
        };
        for vertex in 0..n {
            let range = vertex * influences..(vertex + 1) * influences;
            let mut sum = 0.0;
            for (&joint, &weight) in joints[range.clone()].iter().zip(&weights[range.clone()]) {
                if !(weight.is_finite() && weight >= 0.0) {
                    return Err(MeshError::BadWeight { vertex, weight });
                }
                if weight > 0.0 && joint as usize >= joint_count {
                    return Err(MeshError::JointOutOfRange {
                        vertex,
                        joint,
                        joints: joint_count,
                    });
                }
                sum += weight;
            }
            if sum <= 0.0 {
                return Err(MeshError::Unweighted { vertex });
            }
            weights[range].iter_mut().for_each(|w| *w /= sum);
        }
        // A zero weight may name any joint; point it at joint 0 so every index is in range.
        let mut joints = joints;
        for (j, w) in joints.iter_mut().zip(&weights) {
            if *w == 0.0 {
                *j = 0;
            }
        }
        Ok(Self {
            positions,
            normals,
            indices,
            influences,
            joints,
            weights,
            targets: Vec::new(),
        })
    }

    /// The same mesh with these morph targets (replacing any it had).
    ///
    /// # Errors
    /// A target whose lists do not have one entry per vertex, or with a non-finite entry.
    pub fn with_targets(mut self, targets: Vec<MorphTarget>) -> Result<Self, MeshError> {
        for t in &targets {
            t.check(self.vertex_count())?;
        }
        self.targets = targets;
        Ok(self)
    }

    /// The same mesh without morph targets.
    #[must_use]
    pub fn without_targets(mut self) -> Self {
        self.targets = Vec::new();
        self
    }

    /// Morph targets, in the file's order.
    #[must_use]
    pub fn targets(&self) -> &[MorphTarget] {
        &self.targets
    }

    /// Number of vertices.
    #[must_use]
    pub fn vertex_count(&self) -> usize {
        self.positions.len()
    }
    /// Bind-pose vertex positions, model space, metres.
    #[must_use]
    pub fn positions(&self) -> &[Vec3] {
        &self.positions
    }
    /// Bind-pose vertex normals, model space (given, or computed area-weighted).
    #[must_use]
    pub fn normals(&self) -> &[Vec3] {
        &self.normals
    }
    /// Triangle list: three vertex indices per triangle.
    #[must_use]
    pub fn indices(&self) -> &[u32] {
        &self.indices
    }
    /// (joint, weight) pairs per vertex.
    #[must_use]
    pub fn influences(&self) -> usize {
        self.influences
    }
    /// Joint index of each influence slot, [`Self::influences`] per vertex; a zero-weight
    /// slot points at joint 0.
    #[must_use]
    pub fn joints(&self) -> &[u16] {
        &self.joints
    }
    /// Weight of each influence slot, [`Self::influences`] per vertex, each vertex's summing
    /// to one.
    #[must_use]
    pub fn weights(&self) -> &[f32] {
        &self.weights
    }

    /// The same mesh with `count` influences per vertex: the heaviest are kept (and
    /// renormalised) when shrinking, zero-weight slots added when growing. GPU paths use 4 or 8.
    #[must_use]
    pub fn with_influences(&self, count: usize) -> Self {
        let count = count.max(1);
        let mut joints = Vec::with_capacity(self.vertex_count() * count);
        let mut weights = Vec::with_capacity(self.vertex_count() * count);
        for v in 0..self.vertex_count() {
            let range = v * self.influences..(v + 1) * self.influences;
            let mut pairs: Vec<(u16, f32)> = self.joints[range.clone()]
                .iter()
                .copied()
                .zip(self.weights[range].iter().copied())
                .collect();
            pairs.sort_by(|a, b| b.1.total_cmp(&a.1));
            pairs.resize(count, (0, 0.0));
            let sum: f32 = pairs.iter().map(|p| p.1).sum();
            for (j, w) in pairs {
                joints.push(j);
                weights.push(if sum > 0.0 { w / sum } else { w });
            }
        }
        Self {
            joints,
            weights,
            influences: count,
            ..self.clone()
        }
    }

    /// Applies `f` to positions and `g` to normals, e.g. to re-orient or rescale the mesh.
    /// Morph displacements follow: `Δp' = f(p + Δp) − f(p)`, `Δn' = g(n + Δn) − g(n)`.
    #[must_use]
    pub fn map_vertices(&self, f: impl Fn(Vec3) -> Vec3, g: impl Fn(Vec3) -> Vec3) -> Self {
        let targets = self
            .targets
            .iter()
            .map(|t| MorphTarget {
                name: t.name.clone(),
                positions: (self.positions.iter().zip(&t.positions))
                    .map(|(&p, &d)| f(p + d) - f(p))
                    .collect(),
                normals: (self.normals.iter().zip(&t.normals))
                    .map(|(&n, &d)| g(n + d) - g(n))
                    .collect(),
            })
            .collect();
        Self {
            positions: self.positions.iter().map(|&p| f(p)).collect(),
            normals: self
                .normals
                .iter()
                .map(|&n| g(n).normalize_or_zero())
                .collect(),
            targets,
            ..self.clone()
        }
    }

    /// Axis-aligned bounds of the bind-pose positions.
    #[must_use]
    pub fn bounds(&self) -> (Vec3, Vec3) {
        self.positions.iter().fold(
            (Vec3::splat(f32::MAX), Vec3::splat(f32::MIN)),
            |(lo, hi), &p| (lo.min(p), hi.max(p)),
        )
    }
}

fn check_len(what: &'static str, expected: usize, actual: usize) -> Result<(), MeshError> {
    if expected == actual {
        Ok(())
    } else {
        Err(MeshError::Length {
            what,
            expected,
            actual,
        })
    }
}

/// Area-weighted vertex normals: the sum of the (unnormalised) cross products of every
/// triangle that uses the vertex, normalised. Indices must be in range.
#[must_use]
pub fn compute_normals(positions: &[Vec3], indices: &[u32]) -> Vec<Vec3> {
    let mut normals = vec![Vec3::ZERO; positions.len()];
    for tri in indices.chunks_exact(3) {
        let [a, b, c] = [tri[0] as usize, tri[1] as usize, tri[2] as usize];
        let (Some(&pa), Some(&pb), Some(&pc)) =
            (positions.get(a), positions.get(b), positions.get(c))
        else {
            continue;
        };
        let n = (pb - pa).cross(pc - pa);
        for i in [a, b, c] {
            normals[i] += n;
        }
    }
    normals
        .iter()
        .map(|n| n.try_normalize().unwrap_or(Vec3::Y))
        .collect()
}

/// The blended matrix `Σ_k w_k M_{j_k}` of one vertex.
#[must_use]
pub fn blend_matrix(mesh: &SkinnedMesh, skinning: &[Mat4], vertex: usize) -> Mat4 {
    let k = mesh.influences;
    let range = vertex * k..(vertex + 1) * k;
    let mut blended = Mat4::ZERO;
    for (&j, &w) in mesh.joints[range.clone()].iter().zip(&mesh.weights[range]) {
        if w != 0.0 {
            blended += skinning[j as usize] * w;
        }
    }
    blended
}

/// Linear blend skinning (seed 001): `v' = Σ_k w_k M_{j_k} v`, and the normal
/// `n' = normalize((Σ_k w_k M_{j_k})₃ₓ₃⁻ᵀ n)`. `skinning` holds `M_j = W_j · B_j⁻¹`.
///
/// # Panics
/// When `skinning` has fewer matrices than the mesh's joints refer to, or an output buffer is
/// not one entry per vertex (caller bugs: [`SkinnedMesh::new`] checked the joint range).
pub fn skin_cpu(
    mesh: &SkinnedMesh,
    skinning: &[Mat4],
    positions: &mut [Vec3],
    normals: &mut [Vec3],
) {
    let n = mesh.vertex_count();
    assert!(
        positions.len() == n && normals.len() == n,
        "output buffers must hold {n} vertices"
    );
    for v in 0..n {
        let m = blend_matrix(mesh, skinning, v);
        positions[v] = m.transform_point3(mesh.positions[v]);
        let linear = Mat3::from_mat4(m);
        normals[v] = (linear.inverse().transpose() * mesh.normals[v]).normalize_or_zero();
    }
}

/// One morph target of a mesh (re-exported by [`crate::morph`], which weighs them): per-vertex displacements of positions and normals.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct MorphTarget {
    /// The target's name (glTF `mesh.extras.targetNames`, else `target<k>`).
    pub name: String,
    /// Position displacement of every vertex, model (bind) space, metres.
    pub positions: Vec<Vec3>,
    /// Normal displacement of every vertex; empty when the target leaves normals alone.
    #[serde(default)]
    pub normals: Vec<Vec3>,
}

impl MorphTarget {
    /// Checks the target against a mesh of `vertices` vertices.
    ///
    /// # Errors
    /// A list of the wrong length, or a non-finite displacement.
    pub fn check(&self, vertices: usize) -> Result<(), MeshError> {
        if self.positions.len() != vertices {
            return Err(MeshError::Length {
                what: "morph target positions",
                expected: vertices,
                actual: self.positions.len(),
            });
        }
        if !self.normals.is_empty() && self.normals.len() != vertices {
            return Err(MeshError::Length {
                what: "morph target normals",
                expected: vertices,
                actual: self.normals.len(),
            });
        }
        for (what, list) in [
            ("morph position", &self.positions),
            ("morph normal", &self.normals),
        ] {
            if let Some(vertex) = list.iter().position(|d| !d.is_finite()) {
                return Err(MeshError::NotFinite { vertex, what });
            }
        }
        Ok(())
    }

    /// Whether the target displaces no vertex at all.
    #[must_use]
    pub fn is_empty(&self) -> bool {
        self.positions.iter().all(|d| *d == Vec3::ZERO)
            && self.normals.iter().all(|d| *d == Vec3::ZERO)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fk::PoseBuffers;
    use crate::testing::f32s;
    use crate::testing::{arb_skeleton, arb_transforms};
    use proptest::prelude::*;

    fn random_mesh(joints: usize, seeds: &[(f32, f32, f32, u16, u16, f32)]) -> SkinnedMesh {
        let positions = seeds
            .iter()
            .map(|s| Vec3::new(s.0, s.1, s.2))
            .collect::<Vec<_>>();
        let normals = seeds
            .iter()
            .map(|s| Vec3::new(s.1, s.2, s.0 + 3.0).normalize())
            .collect();
        let mut js = Vec::new();
        let mut ws = Vec::new();
        for s in seeds {
            js.extend([
                s.3 % joints as u16,
                s.4 % joints as u16,
                0,
                (s.3 / 2) % joints as u16,
            ]);
            ws.extend([s.5, 1.0 - s.5, 0.0, 0.25]);
        }
        SkinnedMesh::new(positions, normals, vec![], 4, js, ws, joints).unwrap()
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(48))]
        /// Bind pose (`W_j = B_j`, so every `M_j = I`) skins every vertex to itself.
        #[test]
        fn bind_pose_is_identity(
            s in arb_skeleton(1..120),
            seeds in prop::collection::vec((f32s(-2.0..2.0), f32s(-2.0..2.0), f32s(-2.0..2.0), 0u16..500, 0u16..500, f32s(0.0..1.0)), 1..200),
        ) {
            let mesh = random_mesh(s.len(), &seeds);
            let mut buffers = PoseBuffers::new(&s);
            buffers.update(&s, s.rest());
            let mut p = vec![Vec3::ZERO; mesh.vertex_count()];
            let mut n = vec![Vec3::ZERO; mesh.vertex_count()];
            skin_cpu(&mesh, &buffers.skinning, &mut p, &mut n);
            for v in 0..mesh.vertex_count() {
                prop_assert!((p[v] - mesh.positions()[v]).length() < 2e-3, "vertex {v}: {} vs {}", p[v], mesh.positions()[v]);
                prop_assert!((n[v] - mesh.normals()[v]).length() < 2e-3);
            }
        }

        /// With one influence, skinning equals transforming by that joint's matrix, and the
        /// normal stays perpendicular to a transformed tangent (the inverse-transpose property).
        #[test]
        fn rigid_influence_matches_matrix(
            (s, pose) in arb_skeleton(1..40).prop_flat_map(|s| { let n = s.len(); (Just(s), arb_transforms(n)) }),
            p in prop::array::uniform3(f32s(-1.0..1.0)),
            joint in 0usize..1000,
        ) {
            let j = (joint % s.len()) as u16;
            let normal = Vec3::new(0.0, 0.0, 1.0);
            let tangent = Vec3::new(1.0, 0.5, 0.0);
            let mesh = SkinnedMesh::new(vec![Vec3::from(p)], vec![normal], vec![], 1, vec![j], vec![3.0], s.len()).unwrap();
            prop_assert_eq!(mesh.weights()[0], 1.0);
            let mut b = PoseBuffers::new(&s);
            b.update(&s, &pose);
            let mut out_p = [Vec3::ZERO];
            let mut out_n = [Vec3::ZERO];
            skin_cpu(&mesh, &b.skinning, &mut out_p, &mut out_n);
            let m = b.skinning[j as usize];
            let expected = m.transform_point3(Vec3::from(p));
            prop_assert!((out_p[0] - expected).length() <= 1e-3 * (1.0 + expected.length()));
            let t = m.transform_vector3(tangent).normalize();
            prop_assert!(out_n[0].dot(t).abs() < 1e-3);
        }
    }

    /// World matrix of `joint` by walking up its parent chain in f64 — recursion instead of
    /// the forward loop in `fk`, so it shares no code with the path under test.
    fn world_f64(s: &crate::Skeleton, pose: &[crate::Transform], joint: usize) -> glam::DMat4 {
        let t = &pose[joint];
        let local = glam::DMat4::from_scale_rotation_translation(
            t.scale.as_dvec3(),
            t.rotation.as_dquat(),
            t.translation.as_dvec3(),
        );
        match s.parents()[joint] {
            Some(p) => world_f64(s, pose, p) * local,
            None => local,
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(48))]
        /// Four influences, away from the bind pose: each vertex is the weighted sum of its
        /// positions under each influence, `Σ_k w_k (W_k B_k⁻¹ v)`, computed per influence in
        /// f64 — not through a blended matrix; the normal is perpendicular to every tangent
        /// mapped by the blended linear part (the inverse-transpose property).
        #[test]
        fn several_influences_match_the_per_influence_sum(
            (s, pose) in arb_skeleton(2..30).prop_flat_map(|s| { let n = s.len(); (Just(s), arb_transforms(n)) }),
            seeds in prop::collection::vec((f32s(-1.0..1.0), f32s(-1.0..1.0), f32s(-1.0..1.0), 0u16..500, 0u16..500, f32s(0.05..0.95)), 1..40),
        ) {
            let mesh = random_mesh(s.len(), &seeds);
            let mut b = PoseBuffers::new(&s);
            b.update(&s, &pose);
            let n = mesh.vertex_count();
            let (mut out_p, mut out_n) = (vec![Vec3::ZERO; n], vec![Vec3::ZERO; n]);
            skin_cpu(&mesh, &b.skinning, &mut out_p, &mut out_n);
            let k = mesh.influences();
            for v in 0..n {
                let p = mesh.positions()[v].as_dvec3();
                let mut expected = glam::DVec3::ZERO;
                let mut linear = glam::DMat3::ZERO;
                let mut distinct = std::collections::BTreeSet::new();
                for i in v * k..(v + 1) * k {
                    let (j, w) = (usize::from(mesh.joints()[i]), f64::from(mesh.weights()[i]));
                    if w == 0.0 { continue; }
                    distinct.insert(j);
                    let m = world_f64(&s, &pose, j) * s.inverse_bind()[j].as_dmat4();
                    expected += w * m.transform_point3(p);
                    linear += glam::DMat3::from_mat4(m) * w;
                }
                let got = out_p[v].as_dvec3();
                prop_assert!((got - expected).length() <= 1e-3 * (1.0 + expected.length()),
                    "vertex {v} ({} influences): {got} vs {expected}", distinct.len());
                if linear.determinant().abs() > 1e-3 {
                    let normal = mesh.normals()[v].as_dvec3();
                    let t1 = normal.any_orthonormal_vector();
                    let t2 = normal.cross(t1);
                    for t in [t1, t2] {
                        let mapped = (linear * t).normalize();
                        prop_assert!(out_n[v].as_dvec3().dot(mapped).abs() < 2e-3, "vertex {v} normal");
                    }
                }
            }
        }
    }

    #[test]
    fn rejects_bad_meshes() {
        let p = vec![Vec3::ZERO; 3];
        let ok = |idx: Vec<u32>, j: Vec<u16>, w: Vec<f32>| {
            SkinnedMesh::new(p.clone(), vec![], idx, 1, j, w, 2)
        };
        assert!(matches!(
            ok(vec![0, 1], vec![0; 3], vec![1.0; 3]),
            Err(MeshError::NotTriangles { .. })
        ));
        assert!(matches!(
            ok(vec![0, 1, 3], vec![0; 3], vec![1.0; 3]),
            Err(MeshError::IndexOutOfRange { .. })
        ));
        assert!(matches!(
            ok(vec![], vec![0, 5, 0], vec![1.0; 3]),
            Err(MeshError::JointOutOfRange { .. })
        ));
        assert!(matches!(
            ok(vec![], vec![0; 3], vec![1.0, 0.0, 1.0]),
            Err(MeshError::Unweighted { vertex: 1 })
        ));
        assert!(matches!(
            ok(vec![], vec![0; 3], vec![1.0, f32::NAN, 1.0]),
            Err(MeshError::BadWeight { .. })
        ));
        assert!(matches!(
            ok(vec![], vec![0; 2], vec![1.0; 2]),
            Err(MeshError::Length { .. })
        ));
    }

    #[test]
    fn computed_normals_face_the_winding() {
        let p = vec![Vec3::ZERO, Vec3::X, Vec3::Y];
        let m = SkinnedMesh::new(p, vec![], vec![0, 1, 2], 1, vec![0; 3], vec![1.0; 3], 1).unwrap();
        assert!(m.normals().iter().all(|n| n.abs_diff_eq(Vec3::Z, 1e-6)));
    }

    #[test]
    fn with_influences_keeps_heaviest() {
        let m = SkinnedMesh::new(
            vec![Vec3::ZERO],
            vec![Vec3::Y],
            vec![],
            3,
            vec![0, 1, 2],
            vec![0.2, 0.5, 0.3],
            3,
        )
        .unwrap();
        let two = m.with_influences(2);
        assert_eq!(two.joints(), &[1, 2]);
        assert!((two.weights()[0] - 0.625).abs() < 1e-6);
        let four = m.with_influences(4);
        assert_eq!(four.weights().len(), 4);
        assert_eq!(four.weights()[3], 0.0);
    }
}
