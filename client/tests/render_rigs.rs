//! GPU compute skinning against the CPU reference `posecast_proto::skinning::skin_cpu` on every
//! skinned rig of ../shared/testdata and the built-in avatar, at several times of each clip;
//! the client's `.glb` mesh reader against the server's importer; and a golden image of the
//! built-in avatar. Bless the golden with `POSECAST_BLESS=1 cargo test -p posecast-client
//! --test render_rigs`.
// Helpers outside #[test] functions are test code too.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod render_support;

use posecast_client::render::glb_mesh::GlbMesh;
use posecast_client::render::image::check_golden;
use posecast_client::render::{Offscreen, Renderer, RendererOptions, Tolerance};
use posecast_proto::Transform;
use posecast_server::asset::Asset;
use posecast_server::builtin::AVATAR_GLB;
use posecast_server::clip::Clip;
use posecast_server::import::{self, cse169, skel, skin};
use render_support::{check_compute_matches_cpu, golden, gpu};
use std::path::{Path, PathBuf};

fn testdata(rel: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../shared/testdata")
        .join(rel)
}

/// The rest pose and poses at `k/4` of each clip's range (start, quarter, half, three
/// quarters, end); an asset without clips gets three poses bending every joint instead.
fn clip_poses(asset: &Asset, clips: &[&Clip]) -> Vec<Vec<Transform>> {
    let rest = asset.skeleton.rest();
    let mut poses = vec![rest.to_vec()];
    for clip in clips {
        for k in 0..=4 {
            let t = clip.start() + clip.duration() * k as f32 / 4.0;
            let mut out = rest.to_vec();
            clip.sample(t, rest, &mut out);
            poses.push(out);
        }
    }
    if clips.is_empty() {
        for k in 1..=3 {
            let bend = glam::Quat::from_euler(glam::EulerRot::XYZ, 0.4 * k as f32, 0.25, -0.3);
            poses.push(
                rest.iter()
                    .map(|r| Transform {
                        rotation: bend * r.rotation,
                        ..*r
                    })
                    .collect(),
            );
        }
    }
    poses
}

fn check_asset(label: &str, asset: &Asset) {
    let Some(gpu) = gpu() else { return };
    assert!(!asset.meshes.is_empty(), "{label}: no meshes");
    let clips: Vec<&Clip> = asset.clips.iter().collect();
    let poses = clip_poses(asset, &clips);
    for m in &asset.meshes {
        let agreement = check_compute_matches_cpu(gpu, &asset.skeleton, &m.mesh, &poses)
            .unwrap_or_else(|e| panic!("{label} / {}: {e}", m.name));
        eprintln!(
            "{label} / {}: {} joints, {} poses, {agreement:?}",
            m.name,
            asset.skeleton.len(),
            poses.len()
        );
    }
}

fn load(rel: &str) -> Vec<Asset> {
    import::load_path(&testdata(rel)).unwrap_or_else(|e| panic!("{rel}: {e}"))
}

#[test]
fn rigged_simple() {
    for a in load("gltf/RiggedSimple/glTF-Binary/RiggedSimple.glb") {
        check_asset("RiggedSimple", &a);
    }
}

#[test]
fn rigged_figure() {
    for a in load("gltf/RiggedFigure/glTF-Binary/RiggedFigure.glb") {
        check_asset("RiggedFigure", &a);
    }
}

#[test]
fn cesium_man() {
    for a in load("gltf/CesiumMan/glTF-Binary/CesiumMan.glb") {
        check_asset("CesiumMan", &a);
    }
}

#[test]
fn simple_skin() {
    for a in load("gltf/SimpleSkin/glTF/SimpleSkin.gltf") {
        check_asset("SimpleSkin", &a);
    }
}

/// 84 skins share one mesh, 21 on each of 4 skeletons: one rig per skeleton. The first three
/// instances and the last of the first and last rigs cover the shallow and deep ends.
#[test]
fn recursive_skeletons() {
    let assets = load("gltf/RecursiveSkeletons/glTF-Binary/RecursiveSkeletons.glb");
    assert_eq!(assets.len(), 4, "{} assets", assets.len());
    for a in [&assets[0], &assets[3]] {
        assert_eq!(a.meshes.len(), 21, "{}", a.name);
        let mut picked = a.clone();
        picked.meshes = [0, 1, 2, 20].iter().map(|&i| a.meshes[i].clone()).collect();
        check_asset(&a.name, &picked);
    }
}

#[test]
fn wasp() {
    for a in load("cse169/wasp.skel") {
        check_asset("wasp", &a);
    }
}

/// `tube.skel` goes with `tube_smooth.skin` (different stems, so assembled by hand).
#[test]
fn tube() {
    let read = |name: &str| std::fs::read_to_string(testdata(&format!("cse169/{name}"))).unwrap();
    let skel = skel::parse("tube.skel", &read("tube.skel")).unwrap();
    let skin = skin::parse(
        "tube_smooth.skin",
        &read("tube_smooth.skin"),
        &skel.skeleton,
    )
    .unwrap();
    let asset = cse169::assemble("tube", skel, Some(skin), Vec::new()).unwrap();
    check_asset("tube", &asset);
}

