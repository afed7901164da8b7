//! Retargeting between rigs whose chains differ (issue 35, goal 5): CMU 01_01 (BVH) onto a rig
//! derived from the same file's skeleton with a shorter spine, no hip connectors, roll joints
//! inside the upper arms, other bone lengths, an A-pose bind and every joint frame turned.
//!
//! Retargeting matches world rotations (`G_j = G_src(j)`, `server/src/rig/retarget.rs`), so the
//! arms and legs of the target point where the source's do, frame by frame, whatever joints lie
//! between them. Copying local rotations by H-Anim name would not: the spine joint the target
//! lacks carries part of the torso's turn, which the copy drops, so every arm segment hanging
//! below it points elsewhere. The test measures both — the world-space figure must stay within
//! [`MAX_DEGREES`], the copy's must exceed [`COPY_AT_LEAST`] — so it shows itself that the two
//! rigs differ enough to tell the methods apart (the other retargeting tests pair rigs whose
//! chains match, where both methods agree).
//!
//! `cargo test --workspace --test rig_retarget_chains -- --nocapture` prints the figures.

// Helpers outside #[test] fns unwrap too: a failure there is a test failure.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod rig_support;

use glam::{EulerRot, Mat4, Quat, Vec3};
use posecast_proto::fk::forward_kinematics;
use posecast_proto::{Skeleton, Transform};
use posecast_rigs::asset::{Asset, SourceFormat, SourceInfo};
use posecast_rigs::clip::Clip;
use posecast_rigs::rig::retarget::DEFAULT_RATE_HZ;
use posecast_rigs::rig::{Normalised, PipelineOptions, RigView, normalise, retarget};
use rig_support::load;

/// The largest segment-direction error allowed for world-space retargeting, degrees
/// (measured: arms 0.034°, legs 0.040° over the clip's 689 frames; as between rigs of the
/// same chains in `rig_retarget.rs`, the resolution of an f32 `acos` near 1).
const MAX_DEGREES: f32 = 0.05;

/// The least worst-case arm error copying local rotations must show for this test to tell
/// the methods apart, degrees: a hundred times [`MAX_DEGREES`] (measured: 31.9°, the turn of
/// CMU's `LowerBack`, which the target has no joint for). The legs do not tell (copying gives
/// 0.0° there): the hip connectors the target drops hold no rotation in 01_01, so the leg
/// chains that move are the same.
const COPY_AT_LEAST: f32 = 5.0;

/// CMU joints the derived rig leaves out: one of the three spine joints, and the hip
/// connectors (the thighs hang from the pelvis itself, as in most rigs).
const DROPPED: &[&str] = &["Spine", "LHipJoint", "RHipJoint"];

/// Upper arms that get a roll joint half way to the elbow (a helper, as many game rigs have).
const ROLLED: &[&str] = &["LeftArm", "RightArm"];

/// How much longer each part's bones are in the derived rig.
fn bone_scale(name: &str) -> f32 {
    if ["Leg", "Foot", "Toe"].iter().any(|p| name.contains(p)) {
        1.15
    } else if ["Arm", "Hand", "Finger", "Thumb"]
        .iter()
        .any(|p| name.contains(p))
    {
        0.9
    } else if ["Back", "Spine", "Neck", "Head"]
        .iter()
        .any(|p| name.contains(p))
    {
        1.1
    } else {
        1.0
    }
}

/// A deterministic joint frame for new joint `k`: up to ±80° about each axis.
fn frame(k: usize) -> Quat {
    let a = |i: usize| 1.4 * ((k * 7 + i * 13) as f32 * 0.77).sin();
    Quat::from_euler(EulerRot::XYZ, a(1), a(2), a(3))
}

