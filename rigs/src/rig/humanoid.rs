//! Whether a rig is a humanoid: what gets the H-Anim neutral pose and takes humanoid clips.
//!
//! Decided from the **rest skeleton** only ([`RestShape`]), never from what a clip does with
//! it (a person bowing deeply in a clip is still a person; a fox stretching its legs in one is
//! still a fox):
//!
//! 1. **Structure** (required): the mapping covers the H-Anim core chain ([`CORE`]), and the
//!    topology is a body's — two legs and two arms branching from one spine, the arms from a
//!    chest above the root, the legs not from the chest. A head above the chest and hands at the
//!    ends of the arm chains are listed as evidence when mapped.
//! 2. **Votes** between a biped and a quadruped, each in −1…+1:
//!    - *proportions* (pose-invariant): arm (upper arm + forearm) over leg (thigh + shank).
//!      A person's is about 0.68 (Drillis & Contini: 0.332 over 0.491 of stature); a
//!      quadruped's forelimb is as long as its hind limb or longer. +1 at ≤ [`ARM_LEG_HUMAN`],
//!      −1 at ≥ [`ARM_LEG_QUADRUPED`], linear between;
//!    - *rest geometry*, only when the rest pose is readable (standing: legs straight and
//!      parallel): the spine's angle to the legs (+1 at ≥ 140°: a spine above the legs; −1 at
//!      ≤ 110°: a level spine), and the hands' height above the feet over the leg length
//!      (+1 at ≥ 0.35; −1 at ≤ 0.15: forefeet on the ground);
//!    - *names*: the file's humanoid bone map (a VRM) +1; a tail from the pelvis −1 at half
//!      weight.
//!
//! Humanoid when the weighted mean vote is positive. The confidence is
//! `0.5 + 0.5 · |mean| · (weight voted / weight possible)`: evidence that could not be read
//! (a crumpled rest pose) lowers it. A user's `humanoid` option overrides the classification.

use glam::Vec3;

use super::names::find;
use super::rest_shape::{RestShape, angle};
use crate::asset::Asset;

/// The H-Anim joints a humanoid's mapping must cover (with a spine joint above the root); the
/// H-Anim neutral pose and retargeting need them.
pub const CORE: &[&str] = &[
    "humanoid_root",
    "l_hip",
    "l_knee",
    "r_hip",
    "r_knee",
    "l_shoulder",
    "l_elbow",
    "r_shoulder",
    "r_elbow",
];

/// Arm-to-leg length ratio at and below which proportions vote for a humanoid.
pub const ARM_LEG_HUMAN: f32 = 0.85;
/// Arm-to-leg length ratio at and above which proportions vote for a quadruped.
pub const ARM_LEG_QUADRUPED: f32 = 1.0;

/// A rig's classification and why, for people.
#[derive(Clone, Debug, PartialEq)]
pub struct Classification {
    /// Whether it is a humanoid.
    pub humanoid: bool,
    /// How sure, 0.5 (a coin toss) to 1.
    pub confidence: f32,
    /// The evidence, one item each (`"arm/leg 0.68 (+1)"`).
    pub evidence: Vec<String>,
    /// The evidence in one line.
    pub reason: String,
}

