//! VRM animation (issue 33, goal 7): a `.vrma` (`VRMC_vrm_animation` 1.0, no skin) imports as a
//! skeleton-only humanoid rig whose clips play on any humanoid through retargeting.
//!
//! The fixture is written here: the built-in avatar's skeleton in its T-pose as plain nodes
//! `bone0`, `bone1`, … (names that say nothing) with a rest rotation on every node (VRM 1.0
//! allows them; the translations compensate, so the world T-pose is the built-in's), under a
//! rotated `Root` node; a `jaw` bone, a `hair` node, an expression and a lookAt node; one
//! animation that turns the left upper arm by a known world rotation `Q` and moves the hips by
//! a known `Δ` metres. References: the file's own figures (its bone map, its T-pose positions)
//! and the hand-derived motion — the upper arm's direction `Q · d₀`, the hips' displacement
//! `k · Δ` with `k` the ratio of hip heights.

// Helpers outside #[test] fns unwrap too: a failure there is a test failure.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod gltf_support;
mod rig_support;

use glam::{Mat4, Quat, Vec3};
use gltf_support::{Bin, glb, glb_of_text, vrm_bone};
use posecast_proto::fk::forward_kinematics;
use posecast_rigs::builtin::skeleton::JOINTS;
use posecast_rigs::clip::Clip;
use posecast_rigs::import::ImportError;
use posecast_rigs::import::files::{FileSet, import_set};
use posecast_rigs::import::gltf::vrma::VrmaError;
use posecast_rigs::rig::{Normalised, PipelineOptions, RigView, normalise, retarget};
use serde_json::{Value, json};

fn joint_index(name: &str) -> usize {
    JOINTS.iter().position(|j| j.name == name).unwrap()
}

fn head(j: usize) -> Vec3 {
    Vec3::from(JOINTS[j].head.map(|x| x as f32))
}

/// The upper arm's world turn in the clip, at its end (t = 1 s).
fn q_arm() -> Quat {
    Quat::from_axis_angle(Vec3::new(0.2, 0.3, 1.0).normalize(), 70f32.to_radians())
}

/// The hips' move in the clip, metres, at its end.
const DELTA: Vec3 = Vec3::new(0.12, -0.05, 0.3);

/// Node indices after the built-in joints.
struct Extra {
    root: usize,
    jaw: usize,
    hair: usize,
    aa: usize,
    look: usize,
}

fn extra() -> Extra {
    let n = JOINTS.len();
    Extra {
        root: n,
        jaw: n + 1,
        hair: n + 2,
        aa: n + 3,
        look: n + 4,
    }
}

