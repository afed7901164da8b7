//! Smallest-three quaternion quantisation for the wire.
//!
//! Bit budget, 48 bits (6 bytes) per rotation:
//! - 2 bits: index of the component with the largest magnitude, which is dropped;
//! - 3 × 15 bits: the other three components, each in `[−1/√2, 1/√2]` (no smaller component can
//!   exceed that once the largest is dropped), uniformly quantised;
//! - 1 bit: unused, zero.
//!
//! `q` and `−q` are the same rotation, so the quaternion is first negated to make the dropped
//! component positive; the decoder restores it as `√(1 − a² − b² − c²)`. Step per component
//! `Δ = √2 / (2¹⁵ − 2) ≈ 4.3e-5`; the measured worst-case angular error over 10⁶ random
//! rotations is in the test `worst_case_error_over_a_million` (`docs/src/reference/figures.md` gives the figure), bounded
//! by [`MAX_ERROR_DEGREES`].

use glam::Quat;

/// Bits per encoded rotation (the 48th is spare).
pub const BITS: u32 = 48;
/// Bytes per encoded rotation.
pub const BYTES: usize = 6;
/// Bits per stored component.
const COMPONENT_BITS: u32 = 15;
// An even number of steps, so zero (the identity's small components) is exactly representable.
const LEVELS: f32 = ((1u32 << COMPONENT_BITS) - 2) as f32;
const RANGE: f32 = std::f32::consts::FRAC_1_SQRT_2;

/// Guaranteed bound on the angle between a rotation and its decoded encoding, in degrees.
pub const MAX_ERROR_DEGREES: f64 = 0.01;

/// Encodes a rotation into 48 bits (low bits of the `u64`).
///
/// Input need not be normalised; `q` and `−q` encode identically. A zero-length or non-finite
/// quaternion encodes the identity rather than garbage.
#[must_use]
pub fn encode(q: Quat) -> u64 {
    let len = q.length();
    let q = if len.is_finite() && len > 1e-12 {
        q * len.recip()
    } else {
        Quat::IDENTITY
    };
    let c = q.to_array();
    // The first component of the largest magnitude, found with selects rather than branches
    // (which component wins varies from joint to joint: branches on it mispredict).
    let mut largest = 0;
    let mut top = c[0].abs();
    for (i, &v) in c.iter().enumerate().skip(1) {
        let bigger = v.abs() > top;
        largest = if bigger { i } else { largest };
        top = if bigger { v.abs() } else { top };
    }
    // −1 when the largest is negative, else 1, from its comparison's bit (no branch either).
    let sign = f32::from_bits(1f32.to_bits() | u32::from(c[largest] < 0.0) << 31);
    let mut bits = largest as u64;
    for i in KEPT[largest] {
        let unit = ((c[i] * sign + RANGE) * (0.5 / RANGE)).clamp(0.0, 1.0);
        // Round to nearest (`unit · LEVELS` is not negative: adding ½ and truncating rounds
        // without a call to the C library's `roundf`). Below 2¹⁵, so converting to `u32`
        // truncates as to `u64` would, without the branches of a conversion to 64 bits.
        let level = (unit * LEVELS + 0.5) as u32;
        bits = (bits << COMPONENT_BITS) | u64::from(level);
    }
    bits
}

/// The components kept, in order, when component `i` is dropped.
const KEPT: [[usize; 3]; 4] = [[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]];

