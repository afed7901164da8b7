//! VRM (issue 18, item 6): a `.vrm` is a GLB whose humanoid bone map (VRM 0.x `VRM`, 1.0
//! `VRMC_vrm`) is the authoritative mapping. Minimal files of both versions, written here from
//! the built-in avatar's skeleton with joint names that say nothing (`n0`, `n1`, …).

// Helpers outside #[test] fns unwrap too: a failure there is a test failure.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod gltf_support;
mod rig_support;

use gltf_support::{builtin_skeleton_glb, glb, vrm_bone};
use posecast_rigs::builtin::skeleton::JOINTS;
use posecast_rigs::import::files::{FileSet, import_set};
use posecast_rigs::rig::{PipelineOptions, RigView, normalise, retarget};
use serde_json::{Value, json};

/// The built-in skeleton in T-pose as glTF nodes `n0`, `n1`, … (plus a hair bone `LeftArm`
/// whose name a guesser would take for an arm), one skinned triangle, and the VRM extension
/// of `version` (0 or 1).
fn vrm(version: u8) -> Vec<u8> {
    let skull = JOINTS.iter().position(|j| j.name == "skullbase").unwrap();
    let bones: Vec<(usize, &str)> = (0..JOINTS.len())
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
    builtin_skeleton_glb(
        1.0,
        |j| format!("n{j}"),
        &[("LeftArm", skull, [0.05, 0.1, 0.0])],
        Some(extension),
    )
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
    let asset = posecast_rigs::import::gltf::from_slice("plain.glb", &plain)
        .unwrap()
        .remove(0);
    let n = normalise(asset, &PipelineOptions::default()).unwrap();
    assert!(!n.humanoid);
}
