//! Cross-rig retargeting: a clip authored for one normalised rig, played on another.
//!
//! Both rigs must be in the same neutral pose (H-Anim, after [`normalise`](super::normalise)),
//! so all-identity local rotations mean the same posture and every joint's neutral world
//! rotation is the identity. Each mapped target joint then takes the world rotation of the
//! source joint with the same H-Anim name, `G_j = G_src(j)`, and its local rotation follows as
//! `L_j = G_parent(j)⁻¹ G_j`; unmapped target joints stay at neutral (`L_j = I`). Matching in
//! world space, not by copying local rotations, keeps rigs with different numbers of spine or
//! neck joints in agreement. The root translation is scaled by the ratio of hip heights.
//!
//! World-space matching is not a per-joint constant map of the source's channels, so the
//! result is baked: the source is sampled at a fixed rate ([`DEFAULT_RATE_HZ`], 30 Hz) over
//! its range, and every target joint gets a linear quaternion track.

use std::collections::HashMap;

use glam::{Mat4, Quat, Vec3};
use posecast_proto::Transform;
use posecast_proto::fk::forward_kinematics;

use super::RigError;
use super::names::find;
use super::pipeline::Normalised;
use crate::asset::Asset;
use crate::clip::{Clip, Interpolation, JointChannels, RotationChannel, Track, VectorChannel};

/// The rate retargeted clips are baked at, keys per second.
pub const DEFAULT_RATE_HZ: f32 = 30.0;

/// The most keys a baked clip gets (an hour at 30 Hz); longer clips are sampled more sparsely.
pub const MAX_KEYS: usize = 108_000;

/// A normalised rig as retargeting sees it: the asset, each joint's H-Anim name and whether it
/// is a humanoid.
#[derive(Clone, Copy, Debug)]
pub struct RigView<'a> {
    /// The normalised asset (skeleton and rest pose).
    pub asset: &'a Asset,
    /// Per joint, its H-Anim name, `None` for an unmapped joint.
    pub hanim: &'a [Option<String>],
    /// Whether the rig counts as a humanoid (retargeting needs both or neither).
    pub humanoid: bool,
}

impl<'a> From<&'a Normalised> for RigView<'a> {
    fn from(n: &'a Normalised) -> Self {
        Self {
            asset: &n.asset,
            hanim: &n.hanim,
            humanoid: n.humanoid,
        }
    }
}

/// [`retarget_at_rate`] at [`DEFAULT_RATE_HZ`].
pub fn retarget(source: RigView<'_>, clip: &Clip, target: RigView<'_>) -> Result<Clip, RigError> {
    retarget_at_rate(source, clip, target, DEFAULT_RATE_HZ)
}

