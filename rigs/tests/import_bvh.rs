//! BVH importer on the files in ../shared/testdata/bvh: joint, End Site, channel and frame
//! counts from SOURCES.md, and joint world positions derived by hand from the file's OFFSETs
//! and Euler angles (seed 002's rotation matrices written out, not glam's quaternions).

#![allow(clippy::unwrap_used)]

use glam::{Mat3, Mat4, Vec3};
use posecast_proto::Transform;
use posecast_proto::fk::forward_kinematics;
use posecast_proto::testing::require_testdata;
use posecast_rigs::asset::Asset;
use posecast_rigs::import;

fn load(rel: &str) -> Option<(Asset, String)> {
    let path = require_testdata(rel)?;
    let mut assets = import::load_path(&path).unwrap();
    assert_eq!(assets.len(), 1);
    Some((assets.remove(0), std::fs::read_to_string(path).unwrap()))
}

/// Seed 002's R_x, R_y, R_z (row-major there; `from_cols_array` takes columns), degrees.
fn rx(d: f32) -> Mat3 {
    let (s, c) = d.to_radians().sin_cos();
    Mat3::from_cols_array(&[1.0, 0.0, 0.0, 0.0, c, s, 0.0, -s, c])
}
fn ry(d: f32) -> Mat3 {
    let (s, c) = d.to_radians().sin_cos();
    Mat3::from_cols_array(&[c, 0.0, -s, 0.0, 1.0, 0.0, s, 0.0, c])
}
fn rz(d: f32) -> Mat3 {
    let (s, c) = d.to_radians().sin_cos();
    Mat3::from_cols_array(&[c, s, 0.0, -s, c, 0.0, 0.0, 0.0, 1.0])
}

/// World positions of every joint at `time` through the importer's clip and proto's FK.
fn world_positions(a: &Asset, time: f32) -> Vec<Vec3> {
    let n = a.skeleton.len();
    let mut pose = vec![Transform::IDENTITY; n];
    a.clips[0].sample(time, a.skeleton.rest(), &mut pose);
    let mut world = vec![Mat4::IDENTITY; n];
    forward_kinematics(&a.skeleton, &pose, &mut world);
    world.iter().map(|w| w.w_axis.truncate()).collect()
}

/// The numbers on the motion line of frame `f`.
fn frame_values(text: &str, f: usize) -> Vec<f32> {
    let lines: Vec<&str> = text.lines().collect();
    let at = lines
        .iter()
        .position(|l| l.trim_start().starts_with("Frame Time"))
        .unwrap();
    lines[at + 1 + f]
        .split_whitespace()
        .map(|v| v.parse().unwrap())
        .collect()
}

#[test]
fn cmu_01_01_figures_and_hand_derived_positions() {
    let Some((a, text)) = load("bvh/cmu/01_01.bvh") else {
        return;
    };
    assert_eq!(a.skeleton.len(), 31);
    assert_eq!(a.source.end_sites.len(), 7);
    let clip = &a.clips[0];
    let dt = 0.0083333f32;
    assert!(
        (clip.duration() - 2751.0 * dt).abs() < 1e-3,
        "{}",
        clip.duration()
    );
    assert_eq!(clip.start(), 0.0);
    assert_eq!(frame_values(&text, 0).len(), 96);
    assert_eq!(
        a.skeleton.names()[..4],
        ["Hips", "LHipJoint", "LeftUpLeg", "LeftLeg"]
    );
    assert!((0..31).all(|j| clip.animates_rotation(j)));
    assert!(clip.animates_translation(0) && !clip.animates_translation(1));

    for f in [0usize, 1, 1000, 2751] {
        let v = frame_values(&text, f);
        // Hips: Xpos Ypos Zpos Zrot Yrot Xrot; the others Zrot Yrot Xrot: R = Rz · Ry · Rx.
        let hips_p = Vec3::new(v[0], v[1], v[2]);
        let hips_r = rz(v[3]) * ry(v[4]) * rx(v[5]);
        let lhip_r = rz(v[6]) * ry(v[7]) * rx(v[8]);
        let lul_r = rz(v[9]) * ry(v[10]) * rx(v[11]);
        // LHipJoint sits at the hips (OFFSET 0 0 0); LeftUpLeg at OFFSET 1.36306 -1.79463
        // 0.83929 from it; LeftLeg at OFFSET 2.44811 -6.72613 0 from LeftUpLeg.
        let lhip_world_r = hips_r * lhip_r;
        let lul = hips_p + lhip_world_r * Vec3::new(1.36306, -1.79463, 0.83929);
        let leg = lul + lhip_world_r * lul_r * Vec3::new(2.44811, -6.72613, 0.0);
        let got = world_positions(&a, f as f32 * dt);
        let tol = 2e-3;
        assert!(
            (got[0] - hips_p).length() < tol,
            "frame {f}: hips {} vs {hips_p}",
            got[0]
        );
        assert!(
            (got[2] - lul).length() < tol,
            "frame {f}: LeftUpLeg {} vs {lul}",
            got[2]
        );
        assert!(
            (got[3] - leg).length() < tol,
            "frame {f}: LeftLeg {} vs {leg}",
            got[3]
        );
    }
}

