//! The built-in avatar's skinned mesh: the `body` segments tessellated as closed tubes
//! (overlapping at the joints), with skin weights that blend smoothly along each limb.

use super::body::{Segment, segments};
use super::skeleton::JOINTS;
use glam::{DVec3, Vec3};
use posecast_proto::skinning::compute_normals;

/// Influences per vertex in the written mesh (`JOINTS_0` / `WEIGHTS_0`).
pub const INFLUENCES: usize = 4;

/// Weights below this are dropped before renormalising, so a vertex only names joints that
/// visibly move it.
const MIN_WEIGHT: f64 = 1e-3;

/// The mesh in bind pose (model space, metres).
#[derive(Clone, Debug, PartialEq)]
pub struct MeshData {
    /// Vertex positions, model space, metres.
    pub positions: Vec<Vec3>,
    /// Area-weighted vertex normals, outward.
    pub normals: Vec<Vec3>,
    /// Counter-clockwise triangles seen from outside.
    pub indices: Vec<u16>,
    /// Per vertex, the indices into [`JOINTS`] of the joints that move it.
    pub joints: Vec<[u16; INFLUENCES]>,
    /// Non-negative, summing to one; unused slots are zero and name joint 0.
    pub weights: Vec<[f32; INFLUENCES]>,
}

/// Builds the whole mesh. Bind-pose joint centres come from [`JOINTS`].
#[must_use]
pub fn build() -> MeshData {
    let mut mesh = MeshData {
        positions: Vec::new(),
        normals: Vec::new(),
        indices: Vec::new(),
        joints: Vec::new(),
        weights: Vec::new(),
    };
    for segment in segments() {
        tessellate(&segment, &mut mesh);
    }
    let indices: Vec<u32> = mesh.indices.iter().map(|&i| u32::from(i)).collect();
    mesh.normals = compute_normals(&mesh.positions, &indices);
    mesh
}

