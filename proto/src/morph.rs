//! Morph targets (blend shapes) and the CPU morphing reference: `v' = v + Σₖ wₖ·Δvₖ`, normals
//! likewise and renormalised, applied before skinning (glTF 2.0 §3.7.2.2). Seed 002's DOFs
//! extended to "any animatable parameter within the character rig": a morph weight is one.
//!
//! A rig's morph *channels* are the distinct target names over all its meshes; every mesh
//! target with that name follows the channel's weight (a face, its eyes and its teeth each have
//! `mouthOpen`, and one weight opens all three). Weights are in `[0, 1]` on every path in
//! (commands, live poses, VMC) and on the wire, quantised to [`WEIGHT_LEVELS`] steps.

use crate::skinning::SkinnedMesh;
use glam::Vec3;

/// Quantisation levels of a streamed weight: `level = round(w · 1023)`, so a decoded weight is
/// within [`MAX_WEIGHT_ERROR`] of the one sent.
pub const WEIGHT_LEVELS: u16 = 1023;
/// The largest difference between a weight and its streamed value: half a level.
pub const MAX_WEIGHT_ERROR: f32 = 0.5 / WEIGHT_LEVELS as f32;

pub use crate::skinning::MorphTarget;

/// Why a weight was refused.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum WeightError {
    /// NaN, infinite or outside `[0, 1]`.
    #[error("morph weight {name} = {value} is outside [0, 1]")]
    Range {
        /// The name it was given under.
        name: String,
        /// The value.
        value: f32,
    },
}

/// Checks one weight given under `name`.
///
/// # Errors
/// [`WeightError::Range`] for NaN, infinities and values outside `[0, 1]`.
pub fn check_weight(name: &str, value: f32) -> Result<f32, WeightError> {
    if (0.0..=1.0).contains(&value) {
        Ok(value)
    } else {
        Err(WeightError::Range {
            name: name.to_owned(),
            value,
        })
    }
}

/// A weight's wire level, `round(w · 1023)`, `w` clamped to `[0, 1]` (NaN → 0).
#[must_use]
pub fn weight_level(w: f32) -> u16 {
    if w.is_nan() {
        return 0;
    }
    // Clamped to [0, 1023] first, so the cast cannot truncate.
    #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
    let level = (w.clamp(0.0, 1.0) * f32::from(WEIGHT_LEVELS)).round() as u16;
    level
}

/// The weight a wire level stands for.
#[must_use]
pub fn weight_value(level: u16) -> f32 {
    f32::from(level.min(WEIGHT_LEVELS)) / f32::from(WEIGHT_LEVELS)
}

/// For each of `mesh`'s targets, the channel (index into `channels`) whose weight drives it,
/// by name; `None` for a target no channel names.
#[must_use]
pub fn target_channels(mesh: &SkinnedMesh, channels: &[String]) -> Vec<Option<usize>> {
    mesh.targets()
        .iter()
        .map(|t| channels.iter().position(|c| *c == t.name))
        .collect()
}

/// The morph channels of a rig with these meshes: distinct target names in first-seen order.
#[must_use]
pub fn channels<'a>(meshes: impl IntoIterator<Item = &'a SkinnedMesh>) -> Vec<String> {
    let mut out: Vec<String> = Vec::new();
    for mesh in meshes {
        for t in mesh.targets() {
            if !out.contains(&t.name) {
                out.push(t.name.clone());
            }
        }
    }
    out
}

