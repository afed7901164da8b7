//! Retargeting CMU 01_01 (BVH) onto CesiumMan, RiggedFigure and the built-in avatar (glTF),
//! and the wasp's walk onto another CSE169 skeleton: finite poses, feet near the ground, arm
//! directions within 0.05° of the source's (arms and legs), frame by frame: the figure the
//! `docs/src/concepts/rigs.md` advertises (0.04°, the resolution of an f32 `acos` near 1).
//!
//! `cargo test -p posecast-server --test rig_retarget -- --nocapture` prints the figures.

// Helpers outside #[test] fns unwrap too: a failure there is a test failure.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod rig_support;

use glam::{Mat4, Vec3};
use posecast_proto::fk::forward_kinematics;
use posecast_rigs::clip::Clip;
use posecast_rigs::rig::retarget::DEFAULT_RATE_HZ;
use posecast_rigs::rig::{Normalised, PipelineOptions, RigView, normalise, retarget};
use rig_support::{builtin, load};

fn normalised(rel: &str) -> Option<Normalised> {
    let asset = load(rel)?.remove(0);
    Some(normalise(asset, &PipelineOptions::default()).unwrap_or_else(|e| panic!("{rel}: {e}")))
}

fn joint(n: &Normalised, name: &str) -> usize {
    n.hanim
        .iter()
        .position(|h| h.as_deref() == Some(name))
        .unwrap_or_else(|| panic!("{}: no {name}", n.asset.name))
}

fn positions(n: &Normalised, clip: &Clip, t: f32) -> Vec<Vec3> {
    let sk = &n.asset.skeleton;
    let mut locals = sk.rest().to_vec();
    clip.sample(t, sk.rest(), &mut locals);
    let mut world = vec![Mat4::IDENTITY; sk.len()];
    forward_kinematics(sk, &locals, &mut world);
    world.iter().map(|w| w.w_axis.truncate()).collect()
}

fn angle(a: Vec3, b: Vec3) -> f32 {
    a.normalize()
        .dot(b.normalize())
        .clamp(-1.0, 1.0)
        .acos()
        .to_degrees()
}

struct Figures {
    frames: usize,
    worst_arm: f32,
    mean_arm: f32,
    worst_leg: f32,
    lowest_foot: f32,
    highest_low_foot: f32,
}

/// The largest segment-direction error allowed, degrees (measured: 0.040).
const MAX_DEGREES: f32 = 0.05;

fn check(source: &Normalised, target: &Normalised) -> Figures {
    let clip = &source.asset.clips[0];
    let out = retarget(RigView::from(source), clip, RigView::from(target)).unwrap();
    assert_eq!(out.joint_count(), target.asset.skeleton.len());
    let frames = ((clip.duration() * DEFAULT_RATE_HZ).ceil() as usize + 1).max(1);
    let height = {
        let sk = &target.asset.skeleton;
        let neutral: Vec<_> = sk
            .rest()
            .iter()
            .map(|t| posecast_proto::Transform {
                rotation: glam::Quat::IDENTITY,
                ..*t
            })
            .collect();
        let mut w = vec![Mat4::IDENTITY; sk.len()];
        forward_kinematics(sk, &neutral, &mut w);
        let ys: Vec<f32> = w.iter().map(|m| m.w_axis.y).collect();
        let lo = ys.iter().cloned().fold(f32::MAX, f32::min);
        let hi = ys.iter().cloned().fold(f32::MIN, f32::max);
        (lo, hi - lo)
    };
    let (floor, size) = height;
    let segs = |side: &str| {
        [("shoulder", "elbow"), ("elbow", "wrist")]
            .map(|(a, b)| (format!("{side}_{a}"), format!("{side}_{b}")))
    };
    let legs = |side: &str| {
        [("hip", "knee"), ("knee", "ankle")]
            .map(|(a, b)| (format!("{side}_{a}"), format!("{side}_{b}")))
    };
    let mut f = Figures {
        frames,
        worst_arm: 0.0,
        mean_arm: 0.0,
        worst_leg: 0.0,
        lowest_foot: f32::MAX,
        highest_low_foot: f32::MIN,
    };
    let mut count = 0;
    for i in 0..frames {
        let t = out.start() + out.duration() * i as f32 / (frames - 1).max(1) as f32;
        let ps = positions(source, clip, t);
        let pt = positions(target, &out, t);
        assert!(
            pt.iter().all(|p| p.is_finite()),
            "{}: non-finite pose at {t}",
            target.asset.name
        );
        for side in ["l", "r"] {
            for (a, b) in segs(side) {
                let e = angle(
                    ps[joint(source, &b)] - ps[joint(source, &a)],
                    pt[joint(target, &b)] - pt[joint(target, &a)],
                );
                f.worst_arm = f.worst_arm.max(e);
                f.mean_arm += e;
                count += 1;
            }
            for (a, b) in legs(side) {
                let e = angle(
                    ps[joint(source, &b)] - ps[joint(source, &a)],
                    pt[joint(target, &b)] - pt[joint(target, &a)],
                );
                f.worst_leg = f.worst_leg.max(e);
            }
        }
        let foot = ["l_ankle", "r_ankle", "l_midtarsal", "r_midtarsal"]
            .iter()
            .filter_map(|n| target.hanim.iter().position(|h| h.as_deref() == Some(*n)))
            .map(|j| (pt[j].y - floor) / size)
            .fold(f32::MAX, f32::min);
        f.lowest_foot = f.lowest_foot.min(foot);
        f.highest_low_foot = f.highest_low_foot.max(foot);
    }
    f.mean_arm /= count as f32;
    f
}

