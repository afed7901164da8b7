//! Importer notes (issue 18, item 5): what an importer skips, renames or leaves out is said,
//! per asset, in `SourceInfo::notes` (which uploads answer as `AssetInfo::notes`).

// Helpers outside #[test] fns unwrap too: a failure there is a test failure.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod gltf_support;

use gltf_support::{Bin, glb, triangle};
use posecast_server::import::{bvh, files, gltf};
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
        has(notes, &["1 morph target weight channel(s) skipped"]),
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
