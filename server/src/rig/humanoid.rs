//! Whether a rig is a humanoid: what gets the H-Anim neutral pose and takes humanoid clips.
//!
//! Names alone do not decide it: a fox's `b_LeftUpperArm` and `b_LeftLeg01` map to H-Anim arm
//! and leg joints like a person's. A rig is humanoid when its mapping covers the H-Anim core
//! chain ([`CORE`] and a spine joint above the root) **and** its legs hang away from its spine
//! — in its rest pose or, since a BVH's rest pose may be a crumple of joint frames (the
//! Bandai-Namco-style files), in the middle of its first clip: the angle between the spine
//! (root to its highest mapped spine joint) and the legs (hip to ankle, or knee) is more than
//! [`MIN_LEG_SPINE_DEGREES`]. A person standing, in T-pose or A-pose, is near 180° whatever
//! axis is up; a quadruped's legs hang at about 90° from its level spine. A user's `humanoid`
//! option overrides the classification.

use glam::{Mat4, Vec3};
use posecast_proto::fk::forward_kinematics;

use super::names::{HANIM_SPINE, find};
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

/// Legs closer than this to the spine's direction (degrees) make a rig not humanoid.
pub const MIN_LEG_SPINE_DEGREES: f32 = 120.0;

/// A rig's classification and why, for people.
#[derive(Clone, Debug, PartialEq)]
pub struct Classification {
    /// Whether it is a humanoid.
    pub humanoid: bool,
    /// Why, in a few words.
    pub reason: String,
}

/// Classifies a rig from its H-Anim mapping and its rest pose.
#[must_use]
pub fn classify(asset: &Asset, hanim: &[Option<String>]) -> Classification {
    let missing: Vec<&str> = CORE
        .iter()
        .copied()
        .filter(|n| find(hanim, n).is_none())
        .collect();
    if !missing.is_empty() {
        return Classification {
            humanoid: false,
            reason: format!("no H-Anim joint mapped for {}", missing.join(", ")),
        };
    }
    let joint = |n: &str| find(hanim, n);
    let Some(root) = joint("humanoid_root") else {
        return not("no humanoid_root");
    };
    let sk = &asset.skeleton;
    let Some(top) = HANIM_SPINE
        .iter()
        .skip(2)
        .rev()
        .filter_map(|n| joint(n))
        .find(|&s| is_ancestor(sk.parents(), root, s))
    else {
        return not("no spine joint mapped above humanoid_root");
    };
    let legs: Vec<(usize, usize)> = ["l", "r"]
        .iter()
        .filter_map(|side| {
            let hip = joint(&format!("{side}_hip"))?;
            let foot =
                joint(&format!("{side}_ankle")).or_else(|| joint(&format!("{side}_knee")))?;
            Some((hip, foot))
        })
        .collect();
    let angle_in = |locals: &[posecast_proto::Transform]| -> Option<f32> {
        let mut world = vec![Mat4::IDENTITY; sk.len()];
        forward_kinematics(sk, locals, &mut world);
        let pos = |j: usize| world[j].w_axis.truncate();
        let spine = (pos(top) - pos(root)).normalize_or_zero();
        let leg = legs
            .iter()
            .map(|&(h, f)| (pos(f) - pos(h)).normalize_or_zero())
            .sum::<Vec3>()
            .normalize_or_zero();
        let angle = spine.dot(leg).clamp(-1.0, 1.0).acos().to_degrees();
        (spine != Vec3::ZERO && leg != Vec3::ZERO && angle.is_finite()).then_some(angle)
    };
    let at_rest = angle_in(sk.rest());
    if let Some(a) = at_rest.filter(|&a| a >= MIN_LEG_SPINE_DEGREES) {
        return Classification {
            humanoid: true,
            reason: format!("H-Anim core chain mapped, legs {a:.0}° from the spine at rest"),
        };
    }
    let in_clip = asset.clips.first().and_then(|clip| {
        let mut locals = sk.rest().to_vec();
        clip.sample(clip.start() + 0.5 * clip.duration(), sk.rest(), &mut locals);
        angle_in(&locals).map(|a| (a, clip.name().to_owned()))
    });
    if let Some((a, clip)) = in_clip
        .as_ref()
        .filter(|(a, _)| *a >= MIN_LEG_SPINE_DEGREES)
    {
        return Classification {
            humanoid: true,
            reason: format!("H-Anim core chain mapped, legs {a:.0}° from the spine in clip {clip}"),
        };
    }
    let measured = match (at_rest, in_clip) {
        (Some(r), Some((c, clip))) => format!("{r:.0}° at rest, {c:.0}° in clip {clip}"),
        (Some(r), None) => format!("{r:.0}° at rest"),
        (None, Some((c, clip))) => format!("{c:.0}° in clip {clip}"),
        (None, None) => return not("spine or legs of zero length"),
    };
    not(&format!(
        "its legs are {measured} from its spine (a humanoid's hang away from it, more than \
         {MIN_LEG_SPINE_DEGREES:.0}°)"
    ))
}

fn not(reason: &str) -> Classification {
    Classification {
        humanoid: false,
        reason: reason.to_owned(),
    }
}

fn is_ancestor(parents: &[Option<usize>], a: usize, mut b: usize) -> bool {
    while let Some(p) = parents[b] {
        if p == a {
            return true;
        }
        b = p;
    }
    false
}
