//! VRM (issue 18, item 6): a `.vrm` is a GLB whose humanoid bone map (VRM 0.x `VRM`, 1.0
//! `VRMC_vrm`) is the authoritative mapping. Minimal files of both versions, written here from
//! the built-in avatar's skeleton with joint names that say nothing (`n0`, `n1`, …).

// Helpers outside #[test] fns unwrap too: a failure there is a test failure.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod gltf_support;
mod rig_support;

use glam::{Mat4, Vec3};
use gltf_support::{Bin, glb, triangle};
use posecast_server::builtin::skeleton::JOINTS;
use posecast_server::import::files::{FileSet, import_set};
use posecast_server::rig::{PipelineOptions, RigView, normalise, retarget};
use serde_json::{Value, json};

/// The VRM bone of each built-in joint (`sacroiliac` has none).
fn vrm_bone(hanim: &str) -> Option<&'static str> {
    Some(match hanim {
        "humanoid_root" => "hips",
        "vl5" => "spine",
        "vt10" => "chest",
        "vt1" => "upperChest",
        "vc4" => "neck",
        "skullbase" => "head",
        "l_sternoclavicular" => "leftShoulder",
        "l_shoulder" => "leftUpperArm",
        "l_elbow" => "leftLowerArm",
        "l_wrist" => "leftHand",
        "l_hip" => "leftUpperLeg",
        "l_knee" => "leftLowerLeg",
        "l_ankle" => "leftFoot",
        "l_midtarsal" => "leftToes",
        "r_sternoclavicular" => "rightShoulder",
        "r_shoulder" => "rightUpperArm",
        "r_elbow" => "rightLowerArm",
        "r_wrist" => "rightHand",
        "r_hip" => "rightUpperLeg",
        "r_knee" => "rightLowerLeg",
        "r_ankle" => "rightFoot",
        "r_midtarsal" => "rightToes",
        _ => return None,
    })
}

/// The built-in skeleton in T-pose as glTF nodes `n0`, `n1`, … (plus a hair bone `LeftArm`
/// whose name a guesser would take for an arm), one skinned triangle, and the VRM extension
/// of `version` (0 or 1).
fn vrm(version: u8) -> Vec<u8> {
    let mut bin = Bin::default();
    let (pos, idx) = triangle(&mut bin);
    let joints = bin.u16s(&[0; 12], "VEC4");
    let weights = bin.floats(&[1.0, 0.0, 0.0, 0.0].repeat(3), "VEC4");
    let n = JOINTS.len();
    let head = |j: usize| Vec3::from(JOINTS[j].head.map(|x| x as f32));
    let mut nodes: Vec<Value> = (0..n)
        .map(|j| {
            let t = match JOINTS[j].parent {
                Some(p) => head(j) - head(p),
                None => head(j),
            };
            let children: Vec<usize> = (0..n).filter(|&c| JOINTS[c].parent == Some(j)).collect();
            let mut node = json!({"name": format!("n{j}"), "translation": t.to_array()});
            if !children.is_empty() {
                node["children"] = json!(children);
            }
            node
        })
        .collect();
    // A hair bone on the head whose name reads like an arm: the VRM map does not list it.
    let hair = n;
    nodes.push(json!({"name": "LeftArm", "translation": [0.05, 0.1, 0.0]}));
    let skull = JOINTS.iter().position(|j| j.name == "skullbase").unwrap();
    nodes[skull]["children"] = json!([hair]);
    nodes.push(json!({"name": "body", "mesh": 0, "skin": 0}));
    let mut ibm = Vec::new();
    for j in 0..n {
        ibm.extend(Mat4::from_translation(-head(j)).to_cols_array());
    }
    ibm.extend(Mat4::from_translation(-(head(skull) + Vec3::new(0.05, 0.1, 0.0))).to_cols_array());
    let ibm = bin.floats(&ibm, "MAT4");
    let bones: Vec<(usize, &str)> = (0..n)
        .filter_map(|j| vrm_bone(JOINTS[j].name).map(|b| (j, b)))
        .collect();
    let extension = if version == 0 {
        json!({"VRM": {"specVersion": "0.0", "humanoid": {"humanBones":
            bones.iter().map(|(j, b)| json!({"bone": b, "node": j, "useDefaultValues": true})).collect::<Vec<_>>()}}})
    } else {
        let mut map = serde_json::Map::new();
        for (j, b) in &bones {
            map.insert((*b).to_owned(), json!({"node": j}));
        }
        json!({"VRMC_vrm": {"specVersion": "1.0", "humanoid": {"humanBones": map}}})
    };
    let mut doc = json!({
        "asset": {"version": "2.0"},
        "extensionsUsed": [if version == 0 { "VRM" } else { "VRMC_vrm" }],
        "extensions": extension,
        "scenes": [{"nodes": [0, n + 1]}],
        "nodes": nodes,
        "skins": [{"joints": (0..=n).collect::<Vec<_>>(), "inverseBindMatrices": ibm}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": pos, "JOINTS_0": joints, "WEIGHTS_0": weights}, "indices": idx}]}]
    });
    bin.finish(&mut doc);
    glb(&doc, &bin.bytes)
}

#[test]
fn vrm_0_and_1_humanoid_bones_are_the_mapping() {
    let avatar = normalise(rig_support::builtin(), &PipelineOptions::default()).unwrap();
    for version in [0, 1] {
        let mut set = FileSet::new();
        set.insert("model.vrm", vrm(version)).unwrap();
        let asset = import_set(&set).unwrap().remove(0);
        let n = normalise(asset, &PipelineOptions::default()).unwrap();
        println!("VRM {version}: {:?}", n.steps);
        assert!(n.humanoid, "VRM {version}: {:?}", n.steps);
        for (j, def) in JOINTS.iter().enumerate() {
            let expected = vrm_bone(def.name).map(|_| def.name);
            let k = n.asset.skeleton.find(&format!("n{j}")).unwrap();
            assert_eq!(
                n.hanim[k].as_deref(),
                expected,
                "VRM {version}: joint n{j} ({})",
                def.name
            );
        }
        let hair = n.asset.skeleton.find("LeftArm").unwrap();
        assert_eq!(n.hanim[hair], None, "VRM {version}: not in the bone map");
        // The built-in avatar's walk plays on it: every mapped limb follows.
        let walk = &avatar.asset.clips[1];
        let out = retarget(RigView::from(&avatar), walk, RigView::from(&n)).unwrap();
        assert_eq!(out.joint_count(), n.asset.skeleton.len());
    }
}

#[test]
fn a_glb_without_the_extension_is_mapped_by_names_only() {
    // The same file without its VRM extension: `n0`, `n1`, … say nothing, so nothing maps.
    let bytes = vrm(1);
    let json_len = u32::from_le_bytes(bytes[12..16].try_into().unwrap()) as usize;
    let mut doc: Value = serde_json::from_slice(&bytes[20..20 + json_len]).unwrap();
    doc.as_object_mut().unwrap().remove("extensions");
    let bin_start = 20 + json_len + 8;
    let plain = glb(&doc, &bytes[bin_start..]);
    let asset = posecast_server::import::gltf::from_slice("plain.glb", &plain)
        .unwrap()
        .remove(0);
    let n = normalise(asset, &PipelineOptions::default()).unwrap();
    assert!(!n.humanoid);
}