/// Retargets `clip` (one channel slot per `source` joint) onto `target`, baked at `rate_hz`
/// keys per second from the clip's start to its end (both included).
///
/// Both rigs need a `humanoid_root`. The target's `humanoid_root` world position follows the
/// source's scaled by `k = hip height(target) / hip height(source)` (hip height: the
/// humanoid root's height above the lowest joint at neutral): horizontally relative to the
/// first frame, starting from the target's own neutral place; vertically above the floor,
/// taken as the lowest joint over the clip for the source and at neutral for the target.
pub fn retarget_at_rate(
    source: RigView<'_>,
    clip: &Clip,
    target: RigView<'_>,
    rate_hz: f32,
) -> Result<Clip, RigError> {
    if !(rate_hz.is_finite() && rate_hz > 0.0) {
        return Err(RigError::BadInput {
            what: "retargeting rate",
            message: format!("{rate_hz} keys per second"),
        });
    }
    let map = PoseRetargeter::new(source, target)?;
    let (ss, ts) = (&source.asset.skeleton, &target.asset.skeleton);
    let mut src_world = vec![Mat4::IDENTITY; ss.len()];

    // Times.
    let duration = clip.duration();
    let keys = ((duration * rate_hz).ceil() as usize + 1).clamp(1, MAX_KEYS);
    let times: Vec<f32> = (0..keys)
        .map(|i| {
            if keys == 1 {
                clip.start()
            } else {
                clip.start() + duration * i as f32 / (keys - 1) as f32
            }
        })
        .collect();

    // Sample the source once per key: local rotations and the root's world position.
    let mut sampler = clip.sampler();
    let mut locals = ss.rest().to_vec();
    let mut frames: Vec<(Vec<Quat>, Vec3)> = Vec::with_capacity(keys);
    let mut src_floor = f32::MAX;
    for &t in &times {
        sampler.sample(clip, t, ss.rest(), &mut locals);
        forward_kinematics(ss, &locals, &mut src_world);
        src_floor = src_floor.min(lowest(&src_world));
        frames.push((
            locals.iter().map(|l| l.rotation).collect(),
            src_world[map.src_root].w_axis.truncate(),
        ));
    }
    let src_start = frames.first().map_or(Vec3::ZERO, |f| f.1);

    // Solve the target per key.
    let n = ts.len();
    let mut rot_keys: Vec<Vec<Quat>> = vec![Vec::with_capacity(keys); n];
    let mut root_keys = Vec::with_capacity(keys);
    let mut scratch = PoseScratch::new(source, target);
    let mut solved = vec![Quat::IDENTITY; n];
    let mut pose = map.tgt_neutral.clone();
    let mut tgt_world = vec![Mat4::IDENTITY; n];
    let tgt_root = map.tgt_root;
    for (src_locals, src_pos) in &frames {
        map.solve(src_locals, &mut scratch, &mut solved);
        for (j, &local) in solved.iter().enumerate() {
            let keys = &mut rot_keys[j];
            // Keep consecutive keys in one hemisphere so linear keys interpolate the short way.
            let local = match keys.last() {
                Some(prev) if prev.dot(local) < 0.0 => -local,
                _ => local,
            };
            keys.push(local);
            pose[j].rotation = local;
        }
        let desired = Vec3::new(
            map.tgt_start.x + map.k * (src_pos.x - src_start.x),
            map.tgt_floor + map.k * (src_pos.y - src_floor),
            map.tgt_start.z + map.k * (src_pos.z - src_start.z),
        );
        forward_kinematics(ts, &pose, &mut tgt_world);
        let local = match ts.parents()[tgt_root] {
            Some(p) => tgt_world[p].inverse().transform_point3(desired),
            None => desired,
        };
        root_keys.push(local);
    }

    let mut joints = Vec::with_capacity(n);
    for (j, keys) in rot_keys.into_iter().enumerate() {
        let rotation = Track::new(Interpolation::Linear, times.clone(), keys)?;
        let translation = if j == tgt_root {
            Some(VectorChannel::Keys(Track::new(
                Interpolation::Linear,
                times.clone(),
                root_keys.clone(),
            )?))
        } else {
            None
        };
        joints.push(JointChannels {
            rotation: Some(RotationChannel::Keys(rotation)),
            translation,
            ..Default::default()
        });
    }
    Ok(Clip::new(
        format!(
            "{} ({} → {})",
            clip.name(),
            source.asset.name,
            target.asset.name
        ),
        joints,
        Some((clip.start(), clip.end())),
    )?
    // Morph weights are by channel name: they carry over as they are.
    .with_morphs(clip.morphs().to_vec()))
}

/// One source pose to target local rotations, the per-pose step of world-space retargeting.
///
/// Built once per (source rig, target rig); [`PoseRetargeter::solve`] then maps a source pose
/// without allocating. Both rigs are normalised to the same neutral pose, so a mapped target
/// joint takes the world rotation of the source joint with its H-Anim name,
/// `G_j = G_src(j)`, and `L_j = G_parent(j)⁻¹ G_j`; unmapped joints stay neutral (`L_j = I`).
/// The baker ([`retarget_at_rate`]) and live driving both use it, so they are one piece of
/// maths.
#[derive(Clone, Debug)]
pub struct PoseRetargeter {
    /// Per target joint, the source joint it takes its world rotation from.
    pairs: Vec<Option<usize>>,
    src_parents: Vec<Option<usize>>,
    tgt_parents: Vec<Option<usize>>,
    /// The source's `humanoid_root`.
    pub src_root: usize,
    /// The target's `humanoid_root`.
    pub tgt_root: usize,
    /// Root translation scale: hip height(target) / hip height(source).
    pub k: f32,
    /// The target's neutral pose (identity rotations over its rest translations).
    pub tgt_neutral: Vec<Transform>,
    /// The target's lowest joint at neutral (its floor), metres.
    pub tgt_floor: f32,
    /// The target's `humanoid_root` world position at neutral.
    pub tgt_start: Vec3,
    /// The source's `humanoid_root` world position at neutral.
    pub src_start: Vec3,
    /// The source's lowest joint at neutral (its floor), metres.
    pub src_floor: f32,
}

/// Working memory of [`PoseRetargeter::solve`] (world rotations of both rigs).
#[derive(Clone, Debug)]
pub struct PoseScratch {
    src_world: Vec<Quat>,
    tgt_world: Vec<Quat>,
}

impl PoseScratch {
    /// Room for one pose of each rig.
    #[must_use]
    pub fn new(source: RigView<'_>, target: RigView<'_>) -> Self {
        Self {
            src_world: vec![Quat::IDENTITY; source.asset.skeleton.len()],
            tgt_world: vec![Quat::IDENTITY; target.asset.skeleton.len()],
        }
    }
}