#[test]
fn test_simple_by_hand() {
    let Some((a, _)) = load("bvh/bvh_anim/test_simple.bvh") else {
        return;
    };
    assert_eq!(a.skeleton.names(), &["Base", "End"]);
    assert_eq!(a.source.end_sites, vec![(1, Vec3::new(0.0, 0.0, 30.0))]);
    let clip = &a.clips[0];
    assert!((clip.duration() - 1.0 / 30.0).abs() < 1e-7); // Frame Time 0.033333333
    // Frame 0: everything zero, so End is at its offset.
    let p = world_positions(&a, 0.0);
    assert!(p[1].abs_diff_eq(Vec3::new(0.0, 0.0, 15.0), 1e-6));
    // Frame 1: all channels 1. Root `Zrotation Xrotation Yrotation` is Rz · Rx · Ry.
    let root_r = rz(1.0) * rx(1.0) * ry(1.0);
    let end = Vec3::ONE + root_r * Vec3::new(0.0, 0.0, 15.0);
    let p = world_positions(&a, clip.end());
    assert!((p[0] - Vec3::ONE).length() < 1e-5);
    assert!((p[1] - end).length() < 1e-4, "{} vs {end}", p[1]);
    // Halfway: slerp of the root between identity and root_r is the half angle about the
    // same axis; the root position is the mean.
    let p = world_positions(&a, clip.end() / 2.0);
    assert!((p[0] - Vec3::splat(0.5)).length() < 1e-5);
}

#[test]
fn sinusoidal_without_end_sites() {
    let Some((a, text)) = load("bvh/fairmotion/sinusoidal.bvh") else {
        return;
    };
    assert_eq!(a.skeleton.len(), 4);
    assert!(a.source.end_sites.is_empty());
    assert_eq!(frame_values(&text, 0).len(), 15);
    let clip = &a.clips[0];
    let dt = 1.0f32 / 60.0; // Frame Time 0.016666666666666666
    assert!((clip.duration() - 119.0 * dt).abs() < 1e-4);
    // child1 at OFFSET (0, 5, 0) under the root: X Y Z order is Rx · Ry · Rz.
    for f in [0usize, 37, 119] {
        let v = frame_values(&text, f);
        let root_r = rx(v[3]) * ry(v[4]) * rz(v[5]);
        let c1_r = rx(v[6]) * ry(v[7]) * rz(v[8]);
        let c1 = Vec3::new(v[0], v[1], v[2]) + root_r * Vec3::new(0.0, 5.0, 0.0);
        let c2 = c1 + root_r * c1_r * Vec3::new(-5.0, 0.0, 0.0);
        let p = world_positions(&a, f as f32 * dt);
        assert!((p[1] - c1).length() < 1e-3, "frame {f}: {} vs {c1}", p[1]);
        assert!((p[2] - c2).length() < 1e-3, "frame {f}: {} vs {c2}", p[2]);
    }
}
