//! Importer notes (issue 18, item 5): what an importer skips, renames or leaves out is said,
//! per asset, in `SourceInfo::notes` (which uploads answer as `AssetInfo::notes`).

// Helpers outside #[test] fns unwrap too: a failure there is a test failure.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod gltf_support;

use gltf_support::{Bin, glb, triangle};
use posecast_rigs::import::{bvh, files, gltf};
use serde_json::json;

fn has(notes: &[String], words: &[&str]) -> bool {
    notes.iter().any(|n| words.iter().all(|w| n.contains(w)))
}

#[test]
fn gltf_notes_materials_repeated_names_and_loose_meshes() {
    let mut bin = Bin::default();
    let (pos, idx) = triangle(&mut bin);
    let joints = bin.u16s(&[0, 0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0], "VEC4");
    let weights = bin.floats(&[1.0, 0.0, 0.0, 0.0].repeat(3), "VEC4");
    let times = bin.floats(&[0.0, 1.0], "SCALAR");
    let morph = bin.floats(&[0.0, 1.0], "SCALAR");
    let mut doc = json!({
        "asset": {"version": "2.0"},
        "scenes": [{"nodes": [0, 2, 3]}],
        "nodes": [
            {"name": "bone", "children": [1]},
            {"name": "bone", "translation": [0.0, 1.0, 0.0]},
            {"name": "skinned", "mesh": 0, "skin": 0},
            {"name": "floor", "mesh": 1}
        ],
        "skins": [{"joints": [0, 1]}],
        "materials": [{"name": "steel"}],
        "meshes": [
            {"name": "body", "primitives": [{"attributes": {"POSITION": pos, "JOINTS_0": joints, "WEIGHTS_0": weights}, "indices": idx, "material": 0}],
             "weights": [0.0]},
            {"name": "floor", "primitives": [{"attributes": {"POSITION": pos}, "indices": idx}]}
        ],
        "animations": [{"channels": [{"sampler": 0, "target": {"node": 2, "path": "weights"}}],
                        "samplers": [{"input": times, "output": morph}]}]
    });
    bin.finish(&mut doc);
    let asset = gltf::from_slice("notes.glb", &glb(&doc, &bin.bytes))
        .unwrap()
        .remove(0);
    let notes = &asset.source.notes;
    println!("{notes:#?}");
    assert!(
        has(notes, &["materials not imported", "steel"]),
        "{notes:?}"
    );
    assert!(has(notes, &["repeated joint names", "bone#2"]), "{notes:?}");
    assert!(has(notes, &["hang from no joint", "floor"]), "{notes:?}");
    assert!(
        has(
            notes,
            &["1 morph weight channel(s) on nodes without morph targets ignored"]
        ),
        "{notes:?}"
    );
}

#[test]
fn an_anim_with_fewer_channels_than_the_skeleton_is_noted() {
    let skel = "balljoint root {\n offset 0 0 0\n balljoint mid {\n offset 0 1 0\n \
                balljoint tip {\n offset 0 1 0\n }\n }\n}\n";
    // 3 root translations + the root's 3 rotations: 6 of the skeleton's 12 channels.
    let channel = "channel {\n extrapolate constant constant\n keys 1 {\n 0 0 flat flat\n }\n}\n";
    let anim = format!(
        "animation {{\n range 0 1\n numchannels 6\n{}}}\n",
        channel.repeat(6)
    );
    let asset =
        files::skel_with_companions("arm.skel", skel, None, vec![("short.anim".into(), anim)])
            .unwrap();
    let notes = &asset.source.notes;
    assert!(
        has(
            notes,
            &["short.anim", "6 of the skeleton's 12 channels", "mid, tip"]
        ),
        "{notes:?}"
    );
}

#[test]
fn bvh_repeated_names_are_listed() {
    let text = "HIERARCHY\nROOT a\n{\n OFFSET 0 0 0\n CHANNELS 3 Zrotation Xrotation Yrotation\n \
                JOINT a\n {\n  OFFSET 0 1 0\n  CHANNELS 3 Zrotation Xrotation Yrotation\n  \
                End Site\n  {\n   OFFSET 0 1 0\n  }\n }\n}\nMOTION\nFrames: 1\nFrame Time: 0.1\n\
                0 0 0 0 0 0\n";
    let asset = bvh::parse("twice.bvh", text).unwrap();
    assert!(
        has(&asset.source.notes, &["repeated joint names", "\"a#2\""]),
        "{:?}",
        asset.source.notes
    );
}