#[test]
fn builtin_avatar() {
    let rig = posecast_server::builtin::rig().unwrap();
    let clips: Vec<&Clip> = rig.clips.iter().map(|c| &**c).collect();
    assert!(clips.len() >= 3);
    let Some(gpu) = gpu() else { return };
    let poses = clip_poses(&rig.asset, &clips);
    for m in &rig.asset.meshes {
        let agreement = check_compute_matches_cpu(gpu, rig.skeleton(), &m.mesh, &poses).unwrap();
        eprintln!("built-in / {}: {agreement:?}", m.name);
    }
}

/// The client's reader gives the importer's mesh (merged over primitives, joints by name) for
/// every single-skin `.glb` here: same positions, triangles and influences.
#[test]
fn glb_reader_matches_the_importer() {
    let files: [(&str, Vec<u8>); 4] = [
        ("built-in", AVATAR_GLB.to_vec()),
        (
            "RiggedSimple",
            std::fs::read(testdata("gltf/RiggedSimple/glTF-Binary/RiggedSimple.glb")).unwrap(),
        ),
        (
            "RiggedFigure",
            std::fs::read(testdata("gltf/RiggedFigure/glTF-Binary/RiggedFigure.glb")).unwrap(),
        ),
        (
            "CesiumMan",
            std::fs::read(testdata("gltf/CesiumMan/glTF-Binary/CesiumMan.glb")).unwrap(),
        ),
    ];
    for (label, bytes) in files {
        let assets = import::gltf::from_slice("x.glb", &bytes).unwrap();
        let asset = &assets[0];
        let ours = GlbMesh::from_slice(&bytes)
            .unwrap()
            .for_joints(asset.skeleton.names())
            .unwrap_or_else(|e| panic!("{label}: {e}"));
        let mut positions = Vec::new();
        let mut indices = Vec::new();
        let mut influences = Vec::new();
        for m in &asset.meshes {
            let base = positions.len() as u32;
            positions.extend_from_slice(m.mesh.positions());
            indices.extend(m.mesh.indices().iter().map(|i| i + base));
            let k = m.mesh.influences();
            for (j, w) in m.mesh.joints().chunks(k).zip(m.mesh.weights().chunks(k)) {
                influences.push(sorted_influences(j, w));
            }
        }
        assert_eq!(ours.positions(), &positions[..], "{label}: positions");
        assert_eq!(ours.indices(), &indices[..], "{label}: indices");
        let mine: Vec<_> = ours
            .joints()
            .chunks(4)
            .zip(ours.weights().chunks(4))
            .map(|(j, w)| sorted_influences(j, w))
            .collect();
        assert_eq!(mine.len(), influences.len(), "{label}");
        for (v, (a, b)) in mine.iter().zip(&influences).enumerate() {
            assert_eq!(a.len(), b.len(), "{label} vertex {v}: {a:?} vs {b:?}");
            for ((ja, wa), (jb, wb)) in a.iter().zip(b) {
                assert!(
                    ja == jb && (wa - wb).abs() < 1e-6,
                    "{label} vertex {v}: {a:?} vs {b:?}"
                );
            }
        }
        eprintln!("{label}: {} vertices agree", mine.len());
    }
}

/// Non-zero (joint, weight) pairs, by joint.
fn sorted_influences(joints: &[u16], weights: &[f32]) -> Vec<(u16, f32)> {
    let mut v: Vec<(u16, f32)> = joints
        .iter()
        .zip(weights)
        .filter(|(_, w)| **w > 0.0)
        .map(|(&j, &w)| (j, w))
        .collect();
    v.sort_by_key(|p| p.0);
    v
}

/// Same limits and reasons as `render_golden.rs`'s figure: the golden was made on lavapipe;
/// other GPUs round lighting, sRGB encoding and the grid's anti-aliasing derivatives their own
/// way, a few 8-bit steps on most pixels (mean limit 1 step), and pixels whose centre lies
/// within sub-pixel precision of a silhouette edge may flip (0.4 % may differ by > 32 steps).
const ACROSS_GPUS: Tolerance = Tolerance {
    mean: 1.0,
    outlier_threshold: 32,
    outlier_fraction: 0.004,
};

/// The built-in avatar, mesh read by the client's `.glb` reader, posed by the importer's `walk`
/// clip at 0.25 s, auto-framed, with the ground grid.
#[test]
fn builtin_avatar_walk_matches_golden() {
    let Some(gpu) = gpu() else { return };
    let rig = posecast_server::builtin::rig().unwrap();
    let skeleton = rig.skeleton();
    let mesh = GlbMesh::from_slice(AVATAR_GLB)
        .unwrap()
        .for_joints(skeleton.names())
        .unwrap();
    let walk = rig
        .clip("walk")
        .expect("the built-in avatar has a walk clip");
    let mut pose = skeleton.rest().to_vec();
    walk.sample(walk.start() + 0.25, skeleton.rest(), &mut pose);
    let (width, height) = (320, 240);
    let target = Offscreen::new(gpu, width, height).unwrap();
    let mut renderer = Renderer::new(
        gpu,
        Offscreen::FORMAT,
        width,
        height,
        RendererOptions::default(),
    )
    .unwrap();
    let handle = renderer.add_avatar(skeleton, &mesh).unwrap();
    renderer.set_pose(handle, &pose).unwrap();
    let image = target.render(&mut renderer).unwrap();
    check_golden(&image, &golden("avatar-walk-0.25.png"), &ACROSS_GPUS).unwrap();
}
