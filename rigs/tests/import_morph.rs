//! glTF morph targets (issue 30, goal 1): dense and sparse accessors, normals, names from
//! `mesh.extras.targetNames` (else `target<k>`), and malformed targets refused with an error
//! naming the accessor. The values are derived by hand from the files written here; the
//! Ready Player Me avatar is checked against the file in `import_gltf.rs`.

#![allow(clippy::unwrap_used, clippy::expect_used)]

mod gltf_support;

use glam::Vec3;
use gltf_support::{Bin, glb, triangle};
use posecast_rigs::import::gltf;
use serde_json::{Value, json};

/// One skinned triangle with two targets: `open` dense (every vertex +0.1 z, normals given) and
/// `smile` sparse over a view-less accessor (only vertex 2 moves, by (0.5, 0, 0)).
fn file(names: Option<Value>) -> (Value, Vec<u8>) {
    let mut bin = Bin::default();
    let (pos, idx) = triangle(&mut bin);
    let joints = bin.u16s(&[0; 12], "VEC4");
    let weights = bin.floats(&[1.0, 0.0, 0.0, 0.0].repeat(3), "VEC4");
    let open = bin.floats(&[0.0, 0.0, 0.1].repeat(3), "VEC3");
    let open_n = bin.floats(&[0.0, 0.5, 0.0].repeat(3), "VEC3");
    let values = bin.floats(&[0.5, 0.0, 0.0], "VEC3");
    let indices = bin.u16s(&[2], "SCALAR");
    let smile = bin.floats(&[0.0; 9], "VEC3");
    let mut mesh = json!({"primitives": [{
        "attributes": {"POSITION": pos, "JOINTS_0": joints, "WEIGHTS_0": weights},
        "indices": idx,
        "targets": [{"POSITION": open, "NORMAL": open_n}, {"POSITION": smile}]
    }]});
    if let Some(names) = names {
        mesh["extras"] = json!({ "targetNames": names });
    }
    let mut doc = json!({
        "asset": {"version": "2.0"},
        "nodes": [{"name": "bone"}, {"name": "face", "mesh": 0, "skin": 0}],
        "skins": [{"joints": [0]}],
        "meshes": [mesh]
    });
    bin.finish(&mut doc);
    let view_values = doc["accessors"][values]["bufferView"].clone();
    let view_indices = doc["accessors"][indices]["bufferView"].clone();
    let s = &mut doc["accessors"][smile];
    s.as_object_mut().unwrap().remove("bufferView");
    s["sparse"] = json!({"count": 1,
        "indices": {"bufferView": view_indices, "componentType": 5123},
        "values": {"bufferView": view_values}});
    (doc, bin.bytes)
}

#[test]
fn dense_and_sparse_targets_import_with_their_names() {
    let (doc, bin) = file(Some(json!(["open", "smile"])));
    let a = gltf::from_slice("face.glb", &glb(&doc, &bin))
        .unwrap()
        .remove(0);
    let t = a.meshes[0].mesh.targets();
    assert_eq!(t.len(), 2);
    assert_eq!((t[0].name.as_str(), t[1].name.as_str()), ("open", "smile"));
    assert_eq!(t[0].positions, vec![Vec3::new(0.0, 0.0, 0.1); 3]);
    assert_eq!(t[0].normals, vec![Vec3::new(0.0, 0.5, 0.0); 3]);
    assert_eq!(
        t[1].positions,
        [Vec3::ZERO, Vec3::ZERO, Vec3::new(0.5, 0.0, 0.0)]
    );
    assert!(t[1].normals.is_empty());
    let notes = &a.source.notes;
    assert!(
        notes
            .iter()
            .any(|n| n.contains("2 morph targets on 1 primitives imported")),
        "{notes:?}"
    );
}