/// Accessors without `bufferView` are zeros (glTF 2.0, 3.6.2.1): Ready Player Me's morph
/// targets, stripped of theirs here, import as before; a `sparse` block over a view-less
/// accessor gives its values; and a file with hundreds of real problems gets a short error.
#[test]
fn accessors_without_buffer_views_are_zeros() {
    use posecast_proto::testing::require_testdata;
    let Some(path) = require_testdata("gltf/ReadyPlayerMe/PreviewMesh.glb") else {
        return;
    };
    let bytes = std::fs::read(path).unwrap();
    let json_len = u32::from_le_bytes(bytes[12..16].try_into().unwrap()) as usize;
    let mut doc: serde_json::Value = serde_json::from_slice(&bytes[20..20 + json_len]).unwrap();
    let bin_at = 20 + json_len;
    let bin = bytes[bin_at + 8..].to_vec();
    let mut targets = Vec::new();
    for mesh in doc["meshes"].as_array().unwrap() {
        for prim in mesh["primitives"].as_array().unwrap() {
            for t in prim["targets"].as_array().into_iter().flatten() {
                for a in t.as_object().unwrap().values() {
                    targets.push(a.as_u64().unwrap() as usize);
                }
            }
        }
    }
    assert!(!targets.is_empty());
    for &a in &targets {
        let acc = doc["accessors"][a].as_object_mut().unwrap();
        acc.remove("bufferView");
        acc.remove("byteOffset");
    }
    let original = gltf::from_slice("rpm.glb", &bytes).unwrap().remove(0);
    let stripped = gltf::from_slice("rpm.glb", &glb(&doc, &bin))
        .unwrap_or_else(|e| panic!("{e}"))
        .remove(0);
    assert_eq!(original.meshes.len(), stripped.meshes.len());
    for (a, b) in original.meshes.iter().zip(&stripped.meshes) {
        assert_eq!(a.mesh.positions(), b.mesh.positions());
    }
    println!("{:?}", stripped.source.notes);
    assert!(has(
        &stripped.source.notes,
        &["20 morph targets on 4 primitives imported"]
    ));

    // POSITION as zeros plus a sparse block holding every vertex: the original positions.
    let mut bin2 = Bin::default();
    let (pos, idx) = triangle(&mut bin2);
    let joints = bin2.u16s(&[0; 12], "VEC4");
    let weights = bin2.floats(&[1.0, 0.0, 0.0, 0.0].repeat(3), "VEC4");
    let values = bin2.floats(&[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0], "VEC3");
    let indices = bin2.u16s(&[0, 1, 2], "SCALAR");
    let mut sparse_doc = json!({
        "asset": {"version": "2.0"},
        "nodes": [{"name": "bone"}, {"name": "skinned", "mesh": 0, "skin": 0}],
        "skins": [{"joints": [0]}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": pos, "JOINTS_0": joints, "WEIGHTS_0": weights}, "indices": idx}]}]
    });
    bin2.finish(&mut sparse_doc);
    let views = sparse_doc["accessors"][values]["bufferView"].clone();
    let iviews = sparse_doc["accessors"][indices]["bufferView"].clone();
    let p = &mut sparse_doc["accessors"][pos];
    p.as_object_mut().unwrap().remove("bufferView");
    p["sparse"] = json!({"count": 3, "indices": {"bufferView": iviews, "componentType": 5123},
                         "values": {"bufferView": views}});
    let a = gltf::from_slice("sparse.glb", &glb(&sparse_doc, &bin2.bytes))
        .unwrap()
        .remove(0);
    let want = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]];
    let got: Vec<[f32; 3]> = a.meshes[0]
        .mesh
        .positions()
        .iter()
        .map(|v| v.to_array())
        .collect();
    assert_eq!(got, want);
    // Without the sparse block: zeros.
    sparse_doc["accessors"][pos]
        .as_object_mut()
        .unwrap()
        .remove("sparse");
    let z = gltf::from_slice("zeros.glb", &glb(&sparse_doc, &bin2.bytes))
        .unwrap()
        .remove(0);
    assert!(
        z.meshes[0]
            .mesh
            .positions()
            .iter()
            .all(|v| *v == glam::Vec3::ZERO)
    );

    // 2000 accessors naming a buffer view that does not exist: a few lines, with the count.
    for _ in 0..2000 {
        doc["accessors"].as_array_mut().unwrap().push(
            json!({"bufferView": 99999, "componentType": 5126, "count": 1, "type": "SCALAR"}),
        );
    }
    let e = gltf::from_slice("broken.glb", &glb(&doc, &bin))
        .unwrap_err()
        .to_string();
    println!("{} bytes: {e}", e.len());
    assert!(e.len() < 600, "{} bytes", e.len());
    assert!(e.contains("2000 in all"), "{e}");
}

#[test]
fn joints_without_influence_and_foreign_channels_are_counted() {
    let mut bin = Bin::default();
    let (pos, idx) = triangle(&mut bin);
    let joints = bin.u16s(&[0; 12], "VEC4");
    let weights = bin.floats(&[1.0, 0.0, 0.0, 0.0].repeat(3), "VEC4");
    let times = bin.floats(&[0.0, 1.0], "SCALAR");
    let moves = bin.floats(&[0.0, 0.0, 0.0, 0.0, 1.0, 0.0], "VEC3");
    let mut doc = json!({
        "asset": {"version": "2.0"},
        "nodes": [
            {"name": "root", "children": [1]},
            {"name": "tip", "translation": [0.0, 1.0, 0.0]},
            {"name": "skinned", "mesh": 0, "skin": 0},
            {"name": "lamp"}
        ],
        "skins": [{"joints": [0, 1]}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": pos, "JOINTS_0": joints, "WEIGHTS_0": weights}, "indices": idx}]}],
        "animations": [{"channels": [{"sampler": 0, "target": {"node": 3, "path": "translation"}},
                                     {"sampler": 0, "target": {"node": 1, "path": "translation"}}],
                        "samplers": [{"input": times, "output": moves}]}]
    });
    bin.finish(&mut doc);
    let asset = gltf::from_slice("idle.glb", &glb(&doc, &bin.bytes))
        .unwrap()
        .remove(0);
    let notes = &asset.source.notes;
    println!("{notes:#?}");
    assert!(
        has(notes, &["1 of 2 joints move no vertex", "tip"]),
        "{notes:?}"
    );
    assert!(
        has(notes, &["1 channel(s) on nodes outside this rig ignored"]),
        "{notes:?}"
    );
}