/// The fixture's glTF JSON and binary buffer (see the module docs).
fn vrma_doc() -> (Value, Vec<u8>) {
    let n = JOINTS.len();
    let x = extra();
    // World rest rotations: one per node, none trivial; Root's turns the frame the hips hang in.
    let world_rot = |j: usize| {
        Quat::from_euler(
            glam::EulerRot::XYZ,
            0.4 * (j as f32 * 1.3).sin(),
            0.5 * (j as f32 * 0.7).cos(),
            0.3 * (j as f32 * 2.1).sin(),
        )
    };
    let root_rot = Quat::from_axis_angle(Vec3::new(1.0, 2.0, 0.5).normalize(), 0.8);
    let parent_world = |j: usize| -> (Quat, Vec3) {
        match JOINTS[j].parent {
            Some(p) => (world_rot(p), head(p)),
            None => (root_rot, Vec3::ZERO),
        }
    };
    let local = |j: usize| -> (Quat, Vec3) {
        let (pr, pp) = parent_world(j);
        (
            (pr.inverse() * world_rot(j)).normalize(),
            pr.inverse() * (head(j) - pp),
        )
    };
    let skull = joint_index("skullbase");
    let mut nodes: Vec<Value> = (0..n)
        .map(|j| {
            let (r, t) = local(j);
            json!({"name": format!("bone{j}"), "rotation": r.to_array(), "translation": t.to_array()})
        })
        .collect();
    for (i, node) in nodes.iter_mut().enumerate() {
        let mut children: Vec<usize> = (0..n).filter(|&c| JOINTS[c].parent == Some(i)).collect();
        if i == skull {
            children.extend([x.jaw, x.hair]);
        }
        if !children.is_empty() {
            node["children"] = json!(children);
        }
    }
    let skull_inv = world_rot(skull).inverse();
    nodes.push(json!({"name": "Root", "rotation": root_rot.to_array(), "children": [0]}));
    nodes.push(
        json!({"name": "jaw", "translation": (skull_inv * Vec3::new(0.0, -0.03, 0.05)).to_array()}),
    );
    nodes.push(json!({"name": "hair", "translation": (skull_inv * Vec3::new(0.0, 0.12, -0.05)).to_array()}));
    nodes.push(json!({"name": "Expression_aa"}));
    nodes.push(json!({"name": "LookAt", "translation": [0.0, 1.5, 1.0]}));

    let mut bin = Bin::default();
    let times = bin.floats(&[0.0, 1.0], "SCALAR");
    let arm = joint_index("l_shoulder");
    let (arm_rest, _) = local(arm);
    let arm_parent = world_rot(JOINTS[arm].parent.unwrap());
    // G(t=1) = Q · W_arm, so L(t=1) = W_parent⁻¹ · Q · W_arm.
    let arm_end = (arm_parent.inverse() * q_arm() * world_rot(arm)).normalize();
    let arm_keys = bin.floats(&[arm_rest.to_array(), arm_end.to_array()].concat(), "VEC4");
    let (_, hips_rest) = local(0);
    let hips_end = hips_rest + root_rot.inverse() * DELTA;
    let hips_keys = bin.floats(
        &[hips_rest.to_array(), hips_end.to_array()].concat(),
        "VEC3",
    );
    let weight = bin.floats(&[0.0, 0.0, 0.0, 1.0, 0.0, 0.0], "VEC3");
    let gaze = bin.floats(&[0.0, 1.5, 1.0, 0.5, 1.5, 1.0], "VEC3");
    let jaw = bin.floats(
        &[
            Quat::IDENTITY.to_array(),
            Quat::from_rotation_x(0.3).to_array(),
        ]
        .concat(),
        "VEC4",
    );
    let samplers: Vec<Value> = [arm_keys, hips_keys, weight, gaze, jaw]
        .iter()
        .map(|&output| json!({"input": times, "output": output, "interpolation": "LINEAR"}))
        .collect();
    let channels = json!([
        {"sampler": 0, "target": {"node": arm, "path": "rotation"}},
        {"sampler": 1, "target": {"node": 0, "path": "translation"}},
        {"sampler": 2, "target": {"node": x.aa, "path": "translation"}},
        {"sampler": 3, "target": {"node": x.look, "path": "translation"}},
        {"sampler": 4, "target": {"node": x.jaw, "path": "rotation"}},
    ]);

    let mut bones = serde_json::Map::new();
    for (j, def) in JOINTS.iter().enumerate() {
        if let Some(b) = vrm_bone(def.name) {
            bones.insert(b.to_owned(), json!({ "node": j }));
        }
    }
    bones.insert("jaw".into(), json!({"node": x.jaw}));
    let mut doc = json!({
        "asset": {"version": "2.0"},
        "extensionsUsed": ["VRMC_vrm_animation"],
        "extensions": {"VRMC_vrm_animation": {
            "specVersion": "1.0",
            "humanoid": {"humanBones": bones},
            "expressions": {"preset": {"aa": {"node": x.aa}}},
            "lookAt": {"node": x.look},
        }},
        "scenes": [{"nodes": [x.root, x.aa, x.look]}],
        "scene": 0,
        "nodes": nodes,
        "animations": [{"name": "wave", "samplers": samplers, "channels": channels}],
    });
    bin.finish(&mut doc);
    (doc, bin.bytes)
}