/// Decodes 48 bits from [`encode`] into a unit quaternion with a non-negative largest component.
/// Any 48-bit value decodes to a valid unit quaternion (the spare bits are ignored).
#[must_use]
pub fn decode(bits: u64) -> Quat {
    let mask = (1u64 << COMPONENT_BITS) - 1;
    let largest = ((bits >> (3 * COMPONENT_BITS)) & 3) as usize;
    let mut small = [0.0f32; 3];
    for (k, s) in small.iter_mut().enumerate() {
        let shift = COMPONENT_BITS * (2 - k as u32);
        let level = ((bits >> shift) & mask) as f32;
        *s = level / LEVELS * 2.0 * RANGE - RANGE;
    }
    let sum: f32 = small.iter().map(|v| v * v).sum();
    let mut c = [0.0f32; 4];
    let mut k = 0;
    for (i, slot) in c.iter_mut().enumerate() {
        if i == largest {
            *slot = (1.0 - sum).max(0.0).sqrt();
        } else {
            *slot = small[k];
            k += 1;
        }
    }
    Quat::from_array(c).normalize()
}

/// Writes the 6 bytes of [`encode`] little-endian.
pub fn write(q: Quat, out: &mut Vec<u8>) {
    out.extend_from_slice(&encode(q).to_le_bytes()[..BYTES]);
}

/// Reads 6 little-endian bytes written by [`write()`].
#[must_use]
pub fn read(bytes: [u8; BYTES]) -> Quat {
    let mut b = [0u8; 8];
    b[..BYTES].copy_from_slice(&bytes);
    decode(u64::from_le_bytes(b))
}