/// Classifies a rig from its H-Anim mapping and its rest skeleton (see the module docs).
#[must_use]
pub fn classify(asset: &Asset, hanim: &[Option<String>]) -> Classification {
    let missing: Vec<&str> = CORE
        .iter()
        .copied()
        .filter(|n| find(hanim, n).is_none())
        .collect();
    if !missing.is_empty() {
        return not(vec![format!(
            "no H-Anim joint mapped for {}",
            missing.join(", ")
        )]);
    }
    let shape = RestShape::measure(asset, hanim);
    let parents = asset.skeleton.parents();
    let (Some(root), Some(chest)) = (shape.root, shape.chest) else {
        return not(vec!["the arms hang from no common joint".into()]);
    };
    if chest == root || !is_ancestor(parents, root, chest) {
        return not(vec![
            "the arms do not hang from a spine joint above the root".into(),
        ]);
    }
    if shape
        .legs
        .iter()
        .any(|l| is_ancestor(parents, chest, l.top))
    {
        return not(vec!["the legs hang from the chest, not the pelvis".into()]);
    }
    let mut evidence = vec!["two legs from the pelvis, two arms from a chest above it".to_owned()];
    match shape.head {
        Some(h) if is_ancestor(parents, chest, h) => {
            evidence.push("a head above the chest".into());
        }
        _ => evidence.push("no head mapped above the chest".into()),
    }
    let hands = shape
        .arms
        .iter()
        .filter(|a| a.end.is_some_and(|w| is_ancestor(parents, a.middle, w)))
        .count();
    evidence.push(format!("hands at the end of {hands} of 2 arm chains"));

    // (vote, weight, what)
    let mut votes: Vec<(f32, f32, String)> = Vec::new();
    let mut possible = 0.0;
    possible += 1.0;
    if let (Some(arm), Some(leg)) = (
        shape.arm_length(parents),
        shape.leg_length(parents).filter(|&l| l > 0.0),
    ) {
        let r = arm / leg;
        let v = ramp(r, ARM_LEG_QUADRUPED, ARM_LEG_HUMAN);
        votes.push((v, 1.0, format!("arm/leg length {r:.2}")));
    } else {
        evidence.push("arm or leg length unknown (no wrist or ankle mapped)".into());
    }
    possible += 2.0;
    match shape.readable {
        Some(_) => {
            if let (Some(spine), Some(legs)) = (shape.spine_direction(), shape.leg_direction()) {
                let a = angle(spine, legs);
                votes.push((
                    ramp(a, 110.0, 140.0),
                    1.0,
                    format!("spine {a:.0}° from the legs at rest"),
                ));
            }
            if let (Some(legs), Some(leg)) = (
                shape.leg_direction(),
                shape.leg_length(parents).filter(|&l| l > 0.0),
            ) {
                let up = -legs;
                let sole = shape
                    .soles
                    .iter()
                    .map(|s| s.dot(up))
                    .fold(f32::INFINITY, f32::min);
                let wrists: Vec<Vec3> = shape
                    .arms
                    .iter()
                    .filter_map(|a| a.end.map(|w| shape.world[w]))
                    .collect();
                if !wrists.is_empty() && sole.is_finite() {
                    let h = wrists.iter().map(|w| w.dot(up) - sole).sum::<f32>()
                        / wrists.len() as f32
                        / leg;
                    votes.push((
                        ramp(h, 0.15, 0.35),
                        1.0,
                        format!("hands {h:.2} leg lengths above the feet at rest"),
                    ));
                }
            }
        }
        None => evidence.push(
            "rest pose not standing (legs bent or apart): its directions are not used".into(),
        ),
    }
    if asset.source.bone_map.is_some() {
        possible += 1.0;
        votes.push((1.0, 1.0, "the file's humanoid bone map".into()));
    }
    let tail = asset
        .skeleton
        .names()
        .iter()
        .enumerate()
        .any(|(j, n)| n.to_ascii_lowercase().contains("tail") && is_ancestor(parents, root, j));
    if tail {
        possible += 0.5;
        votes.push((-1.0, 0.5, "a tail".into()));
    }
    let weight: f32 = votes.iter().map(|v| v.1).sum();
    let mean = if weight > 0.0 {
        votes.iter().map(|v| v.0 * v.1).sum::<f32>() / weight
    } else {
        0.0
    };
    for (v, _, what) in &votes {
        evidence.push(format!("{what} ({v:+.1})"));
    }
    let humanoid = mean > 0.0;
    let confidence = 0.5 + 0.5 * mean.abs() * (weight / possible).min(1.0);
    Classification {
        humanoid,
        confidence,
        reason: evidence.join("; "),
        evidence,
    }
}

/// +1 at `plus` and beyond, −1 at `minus` and beyond, linear between.
fn ramp(x: f32, minus: f32, plus: f32) -> f32 {
    if !x.is_finite() {
        return 0.0;
    }
    ((x - minus) / (plus - minus) * 2.0 - 1.0).clamp(-1.0, 1.0)
}

fn not(evidence: Vec<String>) -> Classification {
    Classification {
        humanoid: false,
        confidence: 1.0,
        reason: evidence.join("; "),
        evidence,
    }
}

/// Whether `a` is a strict ancestor of `b`.
fn is_ancestor(parents: &[Option<usize>], a: usize, mut b: usize) -> bool {
    while let Some(p) = parents.get(b).copied().flatten() {
        if p == a {
            return true;
        }
        b = p;
    }
    false
}
