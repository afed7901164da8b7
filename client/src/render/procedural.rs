//! Procedural skinned meshes: tubes along a skeleton's bones, and a small articulated figure.
//! For demos, benchmarks and tests, where no imported asset is at hand.

use glam::{Mat4, Quat, Vec3};
use posecast_proto::{MeshError, Skeleton, SkinnedMesh, Transform};
use std::f32::consts::TAU;

/// Shape of the tubes [`tube_mesh`] builds.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TubeOptions {
    /// Vertices around each ring (at least 3).
    pub sides: usize,
    /// Rings along each bone (at least 2).
    pub rings: usize,
    /// Tube radius as a fraction of the bone's length.
    pub radius: f32,
}

impl Default for TubeOptions {
    fn default() -> Self {
        Self {
            sides: 12,
            rings: 6,
            radius: 0.15,
        }
    }
}

impl TubeOptions {
    /// Vertices one bone's tube has.
    #[must_use]
    pub fn vertices_per_bone(&self) -> usize {
        self.sides.max(3) * self.rings.max(2)
    }
}

/// A tube around every bone (joint → child) of the skeleton's bind pose, with four influences
/// per vertex: mostly the bone's joint `p`, blending towards `p`'s parent near the start, towards
/// the child `c` near the end, and towards `c`'s first child at the very end (each with a small
/// floor, so all four are non-zero wherever those joints exist); weights
/// are renormalised by [`SkinnedMesh::new`]. Triangles wind counter-clockwise seen from outside,
/// so their winding agrees with the outward normals. Bones shorter than 1e-6 get no tube.
pub fn tube_mesh(skeleton: &Skeleton, options: &TubeOptions) -> Result<SkinnedMesh, MeshError> {
    let sides = options.sides.max(3);
    let rings = options.rings.max(2);
    let bind: Vec<Vec3> = skeleton
        .bind_matrices()
        .iter()
        .map(|b| b.w_axis.truncate())
        .collect();
    let first_child: Vec<Option<usize>> = (0..skeleton.len())
        .map(|j| skeleton.children(j).next())
        .collect();
    let mut positions = Vec::new();
    let mut normals = Vec::new();
    let mut joints = Vec::new();
    let mut weights = Vec::new();
    let mut indices = Vec::new();
    for (c, parent) in skeleton.parents().iter().enumerate() {
        let Some(p) = *parent else { continue };
        let (start, end) = (bind[p], bind[c]);
        let axis = end - start;
        let length = axis.length();
        if length.is_nan() || length < 1e-6 {
            continue;
        }
        let dir = axis / length;
        let u = dir.any_orthonormal_vector();
        let v = dir.cross(u);
        let radius = options.radius * length;
        let grandparent = skeleton.parents()[p];
        let grandchild = first_child[c];
        let base = positions.len() as u32;
        for ring in 0..rings {
            let t = ring as f32 / (rings - 1) as f32;
            let centre = start + axis * t;
            // Small floors keep every existing neighbour in every vertex's blend, so most
            // vertices have four real influences.
            let w_gp = grandparent.map_or(0.0, |_| 0.04 + 0.5 * (1.0 - t / 0.35).max(0.0));
            let w_c = 0.04 + 0.8 * ((t - 0.6) / 0.4).max(0.0);
            let w_cc = grandchild.map_or(0.0, |_| 0.02 + 0.3 * ((t - 0.8) / 0.2).max(0.0));
            for side in 0..sides {
                let angle = side as f32 / sides as f32 * TAU;
                let radial = u * angle.cos() + v * angle.sin();
                positions.push(centre + radial * radius);
                normals.push(radial);
                joints.extend([
                    p as u16,
                    grandparent.unwrap_or(p) as u16,
                    c as u16,
                    grandchild.unwrap_or(c) as u16,
                ]);
                weights.extend([1.0, w_gp, w_c, w_cc]);
            }
        }
        for ring in 0..rings as u32 - 1 {
            for side in 0..sides as u32 {
                let next = (side + 1) % sides as u32;
                let at = |r: u32, s: u32| base + r * sides as u32 + s;
                // (u, v, dir) is right-handed (v = dir × u), so going round by increasing angle and along by
                // increasing t makes (a, b, c) counter-clockwise seen from outside.
                let (a, b) = (at(ring, side), at(ring, next));
                let (d, e) = (at(ring + 1, side), at(ring + 1, next));
                indices.extend([a, b, e, a, e, d]);
            }
        }
    }
    SkinnedMesh::new(
        positions,
        normals,
        indices,
        4,
        joints,
        weights,
        skeleton.len(),
    )
}