fn vrma() -> Vec<u8> {
    let (doc, bin) = vrma_doc();
    glb(&doc, &bin)
}

/// The fixture with its JSON text edited by `edit` (so a key can appear twice).
fn vrma_edited(edit: impl FnOnce(String) -> String) -> Vec<u8> {
    let (doc, bin) = vrma_doc();
    let text = edit(serde_json::to_string(&doc).unwrap());
    assert!(
        serde_json::from_str::<Value>(&text).is_ok(),
        "edited JSON does not parse"
    );
    glb_of_text(&text, &bin)
}

fn import(name: &str, bytes: Vec<u8>) -> Result<Vec<posecast_rigs::asset::Asset>, ImportError> {
    let mut set = FileSet::new();
    set.insert(name, bytes).unwrap();
    import_set(&set)
}

fn world_positions(
    skeleton: &posecast_proto::Skeleton,
    locals: &[posecast_proto::Transform],
) -> Vec<Vec3> {
    let mut world = vec![Mat4::IDENTITY; skeleton.len()];
    forward_kinematics(skeleton, locals, &mut world);
    world.iter().map(|w| w.w_axis.truncate()).collect()
}

#[test]
fn the_skeleton_and_bone_map_are_the_files() {
    let mut assets = import("dance.vrma", vrma()).unwrap();
    assert_eq!(assets.len(), 1);
    let asset = assets.remove(0);
    println!("notes: {:#?}", asset.source.notes);
    assert_eq!(asset.name, "dance");
    assert!(asset.meshes.is_empty());
    let sk = &asset.skeleton;
    // The 22 bones with an H-Anim name; `sacroiliac` and `Root` (static, rigid) folded.
    let bones: Vec<usize> = (0..JOINTS.len())
        .filter(|&j| vrm_bone(JOINTS[j].name).is_some())
        .collect();
    assert_eq!(sk.len(), bones.len(), "{:?}", sk.names());
    let map = asset.source.bone_map.as_ref().unwrap();
    assert_eq!(map.len(), bones.len());
    let rest = world_positions(sk, sk.rest());
    for &j in &bones {
        let name = format!("bone{j}");
        let k = sk.find(&name).unwrap_or_else(|| panic!("no {name}"));
        // The file maps node j to the VRM bone of built-in joint j, which is that joint's
        // H-Anim name.
        assert_eq!(map[&name], JOINTS[j].name, "{name}");
        // The file's T-pose, world positions.
        assert!(
            (rest[k] - head(j)).length() < 1e-5,
            "{name}: {} vs {}",
            rest[k],
            head(j)
        );
        // Parent: the nearest ancestor node that is a bone.
        let mut p = JOINTS[j].parent;
        while let Some(q) = p {
            if vrm_bone(JOINTS[q].name).is_some() {
                break;
            }
            p = JOINTS[q].parent;
        }
        let expected = p.map(|q| sk.find(&format!("bone{q}")).unwrap());
        assert_eq!(sk.parents()[k], expected, "{name}");
    }
    assert_eq!(asset.clips.len(), 1);
    assert_eq!(asset.clips[0].name(), "wave");
    let notes = asset.source.notes.join("\n");
    for said in [
        "VRM animation (VRMC_vrm_animation 1.0): a skeleton of 22 joints from 22 humanoid bones \
         and 2 nodes above or between them",
        "1 humanoid bones without an H-Anim counterpart not imported: jaw",
        "1 expressions not imported",
        "1 channel(s) on them ignored: preset/aa",
        &format!(
            "lookAt target (node {}) not imported, 1 channel(s) on it ignored",
            extra().look
        ),
        "1 nodes outside the humanoid bone map not imported: hair",
        "3 channel(s) on nodes outside this rig ignored",
    ] {
        assert!(notes.contains(said), "missing {said:?} in\n{notes}");
    }
    assert!(!notes.contains("mesh(es)"), "{notes}");

    let n = normalise(asset, &PipelineOptions::default()).unwrap();
    println!("steps: {:#?}", n.steps);
    assert!(n.humanoid, "{:?}", n.steps);
    let classification = n
        .steps
        .iter()
        .find(|s| s.starts_with("classification"))
        .unwrap();
    assert!(
        classification.contains("confidence 1.00"),
        "{classification}"
    );
    for &j in &bones {
        let k = n.asset.skeleton.find(&format!("bone{j}")).unwrap();
        assert_eq!(n.hanim[k].as_deref(), Some(JOINTS[j].name));
    }
}

