//! Name mapping by names and limb chains, and which rigs are humanoids (issue 18, items 2
//! and 3), on variants of the built-in avatar written as BVH by other exporters' conventions
//! and on a quadruped whose joint names read like a person's.
//!
//! `cargo test -p posecast-server --test rig_mapping -- --nocapture` prints the figures.

// Helpers outside #[test] fns unwrap too: a failure there is a test failure.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod rig_support;

use glam::{Mat4, Quat, Vec3};
use posecast_proto::fk::forward_kinematics;
use posecast_rigs::builtin::variants::{self, Naming, QUADRUPED_BVH};
use posecast_rigs::clip::Clip;
use posecast_rigs::import::bvh;
use posecast_rigs::rig::{Normalised, PipelineOptions, RigError, RigView, normalise, retarget};
use rig_support::builtin;

fn normalised(name: &str, text: &str, options: &PipelineOptions) -> Normalised {
    normalise(bvh::parse(name, text).unwrap(), options).unwrap()
}

fn joint(n: &Normalised, hanim: &str) -> usize {
    n.hanim
        .iter()
        .position(|h| h.as_deref() == Some(hanim))
        .unwrap_or_else(|| panic!("{}: {hanim} not mapped; {:?}", n.asset.name, n.steps))
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
    a.cross(b).length().atan2(a.dot(b)).to_degrees()
}

/// The worst world-space direction error of the arms (upper arm, forearm) and the shoulder
/// line (right to left shoulder), degrees, of `clip` on `source` retargeted onto `target`.
fn arm_errors(source: &Normalised, clip: &Clip, target: &Normalised) -> (f32, f32) {
    let out = retarget(RigView::from(source), clip, RigView::from(target)).unwrap();
    let (mut arms, mut line) = (0.0f32, 0.0f32);
    for i in 0..=40 {
        let t = out.start() + out.duration() * i as f32 / 40.0;
        let (ps, pt) = (positions(source, clip, t), positions(target, &out, t));
        let seg = |n: &Normalised, p: &[Vec3], a: &str, b: &str| p[joint(n, b)] - p[joint(n, a)];
        for side in ["l", "r"] {
            for (a, b) in [("shoulder", "elbow"), ("elbow", "wrist")] {
                let (a, b) = (format!("{side}_{a}"), format!("{side}_{b}"));
                arms = arms.max(angle(seg(source, &ps, &a, &b), seg(target, &pt, &a, &b)));
            }
        }
        line = line.max(angle(
            seg(source, &ps, "r_shoulder", "l_shoulder"),
            seg(target, &pt, "r_shoulder", "l_shoulder"),
        ));
    }
    (arms, line)
}

/// Mocapbank-style names: `LeftShoulder` is the upper arm. By names alone it stayed unmapped
/// and the arms did not follow; the arm chain from the hand up maps it.
#[test]
fn mocapbank_style_arms_are_mapped_from_the_hands_up() {
    let text = variants::bvh(Naming::Mocapbank, "wave", None).unwrap();
    let n = normalised("mocapbank.bvh", &text, &PipelineOptions::default());
    let name = |hanim: &str| n.asset.skeleton.names()[joint(&n, hanim)].clone();
    assert_eq!(name("l_shoulder"), "LeftShoulder");
    assert_eq!(name("r_shoulder"), "RightShoulder");
    assert_eq!(name("l_sternoclavicular"), "LeftCollar");
    assert_eq!(name("l_elbow"), "LeftElbow");
    assert!(n.humanoid, "{:?}", n.steps);
    let avatar = normalise(builtin(), &PipelineOptions::default()).unwrap();
    let wave = &avatar.asset.clips[2];
    let (arms, line) = arm_errors(&avatar, wave, &n);
    println!(
        "built-in wave -> mocapbank-style rig: arms {arms:.4} deg, shoulder line {line:.4} deg"
    );
    assert!(
        arms <= 0.05 && line <= 0.05,
        "arms {arms}, shoulder line {line}"
    );
    let (arms, line) = arm_errors(&n, &n.asset.clips[0], &avatar);
    println!("mocapbank-style wave -> built-in: arms {arms:.4} deg, shoulder line {line:.4} deg");
    assert!(
        arms <= 0.05 && line <= 0.05,
        "arms {arms}, shoulder line {line}"
    );
}