impl PoseRetargeter {
    /// Matches `target`'s joints to `source`'s by H-Anim name and measures both rigs at
    /// neutral.
    ///
    /// # Errors
    /// A humanoid and a rig that is not one, an H-Anim list of the wrong length, a rig without
    /// `humanoid_root`, or a root that is not above the feet.
    pub fn new(source: RigView<'_>, target: RigView<'_>) -> Result<Self, RigError> {
        if source.humanoid != target.humanoid {
            return Err(RigError::HumanoidMismatch {
                from: source.asset.name.clone(),
                from_humanoid: source.humanoid,
                onto: target.asset.name.clone(),
                onto_humanoid: target.humanoid,
            });
        }
        let (ss, ts) = (&source.asset.skeleton, &target.asset.skeleton);
        for (view, what) in [(&source, "source hanim"), (&target, "target hanim")] {
            if view.hanim.len() != view.asset.skeleton.len() {
                return Err(RigError::Length {
                    what,
                    expected: view.asset.skeleton.len(),
                    actual: view.hanim.len(),
                });
            }
        }
        let root_of = |v: &RigView<'_>| {
            find(v.hanim, "humanoid_root").ok_or_else(|| RigError::NotHumanoid {
                rig: v.asset.name.clone(),
                missing: vec!["humanoid_root".into()],
            })
        };
        let (src_root, tgt_root) = (root_of(&source)?, root_of(&target)?);
        let by_name: HashMap<&str, usize> = source
            .hanim
            .iter()
            .enumerate()
            .filter_map(|(j, h)| h.as_deref().map(|h| (h, j)))
            .collect();
        let pairs: Vec<Option<usize>> = target
            .hanim
            .iter()
            .map(|h| h.as_deref().and_then(|h| by_name.get(h).copied()))
            .collect();
        let (src_neutral, tgt_neutral) = (neutral(source.asset), neutral(target.asset));
        let mut src_world = vec![Mat4::IDENTITY; ss.len()];
        let mut tgt_world = vec![Mat4::IDENTITY; ts.len()];
        forward_kinematics(ss, &src_neutral, &mut src_world);
        let src_floor = lowest(&src_world);
        let src_hip = src_world[src_root].w_axis.y - src_floor;
        forward_kinematics(ts, &tgt_neutral, &mut tgt_world);
        let tgt_floor = lowest(&tgt_world);
        let tgt_hip = tgt_world[tgt_root].w_axis.y - tgt_floor;
        if !(src_hip > 0.0 && tgt_hip > 0.0) {
            return Err(RigError::BadInput {
                what: "hip height",
                message: format!(
                    "source {src_hip}, target {tgt_hip}: the root must be above the feet"
                ),
            });
        }
        // A root a hair above the feet (1e-30) would scale root motion to infinity; even rigs
        // in different units (cm against m) stay well within a factor of 1,000.
        let k = tgt_hip / src_hip;
        if !(k.is_finite() && (1e-3..=1e3).contains(&k)) {
            return Err(RigError::BadInput {
                what: "hip height",
                message: format!(
                    "source {src_hip}, target {tgt_hip}: the rigs' hip heights differ by more than 1,000×"
                ),
            });
        }
        Ok(Self {
            pairs,
            src_parents: ss.parents().to_vec(),
            tgt_parents: ts.parents().to_vec(),
            src_root,
            tgt_root,
            k,
            tgt_neutral,
            tgt_floor,
            tgt_start: tgt_world[tgt_root].w_axis.truncate(),
            src_start: src_world[src_root].w_axis.truncate(),
            src_floor,
        })
    }

    /// Maps one source pose (`src_locals`: local rotations, one per source joint) to target
    /// local rotations (`out`, one per target joint): `G_src = G_src,parent · R` down the
    /// source tree, then `L_j = G_parent(j)⁻¹ G_src(pair(j))` down the target tree.
    /// Missing source entries count as identity.
    pub fn solve(&self, src_locals: &[Quat], scratch: &mut PoseScratch, out: &mut [Quat]) {
        for (j, parent) in self.src_parents.iter().enumerate() {
            let r = src_locals.get(j).copied().unwrap_or(Quat::IDENTITY);
            scratch.src_world[j] = match parent {
                Some(p) => (scratch.src_world[*p] * r).normalize(),
                None => r,
            };
        }
        for (j, parent) in self.tgt_parents.iter().enumerate() {
            let parent = parent.map_or(Quat::IDENTITY, |p| scratch.tgt_world[p]);
            let local = match self.pairs[j] {
                Some(s) => (parent.inverse() * scratch.src_world[s]).normalize(),
                None => Quat::IDENTITY,
            };
            scratch.tgt_world[j] = (parent * local).normalize();
            if let Some(o) = out.get_mut(j) {
                *o = local;
            }
        }
    }
}

/// A rig's neutral pose: all rotations identity over the rest translations.
fn neutral(a: &Asset) -> Vec<Transform> {
    a.skeleton
        .rest()
        .iter()
        .map(|t| Transform {
            rotation: Quat::IDENTITY,
            ..*t
        })
        .collect()
}

fn lowest(world: &[Mat4]) -> f32 {
    world.iter().fold(f32::MAX, |m, w| m.min(w.w_axis.y))
}
