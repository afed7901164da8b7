//! Per rig: joints mapped to H-Anim of all, the classification, and the worst world-space limb
//! and shoulder-line direction errors after retargeting CMU 01_01 onto it — every rig of the
//! shared test files, the built-in avatar, and the built-in avatar rewritten as other exporters'
//! BVH (mocapbank-style names; Bandai-Namco-style names with every joint frame turned) and a
//! quadruped.
//!
//! `cargo bench -p posecast-rigs --bench rig_figures` prints the table `docs/src/concepts/rigs.md` shows.
//!
//! Errors are angles between the same segment of source and target in world space, over every
//! frame of the baked clip (30 Hz): limbs are upper arm, forearm, thigh and shank on both sides;
//! the shoulder line runs from the right to the left shoulder joint. `atan2(|a×b|, a·b)` gives
//! them, exact near zero (f32 `acos` cannot resolve less than 0.03°).

#![allow(clippy::unwrap_used, clippy::expect_used, clippy::print_stdout)]

use glam::{Mat4, Quat, Vec3};
use posecast_proto::fk::forward_kinematics;
use posecast_proto::testing::require_testdata;
use posecast_rigs::asset::Asset;
use posecast_rigs::builtin::variants::{self, Naming, QUADRUPED_BVH};
use posecast_rigs::builtin::{AVATAR_GLB, JOINT_COUNT};
use posecast_rigs::clip::Clip;
use posecast_rigs::import::{bvh, gltf, load_path};
use posecast_rigs::rig::{Normalised, PipelineOptions, RigView, normalise, retarget};

fn positions(n: &Normalised, clip: &Clip, t: f32) -> Vec<Vec3> {
    let sk = &n.asset.skeleton;
    let mut locals = sk.rest().to_vec();
    clip.sample(t, sk.rest(), &mut locals);
    let mut world = vec![Mat4::IDENTITY; sk.len()];
    forward_kinematics(sk, &locals, &mut world);
    world.iter().map(|w| w.w_axis.truncate()).collect()
}

fn angle(a: Vec3, b: Vec3) -> f32 {
    a.cross(b).length().atan2(a.dot(b)).to_degrees()
}

fn joint(n: &Normalised, name: &str) -> Option<usize> {
    n.hanim.iter().position(|h| h.as_deref() == Some(name))
}

/// (worst limb, worst shoulder line) in degrees, or why retargeting was refused.
fn errors(source: &Normalised, target: &Normalised) -> Result<(f32, Option<f32>), String> {
    let clip = &source.asset.clips[0];
    let out =
        retarget(RigView::from(source), clip, RigView::from(target)).map_err(|e| e.to_string())?;
    let frames = ((out.duration() * 30.0).ceil() as usize).max(1);
    let mut segments: Vec<(usize, usize, usize, usize)> = Vec::new();
    for side in ["l", "r"] {
        for (a, b) in [
            ("shoulder", "elbow"),
            ("elbow", "wrist"),
            ("hip", "knee"),
            ("knee", "ankle"),
        ] {
            let (a, b) = (format!("{side}_{a}"), format!("{side}_{b}"));
            if let (Some(sa), Some(sb), Some(ta), Some(tb)) = (
                joint(source, &a),
                joint(source, &b),
                joint(target, &a),
                joint(target, &b),
            ) {
                segments.push((sa, sb, ta, tb));
            }
        }
    }
    let line = match (
        joint(source, "r_shoulder"),
        joint(source, "l_shoulder"),
        joint(target, "r_shoulder"),
        joint(target, "l_shoulder"),
    ) {
        (Some(a), Some(b), Some(c), Some(d)) => Some((a, b, c, d)),
        _ => None,
    };
    let (mut limb, mut shoulder) = (0.0f32, 0.0f32);
    for i in 0..=frames {
        let t = out.start() + out.duration() * i as f32 / frames as f32;
        let (ps, pt) = (positions(source, clip, t), positions(target, &out, t));
        for &(sa, sb, ta, tb) in &segments {
            limb = limb.max(angle(ps[sb] - ps[sa], pt[tb] - pt[ta]));
        }
        if let Some((a, b, c, d)) = line {
            shoulder = shoulder.max(angle(ps[b] - ps[a], pt[d] - pt[c]));
        }
    }
    Ok((limb, line.map(|_| shoulder)))
}