/// A rig derived from CMU 01_01's skeleton (no clip): [`DROPPED`] joints removed (children
/// re-hung on the nearest kept ancestor), a `…Roll` joint inserted in each of [`ROLLED`], every
/// bone scaled by [`bone_scale`], the arms bound 40° lower than the source's T-pose (an A-pose
/// bind: the forearms and hands rotated rigidly about the shoulders), and every joint's frame
/// turned by [`frame`], so its rest local rotations are far from identity. The rest joint
/// positions say where the joints are; the frames only how each joint's axes lie. Binds equal
/// the rest pose.
fn derive(raw: &Asset) -> Asset {
    let sk = &raw.skeleton;
    let names = sk.names();
    let mut world = vec![Mat4::IDENTITY; sk.len()];
    forward_kinematics(sk, sk.rest(), &mut world);
    let p: Vec<Vec3> = world.iter().map(|w| w.w_axis.truncate()).collect();
    let dropped = |j: usize| DROPPED.contains(&names[j].as_str());
    let kept_parent = |mut j: usize| loop {
        match sk.parents()[j] {
            Some(q) if dropped(q) => j = q,
            other => break other,
        }
    };
    // The A-pose: below each upper arm, a rotation about the forward axis bringing the arm
    // 40° nearer the body.
    let lowered: Vec<Option<Quat>> = (0..sk.len())
        .map(|j| {
            let mut a = j;
            while let Some(q) = sk.parents()[a] {
                if ROLLED.contains(&names[q].as_str()) {
                    let outward = (p[a] - p[q]).x.signum();
                    return Some(Quat::from_rotation_z(-outward * 40f32.to_radians()));
                }
                a = q;
            }
            None
        })
        .collect();
    // A point fixed to joint `j`'s bone (from its kept parent's place `from_old`, now at
    // `from_new`), after scaling and lowering.
    let carry = |j: usize, point: Vec3, from_old: Vec3, from_new: Vec3| {
        let turn = lowered[j].unwrap_or(Quat::IDENTITY);
        from_new + bone_scale(&names[j]) * (turn * (point - from_old))
    };
    // New positions of the original joints (parents before children).
    let mut moved = vec![Vec3::ZERO; sk.len()];
    for j in 0..sk.len() {
        moved[j] = match kept_parent(j) {
            Some(q) => carry(j, p[j], p[q], moved[q]),
            None => p[j],
        };
    }
    // The new joint list: (original joint, or the upper arm a roll joint sits in).
    enum New {
        Kept(usize),
        Roll(usize),
    }
    let mut list = Vec::new();
    let mut index = vec![None; sk.len()];
    let mut roll_of = vec![None; sk.len()];
    for j in 0..sk.len() {
        if dropped(j) {
            continue;
        }
        index[j] = Some(list.len());
        list.push(New::Kept(j));
        if ROLLED.contains(&names[j].as_str()) {
            roll_of[j] = Some(list.len());
            list.push(New::Roll(j));
        }
    }
    let mut new_names = Vec::new();
    let mut parents = Vec::new();
    let mut positions = Vec::new();
    for item in &list {
        match *item {
            New::Kept(j) => {
                new_names.push(names[j].clone());
                let q = kept_parent(j);
                parents.push(q.map(|q| roll_of[q].or(index[q]).unwrap()));
                positions.push(moved[j]);
            }
            New::Roll(arm) => {
                new_names.push(format!("{}Roll", names[arm]));
                parents.push(index[arm]);
                let elbow = (0..sk.len())
                    .find(|&c| sk.parents()[c] == Some(arm))
                    .unwrap();
                positions.push((moved[arm] + moved[elbow]) / 2.0);
            }
        }
    }
    let frames: Vec<Quat> = (0..list.len()).map(frame).collect();
    let rest: Vec<Transform> = (0..list.len())
        .map(|k| {
            let (rotation, translation) = match parents[k] {
                Some(q) => (
                    frames[q].inverse() * frames[k],
                    frames[q].inverse() * (positions[k] - positions[q]),
                ),
                None => (frames[k], positions[k]),
            };
            Transform {
                translation,
                rotation,
                scale: Vec3::ONE,
            }
        })
        .collect();
    let inverse_bind = (0..list.len())
        .map(|k| Mat4::from_rotation_translation(frames[k], positions[k]).inverse())
        .collect();
    let end_sites = raw
        .source
        .end_sites
        .iter()
        .map(|&(j, offset)| {
            let k = index[j].expect("end sites sit on kept joints");
            let end = carry(j, world[j].transform_point3(offset), p[j], moved[j]);
            (k, frames[k].inverse() * (end - positions[k]))
        })
        .collect();
    let skeleton = Skeleton::new(new_names, parents, rest, inverse_bind).expect("a valid rig");
    Asset {
        name: "01_01 derived".into(),
        skeleton,
        meshes: vec![],
        clips: vec![],
        source: SourceInfo {
            end_sites,
            ..SourceInfo::new(SourceFormat::Bvh)
        },
        boxes: None,
        expressions: Vec::new(),
    }
}

fn joint(n: &Normalised, name: &str) -> usize {
    n.hanim
        .iter()
        .position(|h| h.as_deref() == Some(name))
        .unwrap_or_else(|| panic!("{}: no {name}", n.asset.name))
}

/// World joint positions of `n` posed by `locals`.
fn positions(n: &Normalised, locals: &[Transform]) -> Vec<Vec3> {
    let sk = &n.asset.skeleton;
    let mut world = vec![Mat4::IDENTITY; sk.len()];
    forward_kinematics(sk, locals, &mut world);
    world.iter().map(|w| w.w_axis.truncate()).collect()
}

fn sampled(n: &Normalised, clip: &Clip, t: f32) -> Vec<Transform> {
    let rest = n.asset.skeleton.rest();
    let mut locals = rest.to_vec();
    clip.sample(t, rest, &mut locals);
    locals
}

fn angle(a: Vec3, b: Vec3) -> f32 {
    a.normalize()
        .dot(b.normalize())
        .clamp(-1.0, 1.0)
        .acos()
        .to_degrees()
}

