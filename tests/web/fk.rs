//! The JavaScript client's forward kinematics and skinning matrices (`server/sdk/fk.js`)
//! against `posecast_proto::fk`.

use crate::root;
use glam::{Mat4, Quat, Vec3};
use posecast_proto::Transform;
use posecast_proto::description::AvatarDescription;
use posecast_proto::fk::{forward_kinematics, skinning_matrices};
use posecast_proto::msg::AvatarId;
use posecast_proto::placement::Placement;
use posecast_proto::testing::{skeleton_bound_at_rest, skip};
use serde_json::{Value, json};
use std::path::PathBuf;
use std::process::Command as Process;

fn avatar(s: &str) -> AvatarId {
    AvatarId(s.into())
}
/// A small deterministic generator (the vectors must not change from run to run).
struct Lcg(u64);

impl Lcg {
    fn next(&mut self) -> f32 {
        self.0 = self
            .0
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        ((self.0 >> 40) as f32) / ((1u64 << 24) as f32)
    }

    fn range(&mut self, lo: f32, hi: f32) -> f32 {
        lo + (hi - lo) * self.next()
    }

    fn vec3(&mut self, lo: f32, hi: f32) -> Vec3 {
        Vec3::new(self.range(lo, hi), self.range(lo, hi), self.range(lo, hi))
    }

    fn quat(&mut self) -> Quat {
        loop {
            let q = Quat::from_xyzw(
                self.range(-1.0, 1.0),
                self.range(-1.0, 1.0),
                self.range(-1.0, 1.0),
                self.range(-1.0, 1.0),
            );
            if q.length() > 0.1 {
                return q.normalize();
            }
        }
    }
}

/// One vector: a description and a pose as the page receives them, and the world matrices
/// `posecast_proto` computes for them (`P · W_j`, column-major) and the skinning matrices
/// (`P · W_j · B_j⁻¹`).
fn fk_case(desc: &AvatarDescription, rng: &mut Lcg) -> Value {
    let skeleton = desc.to_skeleton().unwrap();
    let n = skeleton.len();
    let placement =
        Placement::try_new(rng.vec3(-5.0, 5.0).to_array(), rng.quat().to_array()).unwrap();
    let rotations: Vec<Quat> = (0..n).map(|_| rng.quat()).collect();
    let translations: Vec<Vec3> = desc
        .translated_joints
        .iter()
        .map(|_| rng.vec3(-1.0, 1.0))
        .collect();
    let scales: Vec<Vec3> = desc
        .scaled_joints
        .iter()
        .map(|_| rng.vec3(0.8, 1.25))
        .collect();
    // The frame's values where it carries them, the rest pose's elsewhere.
    let locals: Vec<Transform> = (0..n)
        .map(|j| {
            let rest = skeleton.rest()[j];
            let t = desc
                .translated_joints
                .iter()
                .position(|&k| usize::from(k) == j)
                .map_or(rest.translation, |i| translations[i]);
            let s = desc
                .scaled_joints
                .iter()
                .position(|&k| usize::from(k) == j)
                .map_or(rest.scale, |i| scales[i]);
            Transform {
                translation: t,
                rotation: rotations[j],
                scale: s,
            }
        })
        .collect();
    let mut world = vec![Mat4::IDENTITY; n];
    forward_kinematics(&skeleton, &locals, &mut world);
    let placed: Vec<Mat4> = world.iter().map(|w| placement.to_mat4() * *w).collect();
    let mut skinning = vec![Mat4::IDENTITY; n];
    skinning_matrices(&skeleton, &placed, &mut skinning);
    let placed: Vec<[f32; 16]> = placed.iter().map(Mat4::to_cols_array).collect();
    let skinning: Vec<[f32; 16]> = skinning.iter().map(Mat4::to_cols_array).collect();
    json!({
        "description": desc,
        "pose": {
            "rotations": rotations.iter().map(|q| q.to_array()).collect::<Vec<_>>(),
            "translations": translations.iter().map(|t| t.to_array()).collect::<Vec<_>>(),
            "scales": scales.iter().map(|s| s.to_array()).collect::<Vec<_>>(),
            "placement": placement,
        },
        "worlds": placed,
        "skinning": skinning,
    })
}

/// The client's forward kinematics and skinning matrices agree with `posecast_proto::fk`
/// (within f32 rounding).
#[test]
fn the_clients_forward_kinematics_and_skinning_match_proto() {
    let mut rng = Lcg(0x5eed);
    let mut cases = Vec::new();
    for i in 0..40 {
        let n = 1 + (i % 12);
        let parents: Vec<Option<usize>> = (0..n)
            .map(|j| (j > 0 && (j % 5 != 0)).then(|| (rng.next() * j as f32) as usize))
            .collect();
        let rest: Vec<Transform> = (0..n)
            .map(|_| Transform {
                translation: rng.vec3(-1.0, 1.0),
                rotation: rng.quat(),
                scale: rng.vec3(0.8, 1.25),
            })
            .collect();
        let skeleton = skeleton_bound_at_rest(parents, rest);
        let translated: Vec<bool> = (0..n).map(|_| rng.next() < 0.3).collect();
        let scaled: Vec<bool> = (0..n).map(|_| rng.next() < 0.3).collect();
        let desc = AvatarDescription::new(
            avatar(&format!("random-{i}")),
            i as u32,
            "random".into(),
            &skeleton,
            &translated,
            &scaled,
            None,
        );
        cases.push(fk_case(&desc, &mut rng));
    }
    let rig = posecast_server::builtin::rig().unwrap();
    let builtin =
        posecast_server::avatar::Avatar::new(avatar("avatar"), 1, std::sync::Arc::new(rig));
    for _ in 0..5 {
        cases.push(fk_case(&builtin.description, &mut rng));
    }

    let file: PathBuf =
        std::env::temp_dir().join(format!("posecast-fk-{}.json", std::process::id()));
    std::fs::write(&file, serde_json::to_vec(&cases).unwrap()).unwrap();
    let script = root().join("server/web/check/fk.mjs");
    let out = match Process::new("node").arg(&script).arg(&file).output() {
        Ok(out) => out,
        Err(e) => {
            skip(&format!(
                "node is not installed ({e}): the JavaScript FK is not checked"
            ));
            return;
        }
    };
    std::fs::remove_file(&file).ok();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "fk.mjs: {stdout}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let report: Value = serde_json::from_str(stdout.trim()).unwrap();
    assert_eq!(report["cases"], cases.len(), "{report}");
    println!("JavaScript FK and skinning vs posecast_proto: {report}");
}
