//! The built-in avatar's skinned mesh: one closed, rounded, tapered tube per body segment
//! (overlapping at the joints), with skin weights that blend smoothly along each limb.

use super::skeleton::{JOINTS, joint};
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
    pub positions: Vec<Vec3>,
    /// Area-weighted vertex normals, outward.
    pub normals: Vec<Vec3>,
    /// Counter-clockwise triangles seen from outside.
    pub indices: Vec<u16>,
    pub joints: Vec<[u16; INFLUENCES]>,
    /// Non-negative, summing to one; unused slots are zero and name joint 0.
    pub weights: Vec<[f32; INFLUENCES]>,
}

/// A closed tube around the axis `start → end` whose cross-section is an ellipse with radii
/// `width` (along `width_dir`) and `depth`, interpolated smoothly between `profile` keys and
/// rounded off at both ends like a superellipse of exponent `roundness` (2: an ellipsoid;
/// larger: flatter sides, tighter ends).
#[derive(Clone, Copy, Debug)]
struct Segment {
    start: [f64; 3],
    end: [f64; 3],
    width_dir: [f64; 3],
    /// `[s, width, depth]` with `s` from 0 (start) to 1 (end), increasing.
    profile: &'static [[f64; 3]],
    roundness: f64,
    rings: usize,
    sides: usize,
    /// Joints along the axis, parent first: each owns the stretch from its centre to the next
    /// one's, and weights cross-fade over `blend` metres either side of every joint centre.
    chain: &'static [usize],
    blend: f64,
    /// Joints off the axis that pull nearby vertices along (the hips on the pelvis, the
    /// shoulders on the chest): `(joint, reach, share)` takes up to `share` of a vertex's weight
    /// at the joint centre, fading to nothing `reach` metres away. Centre segments only, as
    /// [`Segment::mirrored`] keeps them as they are.
    attach: &'static [(usize, f64, f64)],
}

impl Segment {
    fn mirrored(&self) -> Self {
        let m = |p: [f64; 3]| [-p[0], p[1], p[2]];
        Self {
            start: m(self.start),
            end: m(self.end),
            width_dir: m(self.width_dir),
            chain: mirror_chain(self.chain),
            ..*self
        }
    }
}