/// Morphs `mesh`'s bind-pose vertices (the CPU reference every GPU path is tested against):
/// `p' = p + Σₖ wₖ·Δpₖ`, `n' = normalize(n + Σₖ wₖ·Δnₖ)`, with `weights[k]` the weight of
/// the mesh's target `k` (missing entries are 0).
///
/// # Panics
/// When an output buffer is not one entry per vertex (a caller bug).
pub fn morph_cpu(
    mesh: &SkinnedMesh,
    weights: &[f32],
    positions: &mut [Vec3],
    normals: &mut [Vec3],
) {
    let n = mesh.vertex_count();
    assert!(
        positions.len() == n && normals.len() == n,
        "output buffers must hold {n} vertices"
    );
    positions.copy_from_slice(mesh.positions());
    normals.copy_from_slice(mesh.normals());
    for (target, &w) in mesh.targets().iter().zip(weights) {
        if w == 0.0 {
            continue;
        }
        for (p, d) in positions.iter_mut().zip(&target.positions) {
            *p += w * *d;
        }
        for (v, d) in normals.iter_mut().zip(&target.normals) {
            *v += w * *d;
        }
    }
    if mesh.targets().iter().any(|t| !t.normals.is_empty()) {
        for v in normals.iter_mut() {
            *v = v.normalize_or_zero();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::skinning::MeshError;

    fn quad() -> SkinnedMesh {
        let p = vec![Vec3::ZERO, Vec3::X, Vec3::Y, Vec3::new(1.0, 1.0, 0.0)];
        SkinnedMesh::new(
            p,
            vec![],
            vec![0, 1, 2, 2, 1, 3],
            1,
            vec![0; 4],
            vec![1.0; 4],
            1,
        )
        .unwrap()
    }

    fn target(name: &str, d: Vec3, dn: Vec3) -> MorphTarget {
        MorphTarget {
            name: name.into(),
            positions: vec![d; 4],
            normals: vec![dn; 4],
        }
    }

    #[test]
    fn morphing_adds_weighted_displacements_and_renormalises_normals() {
        let mesh = quad()
            .with_targets(vec![
                target("up", Vec3::Z, Vec3::X),
                target("side", Vec3::new(0.5, 0.0, 0.0), Vec3::ZERO),
            ])
            .unwrap();
        let (mut p, mut n) = (vec![Vec3::ZERO; 4], vec![Vec3::ZERO; 4]);
        morph_cpu(&mesh, &[0.5, 1.0], &mut p, &mut n);
        // By hand: (1, 0, 0) + 0.5·(0, 0, 1) + 1·(0.5, 0, 0).
        assert!(p[1].abs_diff_eq(Vec3::new(1.5, 0.0, 0.5), 1e-6), "{}", p[1]);
        // The quad's normal is +Z; +0.5·X, normalised.
        let expected = Vec3::new(0.5, 0.0, 1.0).normalize();
        assert!(n[2].abs_diff_eq(expected, 1e-6), "{}", n[2]);
        morph_cpu(&mesh, &[], &mut p, &mut n);
        assert_eq!(p, mesh.positions());
    }

    #[test]
    fn targets_of_the_wrong_length_or_not_finite_are_refused() {
        let mut t = target("a", Vec3::Z, Vec3::ZERO);
        t.positions.pop();
        assert!(matches!(
            quad().with_targets(vec![t]),
            Err(MeshError::Length { actual: 3, .. })
        ));
        let mut t = target("a", Vec3::Z, Vec3::ZERO);
        t.normals[2] = Vec3::NAN;
        assert!(matches!(
            quad().with_targets(vec![t]),
            Err(MeshError::NotFinite { vertex: 2, .. })
        ));
    }

    #[test]
    fn weights_quantise_within_half_a_level_and_refuse_the_out_of_range() {
        for i in 0..=10_000 {
            let w = i as f32 / 10_000.0;
            let back = weight_value(weight_level(w));
            assert!((back - w).abs() <= MAX_WEIGHT_ERROR + 1e-7, "{w} → {back}");
        }
        assert_eq!(weight_level(f32::NAN), 0);
        assert_eq!(weight_level(7.0), WEIGHT_LEVELS);
        for bad in [f32::NAN, -0.01, 1.01, f32::INFINITY, f32::MAX] {
            assert!(check_weight("x", bad).is_err(), "{bad}");
        }
        assert_eq!(check_weight("x", 1.0), Ok(1.0));
    }

    #[test]
    fn channels_are_the_distinct_names_and_targets_find_theirs() {
        let a = quad()
            .with_targets(vec![
                target("open", Vec3::Z, Vec3::ZERO),
                target("blink", Vec3::Y, Vec3::ZERO),
            ])
            .unwrap();
        let b = quad()
            .with_targets(vec![target("blink", Vec3::X, Vec3::ZERO)])
            .unwrap();
        let ch = channels([&a, &b]);
        assert_eq!(ch, ["open", "blink"]);
        assert_eq!(target_channels(&b, &ch), [Some(1)]);
        assert_eq!(target_channels(&b, &["x".into()]), [None]);
    }
}
