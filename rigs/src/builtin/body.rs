//! The built-in avatar's body as data: one rounded, tapered tube per body segment, with the
//! joints that skin it. [`super::mesh`] tessellates and weights them.

use super::skeleton::joint;

/// A closed tube around the axis `start → end` whose cross-section is an ellipse with radii
/// `width` (along `width_dir`) and `depth`, interpolated smoothly between `profile` keys and
/// rounded off at both ends like a superellipse of exponent `roundness` (2: an ellipsoid;
/// larger: flatter sides, tighter ends).
#[derive(Clone, Copy, Debug)]
pub(super) struct Segment {
    pub(super) start: [f64; 3],
    pub(super) end: [f64; 3],
    pub(super) width_dir: [f64; 3],
    /// `[s, width, depth]` with `s` from 0 (start) to 1 (end), increasing.
    pub(super) profile: &'static [[f64; 3]],
    pub(super) roundness: f64,
    pub(super) rings: usize,
    pub(super) sides: usize,
    /// Joints along the axis, parent first: each owns the stretch from its centre to the next
    /// one's, and weights cross-fade over `blend` metres either side of every joint centre.
    pub(super) chain: &'static [usize],
    pub(super) blend: f64,
    /// Joints off the axis that pull nearby vertices along (the hips on the pelvis, the
    /// shoulders on the chest): `(joint, reach, share)` takes up to `share` of a vertex's weight
    /// at the joint centre, fading to nothing `reach` metres away. Centre segments only, as
    /// [`Segment::mirrored`] keeps them as they are.
    pub(super) attach: &'static [(usize, f64, f64)],
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

pub(super) const LEFT: [Segment; 7] = [
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

/// Every segment of the body, right side included.
pub(super) fn segments() -> Vec<Segment> {
    let mut all = CENTRE.to_vec();
    all.extend(LEFT);
    all.extend(LEFT.iter().map(Segment::mirrored));
    all
}