/// Bandai-Namco-style names and offsets: every joint's frame turned so that, at identity,
/// the clavicles sit in front of and behind the spine and point down. Retargeted onto the
/// built-in avatar, its shoulder line and arms follow the source.
#[test]
fn bandai_style_shoulders_follow() {
    let n = rig_support::builtin().skeleton.len();
    let turns: Vec<Quat> = (0..n)
        .map(|j| Quat::from_rotation_y(1.1 + 0.3 * j as f32) * Quat::from_rotation_x(0.9))
        .collect();
    let text = variants::bvh(Naming::Bandai, "wave", Some(&turns)).unwrap();
    let source = normalised("bandai.bvh", &text, &PipelineOptions::default());
    assert_eq!(
        source.asset.skeleton.names()[joint(&source, "l_sternoclavicular")],
        "Shoulder_L"
    );
    let avatar = normalise(builtin(), &PipelineOptions::default()).unwrap();
    let (arms, line) = arm_errors(&source, &source.asset.clips[0], &avatar);
    println!("Bandai-style wave -> built-in: arms {arms:.4} deg, shoulder line {line:.4} deg");
    assert!(
        arms <= 0.05 && line <= 0.05,
        "arms {arms}, shoulder line {line}"
    );
}

/// A quadruped whose joints map by name (`b_LeftUpperArm` → `l_shoulder`, …) is not a
/// humanoid: it keeps its neutral pose (it is not stood on its hind legs) and refuses human
/// clips with a typed error, both ways.
#[test]
fn a_quadruped_is_not_a_humanoid() {
    let fox = normalised("fox.bvh", QUADRUPED_BVH, &PipelineOptions::default());
    println!("{:?}", fox.steps);
    assert!(!fox.humanoid);
    assert!(fox.neutral_pose.is_none(), "{:?}", fox.steps);
    assert!(joint(&fox, "l_shoulder") > 0, "the names still map");
    let avatar = normalise(builtin(), &PipelineOptions::default()).unwrap();
    let walk = &avatar.asset.clips[1];
    let e = retarget(RigView::from(&avatar), walk, RigView::from(&fox)).unwrap_err();
    assert!(matches!(e, RigError::HumanoidMismatch { .. }), "{e}");
    let e = retarget(
        RigView::from(&fox),
        &fox.asset.clips[0],
        RigView::from(&avatar),
    )
    .unwrap_err();
    assert!(matches!(e, RigError::HumanoidMismatch { .. }), "{e}");
    // Its head stays in front of its hips, level: the neutral pose is the rest pose.
    let rest = positions(&fox, &fox.asset.clips[0], 0.0);
    let head = rest[joint(&fox, "skullbase")] - rest[joint(&fox, "humanoid_root")];
    assert!(head.z > 2.0 * head.y.abs(), "{head}");
}

/// The classification is an option: a user can say a rig is (or is not) a humanoid.
#[test]
fn humanoid_is_overridable() {
    let yes = PipelineOptions {
        humanoid: Some(true),
        ..PipelineOptions::default()
    };
    let fox = normalised("fox.bvh", QUADRUPED_BVH, &yes);
    assert!(
        fox.humanoid && fox.neutral_pose.is_some(),
        "{:?}",
        fox.steps
    );
    let no = PipelineOptions {
        humanoid: Some(false),
        ..PipelineOptions::default()
    };
    let avatar = normalise(builtin(), &no).unwrap();
    assert!(!avatar.humanoid && avatar.neutral_pose.is_none());
    // Every shared humanoid stays one.
    for rel in [
        "gltf/CesiumMan/glTF-Binary/CesiumMan.glb",
        "gltf/RiggedFigure/glTF-Binary/RiggedFigure.glb",
        "bvh/cmu/01_01.bvh",
    ] {
        if let Some(assets) = rig_support::load(rel) {
            let n = normalise(assets[0].clone(), &PipelineOptions::default()).unwrap();
            assert!(n.humanoid, "{rel}: {:?}", n.steps);
        }
    }
}