#[test]
fn unnamed_targets_are_numbered() {
    for names in [None, Some(json!(["open"])), Some(json!("not a list"))] {
        let (doc, bin) = file(names.clone());
        let a = gltf::from_slice("face.glb", &glb(&doc, &bin))
            .unwrap()
            .remove(0);
        let got: Vec<&str> = a.meshes[0]
            .mesh
            .targets()
            .iter()
            .map(|t| t.name.as_str())
            .collect();
        let want = if names == Some(json!(["open"])) {
            ["open", "target1"]
        } else {
            ["target0", "target1"]
        };
        assert_eq!(got, want, "{names:?}");
    }
}

#[test]
fn a_target_of_the_wrong_length_is_refused_with_its_accessor() {
    let (mut doc, mut bin) = file(None);
    // A fourth displacement on a three-vertex primitive.
    let open = doc["meshes"][0]["primitives"][0]["targets"][0]["POSITION"]
        .as_u64()
        .unwrap() as usize;
    let at = bin.len();
    bin.extend([0u8; 48]);
    let views = doc["bufferViews"].as_array_mut().unwrap();
    views.push(json!({"buffer": 0, "byteOffset": at, "byteLength": 48}));
    let view = views.len() - 1;
    doc["buffers"][0]["byteLength"] = json!(bin.len());
    doc["accessors"][open]["bufferView"] = json!(view);
    doc["accessors"][open]["count"] = json!(4);
    let e = gltf::from_slice("face.glb", &glb(&doc, &bin))
        .unwrap_err()
        .to_string();
    assert!(e.contains(&format!("accessor {open}")), "{e}");
    assert!(e.contains("morph target 0"), "{e}");
}

/// A mesh whose node scales it by 2, hanging from a joint (imported rigidly): position
/// displacements scale with it, normal displacements keep their size against the unit normals
/// they are added to (`N·Δn / |N·n|`, the direction `N·(n + Δn)` points).
#[test]
fn a_scaled_mesh_keeps_its_targets_in_proportion() {
    let mut bin = Bin::default();
    let (pos, idx) = triangle(&mut bin);
    let joints = bin.u16s(&[0; 12], "VEC4");
    let weights = bin.floats(&[1.0, 0.0, 0.0, 0.0].repeat(3), "VEC4");
    let (face_pos, face_idx) = triangle(&mut bin);
    let normals = bin.floats(&[0.0, 0.0, 1.0].repeat(3), "VEC3");
    let open = bin.floats(&[0.0, 0.0, 0.1].repeat(3), "VEC3");
    let open_n = bin.floats(&[0.0, 0.5, 0.0].repeat(3), "VEC3");
    let mut doc = json!({
        "asset": {"version": "2.0"},
        "nodes": [
            {"name": "bone", "children": [2]},
            {"name": "body", "mesh": 1, "skin": 0},
            {"name": "face", "mesh": 0, "scale": [2.0, 2.0, 2.0]}
        ],
        "skins": [{"joints": [0]}],
        "meshes": [
            {"name": "face", "extras": {"targetNames": ["open"]}, "primitives": [{
                "attributes": {"POSITION": face_pos, "NORMAL": normals}, "indices": face_idx,
                "targets": [{"POSITION": open, "NORMAL": open_n}]}]},
            {"name": "body", "primitives": [{
                "attributes": {"POSITION": pos, "JOINTS_0": joints, "WEIGHTS_0": weights},
                "indices": idx}]}
        ]
    });
    bin.finish(&mut doc);
    let a = gltf::from_slice("scaled.glb", &glb(&doc, &bin.bytes))
        .unwrap()
        .remove(0);
    let face = a
        .meshes
        .iter()
        .find(|m| m.name.starts_with("face"))
        .unwrap_or_else(|| panic!("{:?}", a.meshes.iter().map(|m| &m.name).collect::<Vec<_>>()));
    let t = &face.mesh.targets()[0];
    for (d, dn) in t.positions.iter().zip(&t.normals) {
        assert!(d.abs_diff_eq(Vec3::new(0.0, 0.0, 0.2), 1e-6), "{d}");
        assert!(dn.abs_diff_eq(Vec3::new(0.0, 0.5, 0.0), 1e-6), "{dn}");
    }
    assert!(face.mesh.normals()[0].abs_diff_eq(Vec3::Z, 1e-6));
}

