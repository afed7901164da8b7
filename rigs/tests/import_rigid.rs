//! Meshes parented to joints (issue 18, item 4): a robot-style glTF whose props hang from bones
//! through plain nodes imports them rigidly skinned to their joint (weight 1), posed exactly
//! where the node hierarchy puts them, and serves them in `mesh.glb`.

// Helpers outside #[test] fns unwrap too: a failure there is a test failure.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod gltf_support;

use glam::{Mat4, Quat, Vec3};
use gltf_support::{Bin, glb, triangle};
use posecast_proto::fk::PoseBuffers;
use posecast_proto::skinning::skin_cpu;
use posecast_rigs::import::gltf;
use posecast_rigs::rig::{PipelineOptions, normalise};
use serde_json::json;

/// The arm's rest rotation and its animated end rotation.
fn arm_rotations() -> (Quat, Quat) {
    let rest = Quat::from_rotation_z(30f32.to_radians());
    (rest, rest * Quat::from_rotation_x(60f32.to_radians()))
}

/// `prop`'s transform under `arm`: T(0.5, 0, 0) · R_x(90°) · S(2).
fn prop_local() -> Mat4 {
    Mat4::from_scale_rotation_translation(
        Vec3::splat(2.0),
        Quat::from_rotation_x(90f32.to_radians()),
        Vec3::new(0.5, 0.0, 0.0),
    )
}

/// A skin of two joints (`root`, `arm`) with a skinned triangle, a `prop` triangle on `arm`,
/// a `prop2` triangle on `root` through a plain `holder` node, a `floor` triangle on no joint,
/// and an animation turning `arm`.
fn robot() -> Vec<u8> {
    let (rest, end) = arm_rotations();
    let mut bin = Bin::default();
    let (pos, idx) = triangle(&mut bin);
    let joints = bin.u16s(&[0; 12], "VEC4");
    let weights = bin.floats(
        &[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0],
        "VEC4",
    );
    let arm_world = Mat4::from_rotation_translation(rest, Vec3::Y);
    let mut ibm = Mat4::IDENTITY.to_cols_array().to_vec();
    ibm.extend(arm_world.inverse().to_cols_array());
    let ibm = bin.floats(&ibm, "MAT4");
    let times = bin.floats(&[0.0, 1.0], "SCALAR");
    let values = bin.floats(&[rest.to_array(), end.to_array()].concat(), "VEC4");
    let (s, r, t) = prop_local().to_scale_rotation_translation();
    let mut doc = json!({
        "asset": {"version": "2.0"},
        "scene": 0,
        "scenes": [{"nodes": [0, 2, 6]}],
        "nodes": [
            {"name": "root", "children": [1, 4]},
            {"name": "arm", "translation": [0.0, 1.0, 0.0], "rotation": rest.to_array(), "children": [3]},
            {"name": "body", "mesh": 0, "skin": 0},
            {"name": "prop", "mesh": 1, "translation": t.to_array(), "rotation": r.to_array(), "scale": s.to_array()},
            {"name": "holder", "translation": [0.0, 0.0, 1.0], "children": [5]},
            {"name": "prop2", "mesh": 1},
            {"name": "floor", "mesh": 1}
        ],
        "skins": [{"joints": [0, 1], "inverseBindMatrices": ibm}],
        "meshes": [
            {"name": "body", "primitives": [{"attributes": {"POSITION": pos, "JOINTS_0": joints, "WEIGHTS_0": weights}, "indices": idx}]},
            {"name": "part", "primitives": [{"attributes": {"POSITION": pos}, "indices": idx}]}
        ],
        "animations": [{"name": "lift", "channels": [{"sampler": 0, "target": {"node": 1, "path": "rotation"}}],
                        "samplers": [{"input": times, "output": values}]}]
    });
    bin.finish(&mut doc);
    glb(&doc, &bin.bytes)
}

fn skinned(asset: &posecast_rigs::asset::Asset, t: f32) -> Vec<Vec<Vec3>> {
    let sk = &asset.skeleton;
    let mut locals = sk.rest().to_vec();
    asset.clips[0].sample(t, sk.rest(), &mut locals);
    let mut b = PoseBuffers::new(sk);
    b.update(sk, &locals);
    asset
        .meshes
        .iter()
        .map(|m| {
            let n = m.mesh.vertex_count();
            let (mut p, mut nn) = (vec![Vec3::ZERO; n], vec![Vec3::ZERO; n]);
            skin_cpu(&m.mesh, &b.skinning, &mut p, &mut nn);
            p
        })
        .collect()
}

#[test]
fn meshes_parented_to_joints_are_rigidly_skinned() {
    let bytes = robot();
    let asset = gltf::from_slice("robot.glb", &bytes).unwrap().remove(0);
    let names: Vec<&str> = asset.meshes.iter().map(|m| m.name.as_str()).collect();
    assert_eq!(
        names,
        ["body", "part (rigid on arm)", "part (rigid on root)"],
        "the floor hangs from no joint"
    );
    for m in &asset.meshes[1..] {
        assert_eq!(m.mesh.influences(), 1);
    }
    let tri = [Vec3::ZERO, Vec3::X, Vec3::Y];
    let (rest, end) = arm_rotations();
    for (t, arm) in [(0.0, rest), (0.5, rest.slerp(end, 0.5)), (1.0, end)] {
        let posed = skinned(&asset, t);
        let arm_world = Mat4::from_rotation_translation(arm, Vec3::Y);
        // Where the node hierarchy puts them, computed from the file's own transforms.
        let prop = arm_world * prop_local();
        let prop2 = Mat4::from_translation(Vec3::Z);
        for (k, v) in tri.iter().enumerate() {
            let want = prop.transform_point3(*v);
            assert!(
                (posed[1][k] - want).length() < 1e-5,
                "t {t}: {} vs {want}",
                posed[1][k]
            );
            let want = prop2.transform_point3(*v);
            assert!(
                (posed[2][k] - want).length() < 1e-5,
                "t {t}: {} vs {want}",
                posed[2][k]
            );
        }
    }
    // Normalised and served: mesh.glb holds all three.
    let n = normalise(asset, &PipelineOptions::default()).unwrap();
    let served = posecast_rigs::export::mesh_glb(&n.asset.skeleton, &n.asset.meshes).unwrap();
    let back = gltf::from_slice("mesh.glb", &served).unwrap().remove(0);
    let vertices: usize = back.meshes.iter().map(|m| m.mesh.vertex_count()).sum();
    assert_eq!(vertices, 9);
}
