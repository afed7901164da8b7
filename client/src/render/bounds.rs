//! Conservative bounds of a skinned mesh from its pose in O(joints), for framing the camera
//! without skinning every vertex on the CPU.

use glam::{Mat4, Vec3};
use posecast_proto::SkinnedMesh;

/// An axis-aligned box, `min ≤ max` component-wise.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Aabb {
    /// The corner with the smallest coordinates, in the space of the points it bounds.
    pub min: Vec3,
    /// The corner with the largest coordinates, same space.
    pub max: Vec3,
}

impl Aabb {
    /// The smallest box holding every point, or `None` for no points.
    #[must_use]
    pub fn from_points(points: impl IntoIterator<Item = Vec3>) -> Option<Self> {
        let mut points = points.into_iter();
        let first = points.next()?;
        Some(points.fold(
            Self {
                min: first,
                max: first,
            },
            |b, p| Self {
                min: b.min.min(p),
                max: b.max.max(p),
            },
        ))
    }

    /// The smallest box holding both boxes.
    #[must_use]
    pub fn union(self, other: Self) -> Self {
        Self {
            min: self.min.min(other.min),
            max: self.max.max(other.max),
        }
    }

    /// The box's centre, `(min + max) / 2`.
    #[must_use]
    pub fn center(&self) -> Vec3 {
        (self.min + self.max) * 0.5
    }

    /// Length of the diagonal.
    #[must_use]
    pub fn size(&self) -> f32 {
        (self.max - self.min).length()
    }

    /// The eight corners.
    #[must_use]
    pub fn corners(&self) -> [Vec3; 8] {
        let (a, b) = (self.min, self.max);
        [
            Vec3::new(a.x, a.y, a.z),
            Vec3::new(b.x, a.y, a.z),
            Vec3::new(a.x, b.y, a.z),
            Vec3::new(b.x, b.y, a.z),
            Vec3::new(a.x, a.y, b.z),
            Vec3::new(b.x, a.y, b.z),
            Vec3::new(a.x, b.y, b.z),
            Vec3::new(b.x, b.y, b.z),
        ]
    }

    /// Whether `p` lies inside, allowing `slack` outside each face.
    #[must_use]
    pub fn contains(&self, p: Vec3, slack: f32) -> bool {
        p.cmpge(self.min - slack).all() && p.cmple(self.max + slack).all()
    }

    /// The box around the image of this box under an affine matrix.
    #[must_use]
    pub fn transformed(&self, m: &Mat4) -> Self {
        let corners = self.corners().map(|c| m.transform_point3(c));
        let mut out = Self {
            min: corners[0],
            max: corners[0],
        };
        for c in &corners[1..] {
            out.min = out.min.min(*c);
            out.max = out.max.max(*c);
        }
        out
    }
}

/// For each joint, the box in that joint's *bind space* (`B_j⁻¹ v`) of the bind-pose vertices
/// it influences.
///
/// A skinned vertex `v' = Σ_k w_k W_{j_k} (B_{j_k}⁻¹ v)` with `w_k ≥ 0`, `Σ w_k = 1` is a
/// convex combination of points `W_{j_k} (B_{j_k}⁻¹ v)`, each inside the joint's box carried
/// by its world matrix `W_{j_k}`; so the box around all those carried boxes holds every
/// skinned vertex, for any pose.
#[derive(Clone, Debug)]
pub struct JointBounds {
    boxes: Vec<Option<Aabb>>,
}

impl JointBounds {
    /// Builds the boxes from the mesh's influences and the skeleton's inverse bind matrices.
    /// Influences naming a joint past `inverse_bind` are ignored (the caller validated them).
    #[must_use]
    pub fn new(inverse_bind: &[Mat4], mesh: &SkinnedMesh) -> Self {
        let mut boxes: Vec<Option<Aabb>> = vec![None; inverse_bind.len()];
        let k = mesh.influences();
        for (v, &p) in mesh.positions().iter().enumerate() {
            let range = v * k..(v + 1) * k;
            let (Some(joints), Some(weights)) =
                (mesh.joints().get(range.clone()), mesh.weights().get(range))
            else {
                continue;
            };
            for (&j, &w) in joints.iter().zip(weights) {
                let j = usize::from(j);
                let (Some(slot), Some(ib)) = (boxes.get_mut(j), inverse_bind.get(j)) else {
                    continue;
                };
                if w <= 0.0 {
                    continue;
                }
                let local = ib.transform_point3(p);
                *slot = Some(match *slot {
                    Some(b) => b.union(Aabb {
                        min: local,
                        max: local,
                    }),
                    None => Aabb {
                        min: local,
                        max: local,
                    },
                });
            }
        }
        Self { boxes }
    }

    /// A box holding every skinned vertex for world matrices `world` (`W_j`, model space).
    #[must_use]
    pub fn skinned(&self, world: &[Mat4]) -> Option<Aabb> {
        self.boxes
            .iter()
            .zip(world)
            .filter_map(|(b, w)| b.map(|b| b.transformed(w)))
            .reduce(Aabb::union)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::procedural::{TubeOptions, tube_mesh};
    use posecast_proto::fk::PoseBuffers;
    use posecast_proto::skinning::skin_cpu;
    use posecast_proto::testing::{arb_skeleton, arb_transforms};
    use proptest::prelude::*;

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(32))]
        /// Every CPU-skinned vertex lies inside the pose's joint-box bound.
        #[test]
        fn skinned_vertices_lie_inside(
            (s, pose) in arb_skeleton(2..24).prop_flat_map(|s| { let n = s.len(); (Just(s), arb_transforms(n)) }),
        ) {
            let mesh = tube_mesh(&s, &TubeOptions { sides: 5, rings: 4, radius: 0.2 }).unwrap();
            let bounds = JointBounds::new(s.inverse_bind(), &mesh);
            let mut buffers = PoseBuffers::new(&s);
            buffers.update(&s, &pose);
            let mut p = vec![Vec3::ZERO; mesh.vertex_count()];
            let mut n = vec![Vec3::ZERO; mesh.vertex_count()];
            skin_cpu(&mesh, &buffers.skinning, &mut p, &mut n);
            let Some(b) = bounds.skinned(&buffers.world) else {
                prop_assert_eq!(mesh.vertex_count(), 0);
                return Ok(());
            };
            let slack = 1e-4 * (1.0 + b.min.abs().max(b.max.abs()).max_element());
            for v in &p {
                prop_assert!(b.contains(*v, slack), "{v} outside {b:?}");
            }
        }
    }
}