/// Humanoid root height above the lowest joint at neutral (identity local rotations), metres.
fn hip_height(n: &Normalised) -> f32 {
    let sk = &n.asset.skeleton;
    let neutral: Vec<_> = sk
        .rest()
        .iter()
        .map(|t| posecast_proto::Transform {
            rotation: Quat::IDENTITY,
            ..*t
        })
        .collect();
    let p = world_positions(sk, &neutral);
    let root = joint(n, "humanoid_root");
    p[root].y - p.iter().map(|v| v.y).fold(f32::MAX, f32::min)
}

fn joint(n: &Normalised, hanim: &str) -> usize {
    n.hanim
        .iter()
        .position(|h| h.as_deref() == Some(hanim))
        .unwrap_or_else(|| panic!("{}: no {hanim}", n.asset.name))
}

fn positions(n: &Normalised, clip: &Clip, t: f32) -> Vec<Vec3> {
    let sk = &n.asset.skeleton;
    let mut locals = sk.rest().to_vec();
    clip.sample(t, sk.rest(), &mut locals);
    world_positions(sk, &locals)
}

fn angle(a: Vec3, b: Vec3) -> f32 {
    a.normalize()
        .dot(b.normalize())
        .clamp(-1.0, 1.0)
        .acos()
        .to_degrees()
}

/// The largest direction error allowed, degrees.
const MAX_DEGREES: f32 = 0.5;

#[test]
fn retargeted_onto_humanoids_the_arm_turns_and_the_hips_move_as_the_file_says() {
    let source = normalise(
        import("dance.vrma", vrma()).unwrap().remove(0),
        &PipelineOptions::default(),
    )
    .unwrap();
    let d0 = (head(joint_index("l_elbow")) - head(joint_index("l_shoulder"))).normalize();
    let expected_dir = q_arm() * d0;
    let mut targets = vec![normalise(rig_support::builtin(), &PipelineOptions::default()).unwrap()];
    if let Some(mut a) = rig_support::load("gltf/CesiumMan/glTF-Binary/CesiumMan.glb") {
        targets.push(normalise(a.remove(0), &PipelineOptions::default()).unwrap());
    }
    let clip = &source.asset.clips[0];
    let (start, end) = (clip.start(), clip.end());
    assert_eq!((start, end), (0.0, 1.0));
    for target in &targets {
        let out = retarget(RigView::from(&source), clip, RigView::from(target)).unwrap();
        let (p0, p1) = (positions(target, &out, start), positions(target, &out, end));
        let seg = |p: &[Vec3], a: &str, b: &str| p[joint(target, b)] - p[joint(target, a)];
        let arm0 = seg(&p0, "l_shoulder", "l_elbow");
        let arm1 = seg(&p1, "l_shoulder", "l_elbow");
        let right0 = seg(&p0, "r_shoulder", "r_elbow");
        let right1 = seg(&p1, "r_shoulder", "r_elbow");
        let k = hip_height(target) / hip_height(&source);
        let root = joint(target, "humanoid_root");
        let moved = p1[root] - p0[root];
        println!(
            "{}: arm at start {:.4}° from the file's T-pose, at end {:.4}° from Q·d0 (turned \
             {:.3}° of {:.3}°); right arm still within {:.4}°; hips moved {moved:.4} m, file \
             {DELTA} m × k {k:.4}",
            target.asset.name,
            angle(arm0, d0),
            angle(arm1, expected_dir),
            angle(arm0, arm1),
            angle(d0, expected_dir),
            angle(right0, right1),
        );
        assert!(angle(arm0, d0) < MAX_DEGREES, "{}", target.asset.name);
        assert!(
            angle(arm1, expected_dir) < MAX_DEGREES,
            "{}",
            target.asset.name
        );
        assert!(angle(right0, right1) < MAX_DEGREES, "{}", target.asset.name);
        assert!(
            (moved - k * DELTA).length() < 1e-3,
            "{}: hips moved {moved}, expected {}",
            target.asset.name,
            k * DELTA
        );
        if target.asset.name == "avatar" {
            // The same body: the hips move by the file's metres.
            assert!((k - 1.0).abs() < 1e-3, "k {k}");
        }
    }
}