/// The angle, in degrees, between two rotations (treating `q ≡ −q`), computed in f64.
#[must_use]
pub fn angle_between_degrees(a: Quat, b: Quat) -> f64 {
    let a = a.normalize().to_array().map(f64::from);
    let b = b.normalize().to_array().map(f64::from);
    let sign = if a.iter().zip(&b).map(|(x, y)| x * y).sum::<f64>() < 0.0 {
        -1.0
    } else {
        1.0
    };
    // For unit quaternions |a − b| = 2 sin(φ/2) and |a + b| = 2 cos(φ/2), where φ is the 4-D
    // angle and 2φ the rotation angle; atan2 of the two is well conditioned near zero.
    let diff2: f64 = a.iter().zip(&b).map(|(x, y)| (x - sign * y).powi(2)).sum();
    let sum2: f64 = a.iter().zip(&b).map(|(x, y)| (x + sign * y).powi(2)).sum();
    (4.0 * diff2.sqrt().atan2(sum2.sqrt())).to_degrees()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::f32s;
    use proptest::prelude::*;

    /// Deterministic uniform random rotations (Shoemake's method) from a small PCG.
    fn random_rotations(count: usize, mut state: u64) -> impl Iterator<Item = Quat> {
        let mut next = move || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((state >> 11) as f64) / ((1u64 << 53) as f64)
        };
        (0..count).map(move |_| {
            let (u1, u2, u3) = (next(), next(), next());
            let tau = std::f64::consts::TAU;
            let (a, b) = ((1.0 - u1).sqrt(), u1.sqrt());
            Quat::from_xyzw(
                (a * (tau * u2).sin()) as f32,
                (a * (tau * u2).cos()) as f32,
                (b * (tau * u3).sin()) as f32,
                (b * (tau * u3).cos()) as f32,
            )
        })
    }

    #[test]
    fn worst_case_error_over_a_million() {
        let mut worst = 0.0f64;
        for q in random_rotations(1_000_000, 0x5eed) {
            worst = worst.max(angle_between_degrees(q, decode(encode(q))));
        }
        println!(
            "smallest-three, {BITS} bits: worst angular error over 1e6 rotations = {worst:.6}°"
        );
        assert!(
            worst <= MAX_ERROR_DEGREES,
            "worst error {worst}° exceeds {MAX_ERROR_DEGREES}°"
        );
        assert!(worst > 0.0);
    }

    /// The encoding written the plain way (a loop over the components, branches on which is
    /// largest and its sign, the level converted to 64 bits): [`encode`] must give exactly these bits (v1 and v2 frames carry
    /// them; decoders and the test vectors depend on them).
    fn reference_encode(q: Quat) -> u64 {
        let len = q.length();
        let q = if len.is_finite() && len > 1e-12 {
            q * len.recip()
        } else {
            Quat::IDENTITY
        };
        let c = q.to_array();
        let mut largest = 0;
        for i in 1..4 {
            if c[i].abs() > c[largest].abs() {
                largest = i;
            }
        }
        let sign = if c[largest] < 0.0 { -1.0 } else { 1.0 };
        let mut bits = largest as u64;
        for (i, &v) in c.iter().enumerate() {
            if i != largest {
                let unit = ((v * sign + RANGE) * (0.5 / RANGE)).clamp(0.0, 1.0);
                bits = (bits << COMPONENT_BITS) | (unit * LEVELS + 0.5) as u64;
            }
        }
        bits
    }

    #[test]
    fn bits_are_the_reference_bits() {
        for (k, q) in random_rotations(300_000, 0xb175).enumerate() {
            // Negated, scaled, and with components zeroed or tied in magnitude.
            let tied = Quat::from_array(q.to_array().map(|v| (v * 4.0).round() / 4.0));
            for q in [q, -q, q * (1.0 + k as f32 * 1e-5), tied] {
                assert_eq!(encode(q), reference_encode(q), "{q:?}");
            }
        }
        for q in [
            Quat::IDENTITY,
            -Quat::IDENTITY,
            Quat::from_xyzw(0.0, 0.0, 0.0, 0.0),
            Quat::from_xyzw(0.5, -0.5, 0.5, -0.5),
            Quat::from_xyzw(-0.5, 0.5, -0.5, 0.5),
            Quat::from_xyzw(f32::INFINITY, 0.0, 0.0, 1.0),
        ] {
            assert_eq!(encode(q), reference_encode(q), "{q:?}");
        }
    }

    #[test]
    fn angle_measure_is_right() {
        let a = Quat::from_rotation_y(0.0);
        let b = Quat::from_rotation_y(1f32.to_radians());
        assert!((angle_between_degrees(a, b) - 1.0).abs() < 1e-4);
        assert!((angle_between_degrees(a, -b) - 1.0).abs() < 1e-4);
    }

    #[test]
    fn edge_cases() {
        assert_eq!(decode(encode(Quat::IDENTITY)), Quat::IDENTITY);
        assert_eq!(encode(-Quat::IDENTITY), encode(Quat::IDENTITY));
        assert_eq!(
            decode(encode(Quat::from_xyzw(0.0, 0.0, 0.0, 0.0))),
            Quat::IDENTITY
        );
        assert_eq!(
            decode(encode(Quat::from_xyzw(f32::NAN, 0.0, 0.0, 1.0))),
            Quat::IDENTITY
        );
        // Two equal largest components (a 90° turn) and an all-equal quaternion.
        for q in [
            Quat::from_xyzw(0.0, 0.5f32.sqrt(), 0.0, 0.5f32.sqrt()),
            Quat::from_xyzw(0.5, -0.5, 0.5, -0.5),
        ] {
            assert!(angle_between_degrees(q, decode(encode(q))) < MAX_ERROR_DEGREES);
        }
        // Every bit pattern decodes to a unit quaternion.
        for bits in [0u64, u64::MAX, 0xFFFF_FFFF_FFFF, 0x1234_5678_9ABC] {
            assert!((decode(bits).length() - 1.0).abs() < 1e-5);
        }
        assert!(encode(Quat::IDENTITY) < 1 << BITS);
    }

    proptest! {
        #[test]
        fn bound_holds_for_unnormalised_and_negated(
            v in prop::array::uniform4(f32s(-10.0..10.0)), negate: bool,
        ) {
            let q = Quat::from_array(v);
            prop_assume!(q.length() > 1e-3);
            let q = if negate { -q } else { q };
            let mut bytes = Vec::new();
            write(q, &mut bytes);
            prop_assert_eq!(bytes.len(), BYTES);
            let back = read(bytes.try_into().unwrap());
            prop_assert!(angle_between_degrees(q, back) <= MAX_ERROR_DEGREES);
        }
    }
}