#[test]
fn cmu_01_01_onto_gltf_avatars() {
    let Some(cmu) = normalised("bvh/cmu/01_01.bvh") else {
        return;
    };
    let mut targets: Vec<Normalised> = [
        "gltf/CesiumMan/glTF-Binary/CesiumMan.glb",
        "gltf/RiggedFigure/glTF-Binary/RiggedFigure.glb",
    ]
    .iter()
    .filter_map(|r| normalised(r))
    .collect();
    targets.push(normalise(builtin(), &PipelineOptions::default()).unwrap());
    for target in &targets {
        let f = check(&cmu, target);
        println!(
            "01_01 -> {}: {} frames at {DEFAULT_RATE_HZ} Hz; arm direction error max {:.3} deg, \
             mean {:.3} deg; leg max {:.3} deg; lowest foot joint over the floor / height: \
             min {:.3}, max {:.3}",
            target.asset.name,
            f.frames,
            f.worst_arm,
            f.mean_arm,
            f.worst_leg,
            f.lowest_foot,
            f.highest_low_foot
        );
        assert!(
            f.worst_arm <= MAX_DEGREES && f.worst_leg <= MAX_DEGREES,
            "{}: arms {}°, legs {}°",
            target.asset.name,
            f.worst_arm,
            f.worst_leg
        );
        // Feet near the ground: at their lowest over the clip, the feet are within 3% of the
        // target's height of its floor (the lowest joint at neutral), never far below it.
        assert!(
            f.lowest_foot.abs() <= 0.03,
            "{}: {}",
            target.asset.name,
            f.lowest_foot
        );
    }
}

#[test]
fn cse169_wasp_walk_onto_another_cse169_skeleton() {
    // Neither rig is humanoid enough for the H-Anim pose, so both keep their bind pose as
    // neutral; retargeting still matches the mapped joints' world rotations exactly.
    let (Some(wasp), Some(test)) = (
        normalised("cse169/wasp.skel"),
        normalised("cse169/test.skel"),
    ) else {
        return;
    };
    let clip = &wasp.asset.clips[0];
    let out = retarget(RigView::from(&wasp), clip, RigView::from(&test)).unwrap();
    let world_rot = |n: &Normalised, c: &Clip, t: f32| {
        let sk = &n.asset.skeleton;
        let mut locals = sk.rest().to_vec();
        c.sample(t, sk.rest(), &mut locals);
        let mut w = vec![Mat4::IDENTITY; sk.len()];
        forward_kinematics(sk, &locals, &mut w);
        w.iter()
            .map(|m| glam::Quat::from_mat4(m).normalize())
            .collect::<Vec<_>>()
    };
    let mut worst = 0.0f32;
    for i in 0..=40 {
        let t = out.start() + out.duration() * i as f32 / 40.0;
        let (ws, wt) = (world_rot(&wasp, clip, t), world_rot(&test, &out, t));
        assert!(wt.iter().all(|q| q.is_finite()));
        for name in ["l_hip", "r_hip", "l_knee", "r_knee"] {
            let d = ws[joint(&wasp, name)]
                .dot(wt[joint(&test, name)])
                .abs()
                .min(1.0);
            worst = worst.max(2.0 * d.acos().to_degrees());
        }
    }
    println!("wasp_walk -> test.skel: mapped world rotations differ by at most {worst:.4} deg");
    assert!(worst < 0.08, "{worst}");
}

#[test]
fn cmu_onto_itself_reproduces_the_source() {
    let Some(cmu) = normalised("bvh/cmu/01_01.bvh") else {
        return;
    };
    let f = check(&cmu, &cmu);
    println!(
        "01_01 -> itself: arm max {:.4} deg, leg max {:.4} deg",
        f.worst_arm, f.worst_leg
    );
    assert!(f.worst_arm < MAX_DEGREES && f.worst_leg < MAX_DEGREES);
}