fn vrma_error(bytes: Vec<u8>, name: &str) -> VrmaError {
    match import(name, bytes) {
        Err(ImportError::VrmAnimation { source, .. }) => source,
        Err(e) => panic!("another error: {e}"),
        Ok(_) => panic!("imported"),
    }
}

#[test]
fn malformed_extensions_are_typed_errors() {
    let x = extra();
    let hand = joint_index("l_wrist");
    let right_hand = joint_index("r_wrist");
    let bones_at = r#""humanBones":{"#;
    // A bone on a node the file lacks.
    let e = vrma_error(
        vrma_edited(|s| {
            s.replacen(
                &format!(r#""jaw":{{"node":{}}}"#, x.jaw),
                r#""jaw":{"node":999}"#,
                1,
            )
        }),
        "dance.vrma",
    );
    assert_eq!(
        e,
        VrmaError::MissingNode {
            bone: "jaw".into(),
            node: 999,
            nodes: JOINTS.len() + 5
        }
    );
    // A bone twice.
    let e = vrma_error(
        vrma_edited(|s| {
            s.replacen(
                bones_at,
                &format!(r#"{bones_at}"leftHand":{{"node":{hand}}},"#),
                1,
            )
        }),
        "dance.vrma",
    );
    assert_eq!(
        e,
        VrmaError::DuplicateBone {
            bone: "leftHand".into()
        }
    );
    // Two bones on one node.
    let e = vrma_error(
        vrma_edited(|s| {
            s.replacen(
                &format!(r#""leftHand":{{"node":{hand}}}"#),
                &format!(r#""leftHand":{{"node":{right_hand}}}"#),
                1,
            )
        }),
        "dance.vrma",
    );
    assert!(
        matches!(e, VrmaError::SharedNode { node, .. } if node == right_hand),
        "{e}"
    );
    // No hips.
    let e = vrma_error(
        vrma_edited(|s| {
            s.replacen(r#""hips":{"node":0},"#, "", 1)
                .replacen(r#","hips":{"node":0}"#, "", 1)
        }),
        "dance.vrma",
    );
    assert_eq!(
        e,
        VrmaError::MissingBones {
            bones: vec!["hips".into()]
        }
    );
    // A bone that does not hang from the hips.
    let e = vrma_error(
        vrma_edited(|s| {
            s.replacen(
                &format!(r#""leftHand":{{"node":{hand}}}"#),
                &format!(r#""leftHand":{{"node":{}}}"#, x.aa),
                1,
            )
        }),
        "dance.vrma",
    );
    assert!(
        matches!(e, VrmaError::NotUnderHips { node, .. } if node == x.aa),
        "{e}"
    );
    // humanBones not an object.
    let e = vrma_error(
        vrma_edited(|s| s.replacen(bones_at, r#""humanBones":[],"unused":{"#, 1)),
        "dance.vrma",
    );
    assert!(
        matches!(e, VrmaError::Shape { ref path, .. } if path == "humanoid.humanBones"),
        "{e}"
    );
    // A `.vrma` without the extension.
    let e = vrma_error(
        vrma_edited(|s| s.replacen(r#""VRMC_vrm_animation":"#, r#""OTHER_ext":"#, 1)),
        "dance.vrma",
    );
    assert_eq!(e, VrmaError::Absent);
    // Errors name the file.
    let msg = import(
        "dance.vrma",
        vrma_edited(|s| s.replacen(r#""hips":{"node":0}"#, r#""hips":{"node":999}"#, 1)),
    )
    .unwrap_err()
    .to_string();
    assert!(
        msg.starts_with("dance.vrma: VRMC_vrm_animation: humanoid bone \"hips\" names node 999"),
        "{msg}"
    );
}

#[test]
fn any_gltf_with_the_extension_and_no_skin_is_a_vrm_animation() {
    let asset = import("dance.glb", vrma()).unwrap().remove(0);
    assert_eq!(asset.skeleton.len(), 22);
    assert_eq!(asset.clips.len(), 1);
    // Without it, a skinless glTF is refused as before.
    let plain = vrma_edited(|s| s.replacen(r#""VRMC_vrm_animation":"#, r#""OTHER_ext":"#, 1));
    let e = import("dance.glb", plain).unwrap_err().to_string();
    assert!(e.contains("no skins"), "{e}");
}

/// Mutants of the fixture's JSON (digits changed, huge or negative numbers, spans deleted or
/// repeated) into the importer: each is imported or refused, never a panic, and what imports
/// samples and retargets.
#[test]
fn mutated_vrma_files_never_panic() {
    let (doc, bin) = vrma_doc();
    let text = serde_json::to_string(&doc).unwrap();
    let target = normalise(rig_support::builtin(), &PipelineOptions::default()).unwrap();
    let mut seed = 0x2545_F491_4F6C_DD1Du64;
    let mut next = move |n: usize| {
        seed ^= seed << 13;
        seed ^= seed >> 7;
        seed ^= seed << 17;
        (seed % n as u64) as usize
    };
    let (mut ok, mut refused) = (0, 0);
    for case in 0..300 {
        let mut t = text.clone().into_bytes();
        // Mutate inside the extension half of the time, that is what this importer reads:
        // the extension's object (its keys end with `specVersion`).
        let ext = text.find(r#""VRMC_vrm_animation":{"#).unwrap();
        let ext_end = ext + text[ext..].find(r#""specVersion""#).unwrap();
        for _ in 0..1 + next(3) {
            let at = if next(2) == 0 {
                ext + next(ext_end - ext)
            } else {
                next(t.len())
            }
            .min(t.len() - 1);
            match next(4) {
                0 if t[at].is_ascii_digit() => t[at] = b'0' + next(10) as u8,
                1 => {
                    let end = (at + 1 + next(12)).min(t.len());
                    t.drain(at..end);
                }
                2 => {
                    let end = (at + 1 + next(24)).min(t.len());
                    let span = t[at..end].to_vec();
                    t.splice(at..at, span);
                }
                _ if t[at].is_ascii_digit() => {
                    let huge: &[u8] = [&b"99999999999"[..], b"-1", b"4294967296", b"1e40"][next(4)];
                    t.splice(at..at + 1, huge.iter().copied());
                }
                _ => {}
            }
        }
        let mutant = String::from_utf8_lossy(&t).into_owned();
        let bytes = glb_of_text(&mutant, &bin);
        let result = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            let assets = match import("f.vrma", bytes) {
                Ok(a) => a,
                Err(e) => {
                    // The importer's panic guard must not be what catches a mutant.
                    assert!(!e.to_string().contains("parser failed"), "case {case}: {e}");
                    return false;
                }
            };
            for a in assets {
                if let Ok(n) = normalise(a, &PipelineOptions::default())
                    && n.humanoid
                {
                    for c in &n.asset.clips {
                        let _ = retarget(RigView::from(&n), c, RigView::from(&target));
                    }
                }
            }
            true
        }));
        match result {
            Ok(true) => ok += 1,
            Ok(false) => refused += 1,
            Err(_) => panic!("case {case} panicked"),
        }
    }
    println!("{ok} mutants imported, {refused} refused");
    assert!(ok > 0 && refused > 0, "{ok} imported, {refused} refused");
}