fn main() {
    let Some(cmu_path) = require_testdata("bvh/cmu/01_01.bvh") else {
        return;
    };
    let cmu = normalise(
        load_path(&cmu_path).unwrap().remove(0),
        &PipelineOptions::default(),
    )
    .unwrap();

    let mut rigs: Vec<(String, Asset)> = Vec::new();
    for rel in [
        "gltf/CesiumMan/glTF-Binary/CesiumMan.glb",
        "gltf/RiggedFigure/glTF-Binary/RiggedFigure.glb",
        "gltf/RiggedSimple/glTF-Binary/RiggedSimple.glb",
        "gltf/SimpleSkin/glTF/SimpleSkin.gltf",
        "gltf/RecursiveSkeletons/glTF-Binary/RecursiveSkeletons.glb",
        "bvh/cmu/01_01.bvh",
        "bvh/fairmotion/sinusoidal.bvh",
        "bvh/bvh_anim/test_simple.bvh",
        "cse169/wasp.skel",
        "cse169/test.skel",
        "cse169/tube.skel",
    ] {
        let Some(path) = require_testdata(rel) else {
            continue;
        };
        let assets = load_path(&path).unwrap();
        let count = assets.len();
        // RecursiveSkeletons' 4 skeletons (21 skins each, merged) are alike: its first stands
        // for all.
        let asset = assets.into_iter().next().unwrap();
        let label = if count > 1 {
            format!("`{rel}` (first of {count} rigs)")
        } else {
            format!("`{rel}`")
        };
        rigs.push((label, asset));
    }
    rigs.push((
        "built-in avatar".into(),
        gltf::from_slice("avatar.glb", AVATAR_GLB)
            .unwrap()
            .remove(0),
    ));
    let text = variants::bvh(Naming::Mocapbank, "walk", None).unwrap();
    rigs.push((
        "built-in as mocapbank-style BVH".into(),
        bvh::parse("mocapbank.bvh", &text).unwrap(),
    ));
    let turns: Vec<Quat> = (0..JOINT_COUNT)
        .map(|j| Quat::from_rotation_y(1.1 + 0.3 * j as f32) * Quat::from_rotation_x(0.9))
        .collect();
    let text = variants::bvh(Naming::Bandai, "walk", Some(&turns)).unwrap();
    rigs.push((
        "built-in as Bandai-style BVH, joint frames turned".into(),
        bvh::parse("bandai.bvh", &text).unwrap(),
    ));
    rigs.push((
        "quadruped BVH (`builtin::variants`)".into(),
        bvh::parse("fox.bvh", QUADRUPED_BVH).unwrap(),
    ));

    println!("| rig | mapped / joints | classification | worst limb | worst shoulder line |");
    println!("|---|---:|---|---:|---:|");
    for (label, asset) in rigs {
        let n = normalise(asset, &PipelineOptions::default()).unwrap();
        let total = n.hanim.len();
        let mapped = n.hanim.iter().filter(|h| h.is_some()).count();
        let class = if n.humanoid {
            "humanoid"
        } else {
            "not humanoid"
        };
        let (limb, line) = match errors(&cmu, &n) {
            Ok((limb, line)) => (
                format!("{limb:.4}°"),
                line.map_or("—".to_owned(), |l| format!("{l:.4}°")),
            ),
            Err(e) if e.contains("both must be humanoids") => {
                ("refused: `not_humanoid`".to_owned(), "—".to_owned())
            }
            Err(e) => (format!("refused: {e}"), "—".to_owned()),
        };
        println!("| {label} | {mapped} / {total} | {class} | {limb} | {line} |");
    }
}