fn smoothstep(edge0: f64, edge1: f64, x: f64) -> f64 {
    let t = ((x - edge0) / (edge1 - edge0)).clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

/// `[width, depth]` at `s`, smooth between the profile keys.
fn radii(profile: &[[f64; 3]], s: f64) -> [f64; 2] {
    let mut previous = profile[0];
    for &key in profile {
        if s <= key[0] {
            let t = if key[0] > previous[0] {
                smoothstep(previous[0], key[0], s)
            } else {
                1.0
            };
            return [
                previous[1] + (key[1] - previous[1]) * t,
                previous[2] + (key[2] - previous[2]) * t,
            ];
        }
        previous = key;
    }
    [previous[1], previous[2]]
}

/// Appends one segment: a pole, `rings − 1` rings of `sides` vertices, a pole. Rings are
/// spaced by `(1 − cos)/2` so the rounded ends get more of them.
fn tessellate(seg: &Segment, mesh: &mut MeshData) {
    let start = DVec3::from(seg.start);
    let axis = DVec3::from(seg.end) - start;
    let length = axis.length();
    let d = axis / length;
    let w = DVec3::from(seg.width_dir);
    let a = (w - w.dot(d) * d).normalize();
    let b = d.cross(a);
    let base = mesh.positions.len();
    let push = |p: DVec3, mesh: &mut MeshData| {
        let (joints, weights) = skin_weights(seg, p);
        mesh.positions.push(p.as_vec3());
        mesh.joints.push(joints);
        mesh.weights.push(weights);
    };
    push(start, mesh);
    for i in 1..seg.rings {
        let s = (1.0 - (std::f64::consts::PI * i as f64 / seg.rings as f64).cos()) / 2.0;
        let x = (2.0 * s - 1.0).abs();
        let round = (1.0 - x.powf(seg.roundness))
            .max(0.0)
            .powf(1.0 / seg.roundness);
        let [rw, rd] = radii(seg.profile, s);
        let centre = start + axis * s;
        for k in 0..seg.sides {
            let theta = std::f64::consts::TAU * k as f64 / seg.sides as f64;
            let offset = a * (rw * theta.cos()) + b * (rd * theta.sin());
            push(centre + offset * round, mesh);
        }
    }
    push(start + axis, mesh);

    let ring = |i: usize, k: usize| base + 1 + (i - 1) * seg.sides + k % seg.sides;
    let last_pole = base + 1 + (seg.rings - 1) * seg.sides;
    let mut tri = |p: usize, q: usize, r: usize| {
        for v in [p, q, r] {
            // Every vertex index fits: the whole mesh stays well under 65,536 vertices, which
            // `avatar_mesh_fits_u16_indices` checks.
            mesh.indices.push(v as u16);
        }
    };
    for k in 0..seg.sides {
        tri(base, ring(1, k + 1), ring(1, k));
        for i in 1..seg.rings - 1 {
            tri(ring(i, k), ring(i, k + 1), ring(i + 1, k + 1));
            tri(ring(i, k), ring(i + 1, k + 1), ring(i + 1, k));
        }
        tri(
            last_pole,
            ring(seg.rings - 1, k),
            ring(seg.rings - 1, k + 1),
        );
    }
}

/// Weights of the vertex at `p`, `u` metres along the segment's axis: joint `k` of the chain
/// gets `σ_k(u) − σ_{k+1}(u)`, where `σ_k` rises smoothly from 0 to 1 across joint `k`'s centre
/// (`σ_0 = 1`, `σ_n = 0`). The sum telescopes to one, and every segment that shares a chain
/// and an axis line blends the same way, so overlapping tubes move together. Attached joints
/// then take their share `a_i` and the chain keeps `1 − Σ a_i`. The heaviest
/// [`INFLUENCES`] are kept and renormalised.
fn skin_weights(seg: &Segment, p: DVec3) -> ([u16; INFLUENCES], [f32; INFLUENCES]) {
    let start = DVec3::from(seg.start);
    let d = (DVec3::from(seg.end) - start).normalize();
    let u = (p - start).dot(d);
    let rise = |k: usize| -> f64 {
        if k == 0 {
            1.0
        } else if k >= seg.chain.len() {
            0.0
        } else {
            let centre = (DVec3::from(JOINTS[seg.chain[k]].head) - start).dot(d);
            smoothstep(centre - seg.blend, centre + seg.blend, u)
        }
    };
    let mut pairs: Vec<(usize, f64)> = seg
        .chain
        .iter()
        .enumerate()
        .map(|(k, &j)| (j, rise(k) - rise(k + 1)))
        .collect();
    let attached: Vec<(usize, f64)> = seg
        .attach
        .iter()
        .map(|&(j, reach, share)| {
            let distance = p.distance(DVec3::from(JOINTS[j].head));
            (j, share * (1.0 - smoothstep(0.0, reach, distance)))
        })
        .collect();
    let taken: f64 = attached.iter().map(|a| a.1).sum::<f64>().min(1.0);
    pairs.iter_mut().for_each(|pair| pair.1 *= 1.0 - taken);
    pairs.extend(attached);
    pairs.retain(|&(_, w)| w >= MIN_WEIGHT);
    pairs.sort_by(|p, q| q.1.total_cmp(&p.1).then(p.0.cmp(&q.0)));
    pairs.truncate(INFLUENCES);
    let sum: f64 = pairs.iter().map(|p| p.1).sum();
    let mut joints = [0u16; INFLUENCES];
    let mut weights = [0f32; INFLUENCES];
    for (slot, (j, w)) in pairs.into_iter().enumerate() {
        joints[slot] = j as u16;
        weights[slot] = (w / sum) as f32;
    }
    (joints, weights)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::builtin::body::LEFT;
    use crate::builtin::skeleton::joint;

    #[test]
    fn avatar_mesh_fits_u16_indices() {
        let vertices: usize = segments().iter().map(|s| (s.rings - 1) * s.sides + 2).sum();
        assert!(vertices < usize::from(u16::MAX));
        assert_eq!(build().positions.len(), vertices);
    }

    /// Outward winding: every closed tube encloses a positive volume (divergence theorem).
    #[test]
    fn every_segment_is_closed_and_outward() {
        for seg in segments() {
            let mut mesh = MeshData {
                positions: Vec::new(),
                normals: Vec::new(),
                indices: Vec::new(),
                joints: Vec::new(),
                weights: Vec::new(),
            };
            tessellate(&seg, &mut mesh);
            let volume: f32 = mesh
                .indices
                .chunks_exact(3)
                .map(|t| {
                    let [a, b, c] = [t[0], t[1], t[2]].map(|i| mesh.positions[usize::from(i)]);
                    a.dot(b.cross(c)) / 6.0
                })
                .sum();
            let [w, d] = radii(seg.profile, 0.5);
            let length = (DVec3::from(seg.end) - DVec3::from(seg.start)).length();
            // Between a third of and the full bounding cylinder of the middle cross-section.
            let cylinder = (std::f64::consts::PI * w * d * length) as f32;
            assert!(
                volume > 0.2 * cylinder && volume < 1.5 * cylinder,
                "{volume} vs {cylinder}"
            );
            // Every edge is shared by exactly two triangles, once in each direction.
            let mut edges: Vec<(u16, u16)> = mesh
                .indices
                .chunks_exact(3)
                .flat_map(|t| [(t[0], t[1]), (t[1], t[2]), (t[2], t[0])])
                .collect();
            edges.sort_unstable();
            for pair in edges.windows(2) {
                assert_ne!(pair[0], pair[1], "edge used twice in one direction");
            }
            for &(p, q) in &edges {
                assert!(edges.binary_search(&(q, p)).is_ok(), "open edge {p}-{q}");
            }
        }
    }

    #[test]
    fn weights_cross_fade_at_the_knee() {
        let thigh = LEFT[4];
        let knee = (DVec3::from(JOINTS[joint::L_KNEE].head) - DVec3::from(thigh.start))
            .dot((DVec3::from(thigh.end) - DVec3::from(thigh.start)).normalize());
        let on_axis = |u: f64| {
            let start = DVec3::from(thigh.start);
            start + (DVec3::from(thigh.end) - start).normalize() * u
        };
        let (j, w) = skin_weights(&thigh, on_axis(knee));
        let mut at_knee: Vec<(u16, f32)> = j.into_iter().zip(w).filter(|p| p.1 > 0.0).collect();
        at_knee.sort_by_key(|p| p.0);
        assert_eq!(at_knee.len(), 2);
        assert_eq!(at_knee[0].0 as usize, joint::L_HIP);
        assert_eq!(at_knee[1].0 as usize, joint::L_KNEE);
        assert!((at_knee[0].1 - 0.5).abs() < 1e-6);
        let (j, w) = skin_weights(&thigh, on_axis(knee - 0.2));
        assert_eq!((j[0] as usize, w[0]), (joint::L_HIP, 1.0));
    }
}