/// The H-Anim segments compared: each side's upper arm, forearm, thigh and shank.
const ARMS: [(&str, &str); 2] = [("shoulder", "elbow"), ("elbow", "wrist")];
const LEGS: [(&str, &str); 2] = [("hip", "knee"), ("knee", "ankle")];

/// Worst direction errors, degrees: (arms, legs).
#[derive(Default, Debug, Clone, Copy)]
struct Worst(f32, f32);

impl Worst {
    fn add(&mut self, source: (&Normalised, &[Vec3]), target: (&Normalised, &[Vec3])) {
        let seg =
            |(n, p): (&Normalised, &[Vec3]), a: &str, b: &str| p[joint(n, b)] - p[joint(n, a)];
        for side in ["l", "r"] {
            for (segments, worst) in [(&ARMS, &mut self.0), (&LEGS, &mut self.1)] {
                for (a, b) in segments {
                    let (a, b) = (format!("{side}_{a}"), format!("{side}_{b}"));
                    *worst = worst.max(angle(seg(source, &a, &b), seg(target, &a, &b)));
                }
            }
        }
    }
}

#[test]
fn cmu_01_01_onto_a_rig_with_other_chains_matches_in_world_space() {
    let Some(raw) = load("bvh/cmu/01_01.bvh").map(|mut a| a.remove(0)) else {
        return;
    };
    let options = PipelineOptions::default();
    let derived = derive(&raw);
    // The derived rig's binds are not the identity frames the source's are.
    let turned = derived
        .skeleton
        .rest()
        .iter()
        .filter(|t| t.rotation.angle_between(Quat::IDENTITY).to_degrees() > 10.0)
        .count();
    assert!(
        turned * 2 > derived.skeleton.len(),
        "{turned} turned joints"
    );
    let source = normalise(raw, &options).unwrap();
    let target = normalise(derived, &options).unwrap();
    assert!(target.humanoid, "{:?}", target.steps);
    let spine = |n: &Normalised| {
        let mut s: Vec<(String, String)> = n
            .hanim
            .iter()
            .enumerate()
            .filter_map(|(j, h)| {
                let h = h.as_deref()?;
                (h.starts_with("vl") || h.starts_with("vt"))
                    .then(|| (n.asset.skeleton.names()[j].clone(), h.to_owned()))
            })
            .collect();
        s.sort();
        s
    };
    println!("spine of the source: {:?}", spine(&source));
    println!("spine of the target: {:?}", spine(&target));
    println!("target unmapped: {:?}", target.unmapped);
    assert!(spine(&target).len() < spine(&source).len());

    let clip = &source.asset.clips[0];
    let out = retarget(RigView::from(&source), clip, RigView::from(&target)).unwrap();
    assert_eq!(out.joint_count(), target.asset.skeleton.len());
    // The source joint each target joint would copy its local rotation from.
    let pairs: Vec<Option<usize>> = target
        .hanim
        .iter()
        .map(|h| {
            let h = h.as_deref()?;
            source.hanim.iter().position(|s| s.as_deref() == Some(h))
        })
        .collect();
    let neutral: Vec<Transform> = target
        .asset
        .skeleton
        .rest()
        .iter()
        .map(|t| Transform {
            rotation: Quat::IDENTITY,
            ..*t
        })
        .collect();
    let frames = ((clip.duration() * DEFAULT_RATE_HZ).ceil() as usize + 1).max(2);
    let (mut world, mut copied) = (Worst::default(), Worst::default());
    for i in 0..frames {
        let t = out.start() + out.duration() * i as f32 / (frames - 1) as f32;
        let src_locals = sampled(&source, clip, t);
        let ps = positions(&source, &src_locals);
        let pt = positions(&target, &sampled(&target, &out, t));
        assert!(pt.iter().all(|p| p.is_finite()), "non-finite pose at {t}");
        world.add((&source, &ps), (&target, &pt));
        let mut copy = neutral.clone();
        for (c, pair) in copy.iter_mut().zip(&pairs) {
            if let Some(s) = pair {
                c.rotation = src_locals[*s].rotation;
            }
        }
        copied.add((&source, &ps), (&target, &positions(&target, &copy)));
    }
    println!(
        "01_01 -> {} ({frames} frames): world-space retargeting: arms max {:.3} deg, legs max \
         {:.3} deg; copying local rotations by H-Anim name: arms max {:.1} deg, legs max {:.1} deg",
        target.asset.name, world.0, world.1, copied.0, copied.1
    );
    assert!(
        world.0 <= MAX_DEGREES && world.1 <= MAX_DEGREES,
        "world-space retargeting: arms {}°, legs {}°",
        world.0,
        world.1
    );
    assert!(
        copied.0 >= COPY_AT_LEAST,
        "copying local rotations is within {}° of the source's arms: the rigs do not differ \
         enough to tell the methods apart",
        copied.0
    );
}