/// The same chain on the avatar's right side.
fn mirror_chain(chain: &'static [usize]) -> &'static [usize] {
    use joint::*;
    const ARM: &[usize] = &[VT1, R_STERNOCLAVICULAR, R_SHOULDER, R_ELBOW, R_WRIST];
    const LEG: &[usize] = &[SACROILIAC, R_HIP, R_KNEE, R_ANKLE];
    const FOOT: &[usize] = &[R_ANKLE, R_MIDTARSAL];
    match chain {
        LEFT_ARM => ARM,
        LEFT_LEG => LEG,
        LEFT_FOOT => FOOT,
        other => other,
    }
}

const LEFT_ARM: &[usize] = &[
    joint::VT1,
    joint::L_STERNOCLAVICULAR,
    joint::L_SHOULDER,
    joint::L_ELBOW,
    joint::L_WRIST,
];
const LEFT_LEG: &[usize] = &[
    joint::SACROILIAC,
    joint::L_HIP,
    joint::L_KNEE,
    joint::L_ANKLE,
];
const LEFT_FOOT: &[usize] = &[joint::L_ANKLE, joint::L_MIDTARSAL];
const SPINE: &[usize] = &[joint::SACROILIAC, joint::VL5, joint::VT10, joint::VT1];
const NECK: &[usize] = &[joint::VT1, joint::VC4, joint::SKULLBASE];

const X: [f64; 3] = [1.0, 0.0, 0.0];
const Z: [f64; 3] = [0.0, 0.0, 1.0];

/// Torso, neck, head and nose, then the left limbs (mirrored for the right).
const CENTRE: [Segment; 4] = [
    Segment {
        start: [0.0, 0.82, -0.01],
        end: [0.0, 1.50, -0.02],
        width_dir: X,
        profile: &[
            [0.00, 0.150, 0.100],
            [0.13, 0.165, 0.115],
            [0.33, 0.135, 0.095],
            [0.52, 0.145, 0.100],
            [0.73, 0.170, 0.110],
            [0.88, 0.180, 0.100],
            [1.00, 0.100, 0.070],
        ],
        roundness: 3.0,
        rings: 24,
        sides: 24,
        chain: SPINE,
        blend: 0.06,
        attach: &[
            (joint::L_HIP, 0.22, 0.7),
            (joint::R_HIP, 0.22, 0.7),
            (joint::L_SHOULDER, 0.15, 0.5),
            (joint::R_SHOULDER, 0.15, 0.5),
        ],
    },
    Segment {
        start: [0.0, 1.40, -0.02],
        end: [0.0, 1.63, 0.0],
        width_dir: X,
        profile: &[[0.0, 0.060, 0.060], [1.0, 0.050, 0.055]],
        roundness: 4.0,
        rings: 10,
        sides: 14,
        chain: NECK,
        blend: 0.04,
        attach: &[],
    },
    Segment {
        start: [0.0, 1.535, 0.015],
        end: [0.0, 1.75, 0.01],
        width_dir: X,
        profile: &[
            [0.0, 0.070, 0.085],
            [0.4, 0.085, 0.105],
            [1.0, 0.080, 0.095],
        ],
        roundness: 2.0,
        rings: 16,
        sides: 20,
        chain: NECK,
        blend: 0.04,
        attach: &[],
    },
    Segment {
        start: [0.0, 1.655, 0.085],
        end: [0.0, 1.655, 0.135],
        width_dir: X,
        profile: &[[0.0, 0.016, 0.022], [1.0, 0.012, 0.016]],
        roundness: 2.0,
        rings: 6,
        sides: 8,
        chain: &[joint::SKULLBASE],
        blend: 0.04,
        attach: &[],
    },
];

const LEFT: [Segment; 7] = [
    // Clavicle and shoulder cap.
    Segment {
        start: [0.02, 1.43, 0.0],
        end: [0.25, 1.42, 0.0],
        width_dir: Z,
        profile: &[[0.0, 0.060, 0.050], [1.0, 0.060, 0.058]],
        roundness: 3.0,
        rings: 10,
        sides: 12,
        chain: LEFT_ARM,
        blend: 0.04,
        attach: &[],
    },
    // Upper arm.
    Segment {
        start: [0.14, 1.42, 0.0],
        end: [0.50, 1.42, 0.0],
        width_dir: Z,
        profile: &[
            [0.0, 0.058, 0.055],
            [0.5, 0.052, 0.050],
            [1.0, 0.044, 0.042],
        ],
        roundness: 4.0,
        rings: 16,
        sides: 14,
        chain: LEFT_ARM,
        blend: 0.05,
        attach: &[],
    },
    // Forearm.
    Segment {
        start: [0.42, 1.42, 0.0],
        end: [0.75, 1.42, 0.0],
        width_dir: Z,
        profile: &[
            [0.0, 0.044, 0.042],
            [0.3, 0.045, 0.040],
            [1.0, 0.033, 0.026],
        ],
        roundness: 4.0,
        rings: 16,
        sides: 14,
        chain: LEFT_ARM,
        blend: 0.05,
        attach: &[],
    },
    // Hand, palm down.
    Segment {
        start: [0.70, 1.42, 0.0],
        end: [0.92, 1.42, 0.0],
        width_dir: Z,
        profile: &[
            [0.0, 0.035, 0.022],
            [0.4, 0.048, 0.020],
            [1.0, 0.040, 0.014],
        ],
        roundness: 3.0,
        rings: 10,
        sides: 12,
        chain: LEFT_ARM,
        blend: 0.03,
        attach: &[],
    },
    // Thigh.
    Segment {
        start: [0.09, 0.99, 0.0],
        end: [0.09, 0.46, 0.005],
        width_dir: X,
        profile: &[
            [0.0, 0.090, 0.095],
            [0.4, 0.080, 0.085],
            [1.0, 0.058, 0.062],
        ],
        roundness: 4.0,
        rings: 16,
        sides: 14,
        chain: LEFT_LEG,
        blend: 0.06,
        attach: &[],
    },
    // Shin.
    Segment {
        start: [0.09, 0.54, 0.005],
        end: [0.09, 0.05, 0.0],
        width_dir: X,
        profile: &[
            [0.0, 0.058, 0.062],
            [0.3, 0.055, 0.060],
            [1.0, 0.036, 0.040],
        ],
        roundness: 4.0,
        rings: 16,
        sides: 14,
        chain: LEFT_LEG,
        blend: 0.05,
        attach: &[],
    },
    // Foot: its widest, lowest ring sits on y = 0.
    Segment {
        start: [0.09, 0.045, -0.06],
        end: [0.09, 0.045, 0.22],
        width_dir: X,
        profile: &[
            [0.0, 0.040, 0.045],
            [0.5, 0.048, 0.045],
            [1.0, 0.045, 0.028],
        ],
        roundness: 3.0,
        rings: 12,
        sides: 14,
        chain: LEFT_FOOT,
        blend: 0.04,
        attach: &[],
    },
];

fn segments() -> Vec<Segment> {
    let mut all = CENTRE.to_vec();
    all.extend(LEFT);
    all.extend(LEFT.iter().map(Segment::mirrored));
    all
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