/// The triangle with two `weights` animations of its mesh node: `talk` LINEAR over three keys
/// (output key by key: open, smile), `wink` CUBICSPLINE (in-tangents, values, out-tangents of
/// both targets per key). They import as one morph track per target, named after it; the
/// weights at and between keys are the ones derived by hand; the clip lasts the keys' range.
#[test]
fn weight_animations_import_as_morph_tracks() {
    let (mut doc, bin_bytes) = file(Some(json!(["open", "smile"])));
    let mut bin = gltf_support::Bin::from_document(&doc, bin_bytes);
    let times = bin.floats(&[0.0, 1.0, 2.0], "SCALAR");
    let linear = bin.floats(&[0.0, 0.0, 1.0, 0.5, 0.0, 1.0], "SCALAR");
    let cubic_times = bin.floats(&[0.0, 2.0], "SCALAR");
    // Key 0: in (0, 0), value (0.2, 0.4), out (0.3, 0); key 1: in (0, 0), value (1, 0), out (0, 0).
    let cubic = bin.floats(
        &[0.0, 0.0, 0.2, 0.4, 0.3, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0],
        "SCALAR",
    );
    doc["animations"] = json!([
        {"name": "talk",
         "samplers": [{"input": times, "output": linear, "interpolation": "LINEAR"}],
         "channels": [{"sampler": 0, "target": {"node": 1, "path": "weights"}}]},
        {"name": "wink",
         "samplers": [{"input": cubic_times, "output": cubic, "interpolation": "CUBICSPLINE"}],
         "channels": [{"sampler": 0, "target": {"node": 1, "path": "weights"}}]}
    ]);
    bin.finish(&mut doc);
    let a = gltf::from_slice("face.glb", &glb(&doc, &bin.bytes))
        .unwrap()
        .remove(0);
    let talk = a.clips.iter().find(|c| c.name() == "talk").unwrap();
    assert_eq!((talk.start(), talk.end()), (0.0, 2.0));
    let m = talk.morphs();
    assert_eq!(m.len(), 2);
    assert_eq!(
        (m[0].channel.as_str(), m[1].channel.as_str()),
        ("open", "smile")
    );
    for (t, open, smile) in [
        (0.0, 0.0, 0.0),
        (0.5, 0.5, 0.25),
        (1.0, 1.0, 0.5),
        (1.5, 0.5, 0.75),
    ] {
        assert!(
            (m[0].sample(t) - open).abs() < 1e-6,
            "open at {t}: {}",
            m[0].sample(t)
        );
        assert!(
            (m[1].sample(t) - smile).abs() < 1e-6,
            "smile at {t}: {}",
            m[1].sample(t)
        );
    }
    let wink = a.clips.iter().find(|c| c.name() == "wink").unwrap();
    let m = wink.morphs();
    // Hermite at u = 1/2 over dt = 2: h00 = h01 = 1/2, h10 = 1/8, h11 = −1/8 (tangents × dt).
    // open: 0.5·0.2 + 0.125·2·0.3 + 0.5·1 = 0.675; smile: 0.5·0.4 = 0.2.
    assert!(
        (m[0].sample(1.0) - 0.675).abs() < 1e-6,
        "{}",
        m[0].sample(1.0)
    );
    assert!(
        (m[1].sample(1.0) - 0.2).abs() < 1e-6,
        "{}",
        m[1].sample(1.0)
    );
    let notes = &a.source.notes;
    assert!(
        notes
            .iter()
            .any(|n| n.contains("(talk): 2 morph channel(s) animated")),
        "{notes:?}"
    );
}