/// A small humanoid: pelvis, spine, chest, neck, head, arms (shoulder, elbow, wrist, hand) and
/// legs (hip, knee, ankle, toe), 1.7 m tall, facing +Z, feet on y = 0, bound at its rest pose
/// (all rotations identity). Returns the skeleton; pair it with [`tube_mesh`].
#[must_use]
pub fn figure_skeleton() -> Skeleton {
    // (name, parent, rest translation in the parent's space, metres)
    let joints: [(&str, Option<usize>, [f32; 3]); 21] = [
        ("pelvis", None, [0.0, 0.95, 0.0]),
        ("spine", Some(0), [0.0, 0.15, 0.0]),
        ("chest", Some(1), [0.0, 0.2, 0.0]),
        ("neck", Some(2), [0.0, 0.2, 0.0]),
        ("head", Some(3), [0.0, 0.1, 0.02]),
        ("head_end", Some(4), [0.0, 0.18, 0.0]),
        ("l_shoulder", Some(2), [0.18, 0.15, 0.0]),
        ("l_elbow", Some(6), [0.28, 0.0, 0.0]),
        ("l_wrist", Some(7), [0.25, 0.0, 0.0]),
        ("l_hand", Some(8), [0.08, 0.0, 0.0]),
        ("r_shoulder", Some(2), [-0.18, 0.15, 0.0]),
        ("r_elbow", Some(10), [-0.28, 0.0, 0.0]),
        ("r_wrist", Some(11), [-0.25, 0.0, 0.0]),
        ("r_hand", Some(12), [-0.08, 0.0, 0.0]),
        ("l_hip", Some(0), [0.1, -0.05, 0.0]),
        ("l_knee", Some(14), [0.0, -0.42, 0.0]),
        ("l_ankle", Some(15), [0.0, -0.42, 0.0]),
        ("l_toe", Some(16), [0.0, -0.06, 0.14]),
        ("r_hip", Some(0), [-0.1, -0.05, 0.0]),
        ("r_knee", Some(18), [0.0, -0.42, 0.0]),
        ("r_ankle", Some(19), [0.0, -0.42, 0.0]),
    ];
    let names: Vec<String> = joints.iter().map(|j| j.0.to_string()).collect();
    let parents: Vec<Option<usize>> = joints.iter().map(|j| j.1).collect();
    let rest: Vec<Transform> = joints
        .iter()
        .map(|j| Transform::from_translation(Vec3::from(j.2)))
        .collect();
    let mut world = vec![Mat4::IDENTITY; rest.len()];
    for (j, local) in rest.iter().enumerate() {
        world[j] = match parents[j] {
            Some(p) => world[p] * local.to_mat4(),
            None => local.to_mat4(),
        };
    }
    let inverse_bind = world.iter().map(Mat4::inverse).collect();
    // The table above is parent-before-child with unique names: construction cannot fail.
    #[allow(clippy::expect_used)]
    Skeleton::new(names, parents, rest, inverse_bind).expect("figure skeleton is valid")
}

/// A walking-like pose of [`figure_skeleton`] at `phase` (radians; one stride per 2π): arms
/// and legs swing in opposition, elbows and knees bend.
#[must_use]
pub fn figure_pose(skeleton: &Skeleton, phase: f32) -> Vec<Transform> {
    let swing = phase.sin();
    let mut locals = skeleton.rest().to_vec();
    let mut rotate = |name: &str, rotation: Quat| {
        if let Some(local) = skeleton.find(name).and_then(|j| locals.get_mut(j)) {
            local.rotation = rotation * local.rotation;
        }
    };
    rotate(
        "l_shoulder",
        Quat::from_rotation_z(-1.2) * Quat::from_rotation_y(0.5 * swing),
    );
    rotate(
        "r_shoulder",
        Quat::from_rotation_z(1.2) * Quat::from_rotation_y(0.5 * swing),
    );
    rotate("l_elbow", Quat::from_rotation_y(-0.4 - 0.3 * swing));
    rotate("r_elbow", Quat::from_rotation_y(0.4 - 0.3 * swing));
    rotate("l_hip", Quat::from_rotation_x(-0.5 * swing));
    rotate("r_hip", Quat::from_rotation_x(0.5 * swing));
    rotate("l_knee", Quat::from_rotation_x(0.3 + 0.3 * swing.max(0.0)));
    rotate(
        "r_knee",
        Quat::from_rotation_x(0.3 + 0.3 * (-swing).max(0.0)),
    );
    rotate("spine", Quat::from_rotation_y(0.15 * swing));
    rotate("neck", Quat::from_rotation_x(0.1));
    locals
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tube_winding_agrees_with_normals() {
        let s = figure_skeleton();
        let mesh = tube_mesh(&s, &TubeOptions::default()).unwrap();
        assert_eq!(
            mesh.vertex_count(),
            20 * TubeOptions::default().vertices_per_bone()
        );
        let p = mesh.positions();
        for tri in mesh.indices().chunks_exact(3) {
            let [a, b, c] = [tri[0] as usize, tri[1] as usize, tri[2] as usize];
            let face = (p[b] - p[a]).cross(p[c] - p[a]);
            assert!(
                face.dot(mesh.normals()[a]) > 0.0,
                "triangle {tri:?} faces inwards"
            );
        }
    }

    #[test]
    fn figure_stands_on_the_ground() {
        let s = figure_skeleton();
        let mesh = tube_mesh(&s, &TubeOptions::default()).unwrap();
        let (lo, hi) = mesh.bounds();
        assert!(lo.y > -0.1 && lo.y < 0.1, "feet at {lo}");
        assert!(hi.y > 1.6 && hi.y < 1.9, "head at {hi}");
    }
}
