//! The client's `.glb` reader on what the server's mesh endpoint serves
//! (`posecast_server::export::mesh_glb`, `GET /api/assets/{name}/mesh.glb`): for the built-in
//! avatar and every skinned rig of ../shared/testdata, normalised as the server serves them,
//! the mesh the client gets in description joint order has the rig's positions, triangles,
//! normals and influences (four per vertex, the heaviest, renormalised).

#![allow(clippy::unwrap_used, clippy::expect_used)]

use posecast_client::render::glb_mesh::GlbMesh;
use posecast_proto::testing::require_testdata;
use posecast_server::asset::Asset;
use posecast_server::builtin::AVATAR_GLB;
use posecast_server::export::mesh_glb;
use posecast_server::import;
use posecast_server::rig::{PipelineOptions, normalise};

fn normalised(asset: Asset) -> Asset {
    normalise(asset, &PipelineOptions::default()).unwrap().asset
}

fn rigs() -> Vec<Asset> {
    let mut rigs = vec![
        import::gltf::from_slice("avatar.glb", AVATAR_GLB)
            .unwrap()
            .remove(0),
    ];
    for rel in [
        "gltf/CesiumMan/glTF-Binary/CesiumMan.glb",
        "gltf/RiggedFigure/glTF-Binary/RiggedFigure.glb",
        "gltf/RiggedSimple/glTF-Binary/RiggedSimple.glb",
        "gltf/SimpleSkin/glTF/SimpleSkin.gltf",
        "cse169/wasp.skel",
    ] {
        if let Some(path) = require_testdata(rel) {
            rigs.extend(import::load_path(&path).unwrap());
        }
    }
    rigs.into_iter().map(normalised).collect()
}

/// A vertex's influences with weight, by joint.
fn influences(joints: &[u16], weights: &[f32]) -> Vec<(u16, f32)> {
    let mut v: Vec<(u16, f32)> = joints
        .iter()
        .zip(weights)
        .filter(|(_, w)| **w > 0.0)
        .map(|(&j, &w)| (j, w))
        .collect();
    v.sort_by_key(|p| p.0);
    v
}

#[test]
fn the_client_reads_the_mesh_endpoint_as_the_rig_mesh() {
    for rig in rigs() {
        let name = &rig.name;
        let bytes = mesh_glb(&rig.skeleton, &rig.meshes).unwrap();
        let mesh = GlbMesh::from_slice(&bytes)
            .unwrap()
            .for_joints(rig.skeleton.names())
            .unwrap_or_else(|e| panic!("{name}: {e}"));
        let (mut positions, mut normals, mut indices, mut want) = (vec![], vec![], vec![], vec![]);
        for m in &rig.meshes {
            let m = m.mesh.with_influences(4);
            let base = positions.len() as u32;
            positions.extend_from_slice(m.positions());
            normals.extend_from_slice(m.normals());
            indices.extend(m.indices().iter().map(|i| i + base));
            for (j, w) in m.joints().chunks(4).zip(m.weights().chunks(4)) {
                want.push(influences(j, w));
            }
        }
        assert!(mesh.positions() == positions, "{name}: positions differ");
        assert!(mesh.indices() == indices, "{name}: indices differ");
        assert_eq!(mesh.normals().len(), normals.len(), "{name}");
        for (v, (a, b)) in mesh.normals().iter().zip(&normals).enumerate() {
            // The client's mesh renormalises: equal to rounding.
            assert!(a.abs_diff_eq(*b, 1e-6), "{name}: normal {v}: {a} vs {b}");
        }
        let got: Vec<_> = mesh
            .joints()
            .chunks(4)
            .zip(mesh.weights().chunks(4))
            .map(|(j, w)| influences(j, w))
            .collect();
        assert_eq!(got.len(), want.len(), "{name}");
        for (v, (a, b)) in got.iter().zip(&want).enumerate() {
            assert_eq!(a.len(), b.len(), "{name}: vertex {v}");
            for ((ja, wa), (jb, wb)) in a.iter().zip(b) {
                assert_eq!(ja, jb, "{name}: vertex {v}");
                // The client renormalises weights: equal to rounding.
                assert!((wa - wb).abs() < 1e-6, "{name}: vertex {v}");
            }
        }
        eprintln!(
            "{name}: {} vertices, {} bytes",
            positions.len(),
            bytes.len()
        );
    }
}
