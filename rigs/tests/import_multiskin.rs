//! One file, one avatar (issue 33, goal 5): CesiumMan's one skin split the way FBX2glTF
//! splits characters — one skin per arm, one for the body, the body bound through another
//! mesh transform, each skin listing its joints in its own order — plus a rigid `hat` on the
//! neck, imports as one rig whose meshes hold every vertex once and pose exactly as the
//! unsplit file does. A second character under the same non-joint scene node stays an asset
//! of its own.

// Helpers outside #[test] fns unwrap too: a failure there is a test failure.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod gltf_support;

use std::collections::HashMap;

use glam::{Mat4, Quat, Vec3};
use gltf_support::{Bin, glb};
use posecast_proto::fk::PoseBuffers;
use posecast_proto::skinning::skin_cpu;
use posecast_proto::testing::require_testdata;
use posecast_rigs::asset::Asset;
use posecast_rigs::import::gltf as gltf_import;
use serde_json::{Value, json};

const CESIUM: &str = "gltf/CesiumMan/glTF-Binary/CesiumMan.glb";

/// The transform the body skin's mesh is bound through: its inverse binds are `B_k · C`, its
/// vertices `C⁻¹ · v`, so the file poses as the original.
fn body_bind() -> Mat4 {
    Mat4::from_rotation_translation(Quat::from_rotation_y(0.7), Vec3::new(0.3, -0.2, 0.5))
}

/// The hat's transform under the neck joint.
fn hat_local() -> Mat4 {
    Mat4::from_translation(Vec3::new(0.0, 0.0, 0.25))
}

/// What to put in the split file.
#[derive(Clone, Copy, Default)]
struct Split {
    /// A second two-joint, two-skin character under the `Z_UP` node.
    second: bool,
    /// The body skin binds a joint it shares with the arms at another pose.
    other_pose: bool,
}

/// For each part (`armR`, `armL`, `body`), the original vertex of each of its vertices.
type Origins = HashMap<String, Vec<usize>>;

/// The split file, and where its parts' vertices come from.
fn split_cesium(split: Split) -> Option<(Vec<u8>, Origins)> {
    let bytes = std::fs::read(require_testdata(CESIUM)?).unwrap();
    let file = gltf::Gltf::from_slice(&bytes).unwrap();
    let blob = file.blob.clone().unwrap();
    let doc = file.document;
    let skin = doc.skins().next().unwrap();
    let joints: Vec<usize> = skin.joints().map(|n| n.index()).collect();
    let reader = skin.reader(|_| Some(&blob[..]));
    let ibm: Vec<Mat4> = reader
        .read_inverse_bind_matrices()
        .unwrap()
        .map(|m| Mat4::from_cols_array_2d(&m))
        .collect();
    let prim = doc.meshes().next().unwrap().primitives().next().unwrap();
    let r = prim.reader(|_| Some(&blob[..]));
    let pos: Vec<Vec3> = r.read_positions().unwrap().map(Vec3::from).collect();
    let nrm: Vec<Vec3> = r.read_normals().unwrap().map(Vec3::from).collect();
    let jts: Vec<[u16; 4]> = r.read_joints(0).unwrap().into_u16().collect();
    let wts: Vec<[f32; 4]> = r.read_weights(0).unwrap().into_f32().collect();
    let idx: Vec<u32> = r.read_indices().unwrap().into_u32().collect();

    // Each vertex goes to the part of its heaviest joint: the arms' joints by node name.
    let node_name = |n: usize| doc.nodes().nth(n).unwrap().name().unwrap_or("").to_owned();
    let part_of = |v: usize| {
        let (k, _) = (0..4)
            .map(|c| (c, wts[v][c]))
            .fold((0, -1.0), |a, b| if b.1 > a.1 { b } else { a });
        let name = node_name(joints[usize::from(jts[v][k])]);
        if name.starts_with("Skeleton_arm_joint_R") {
            0
        } else if name.starts_with("Skeleton_arm_joint_L") {
            1
        } else {
            2
        }
    };
    let parts: Vec<usize> = (0..pos.len()).map(part_of).collect();
    let json_of = |b: &[u8]| -> Value {
        let len = u32::from_le_bytes(b[12..16].try_into().unwrap()) as usize;
        serde_json::from_slice(&b[20..20 + len]).unwrap()
    };
    let mut doc_json = json_of(&bytes);
    let mut bin = Bin {
        bytes: blob.clone(),
        views: doc_json["bufferViews"].as_array().unwrap().clone(),
        accessors: doc_json["accessors"].as_array().unwrap().clone(),
    };
    let names = ["armR", "armL", "body"];
    let mut origin = HashMap::new();
    let mut skins = Vec::new();
    let mut meshes = Vec::new();
    let c = body_bind();
    for (p, name) in names.iter().enumerate() {
        let verts: Vec<usize> = (0..pos.len()).filter(|&v| parts[v] == p).collect();
        let mut local = HashMap::new();
        for (i, &v) in verts.iter().enumerate() {
            local.insert(v, i as u16);
        }
        // Triangles across two parts are left out; every vertex is kept once.
        let tris: Vec<u16> = idx
            .chunks_exact(3)
            .filter(|t| t.iter().all(|&v| parts[v as usize] == p))
            .flat_map(|t| t.iter().map(|v| local[&(*v as usize)]).collect::<Vec<_>>())
            .collect();
        // The skin's joints: those its vertices use, in an order of its own (reversed).
        let mut used: Vec<usize> = verts
            .iter()
            .flat_map(|&v| (0..4).map(move |c| (v, c)))
            .filter(|&(v, c)| wts[v][c] > 0.0)
            .map(|(v, c)| jts[v][c])
            .map(usize::from)
            .collect();
        if p == 2 {
            // The body's skin lists every joint, as exporters do.
            used = (0..joints.len()).collect();
        }
        used.sort_unstable();
        used.dedup();
        used.reverse();
        let slot: HashMap<usize, u16> = used
            .iter()
            .enumerate()
            .map(|(k, &j)| (j, k as u16))
            .collect();
        let mut joint_values = Vec::new();
        let mut weight_values = Vec::new();
        let mut pos_values = Vec::new();
        let mut nrm_values = Vec::new();
        let bake = if p == 2 { c.inverse() } else { Mat4::IDENTITY };
        for &v in &verts {
            for k in 0..4 {
                let w = wts[v][k];
                joint_values.push(if w > 0.0 {
                    slot[&usize::from(jts[v][k])]
                } else {
                    0
                });
                weight_values.push(w);
            }
            pos_values.extend(bake.transform_point3(pos[v]).to_array());
            nrm_values.extend(bake.transform_vector3(nrm[v]).to_array());
        }
        let mut matrices = Vec::new();
        for &j in &used {
            let mut m = ibm[j];
            if p == 2 {
                m *= c;
                if split.other_pose && node_name(joints[j]) == "torso_joint_3" {
                    m = Mat4::from_rotation_z(0.3) * m;
                }
            }
            matrices.extend(m.to_cols_array());
        }
        let attributes = json!({
            "POSITION": bin.floats(&pos_values, "VEC3"),
            "NORMAL": bin.floats(&nrm_values, "VEC3"),
            "JOINTS_0": bin.u16s(&joint_values, "VEC4"),
            "WEIGHTS_0": bin.floats(&weight_values, "VEC4"),
        });
        let indices = bin.u16s(&tris, "SCALAR");
        meshes.push(
            json!({"name": name, "primitives": [{"attributes": attributes, "indices": indices}]}),
        );
        skins.push(json!({
            "name": name,
            "joints": used.iter().map(|&j| joints[j]).collect::<Vec<_>>(),
            "inverseBindMatrices": bin.floats(&matrices, "MAT4"),
        }));
        origin.insert((*name).to_owned(), verts);
    }
    // The hat: a rigid triangle on the neck.
    let hat = json!({"name": "hat", "primitives": [{"attributes": {
        "POSITION": bin.floats(&[0.0, 0.0, 0.0, 0.1, 0.0, 0.0, 0.0, 0.1, 0.0], "VEC3")},
        "indices": bin.u16s(&[0, 1, 2], "SCALAR")}]});
    meshes.push(hat);
    let nodes = doc_json["nodes"].as_array_mut().unwrap();
    let neck = nodes
        .iter()
        .position(|n| n["name"] == "Skeleton_neck_joint_1")
        .unwrap();
    let first = nodes.len();
    // Node 2 (the mesh node) becomes armR's; armL, body and the hat follow.
    nodes[2] = json!({"name": "armR", "mesh": 0, "skin": 0});
    nodes.push(json!({"name": "armL", "mesh": 1, "skin": 1}));
    nodes.push(json!({"name": "body", "mesh": 2, "skin": 2}));
    let t = hat_local().to_scale_rotation_translation().2;
    nodes.push(json!({"name": "hat", "mesh": 3, "translation": t.to_array()}));
    nodes[1]["children"]
        .as_array_mut()
        .unwrap()
        .extend([json!(first), json!(first + 1)]);
    nodes[neck]["children"]
        .as_array_mut()
        .unwrap()
        .push(json!(first + 2));
    if split.second {
        // Two joints, one skin each, one skinned triangle each, under Z_UP (no joint).
        let second = nodes.len();
        nodes.push(
            json!({"name": "other_root", "translation": [2.0, 0.0, 0.0], "children": [second + 1]}),
        );
        nodes.push(json!({"name": "other_arm", "translation": [0.0, 0.0, 1.0]}));
        nodes.push(json!({"name": "other_a", "mesh": 4, "skin": 3}));
        nodes.push(json!({"name": "other_b", "mesh": 5, "skin": 4}));
        nodes[0]["children"].as_array_mut().unwrap().extend([
            json!(second),
            json!(second + 2),
            json!(second + 3),
        ]);
        for (k, world) in [
            Mat4::from_translation(Vec3::new(2.0, 0.0, 0.0)),
            Mat4::from_translation(Vec3::new(2.0, 0.0, 1.0)),
        ]
        .iter()
        .enumerate()
        {
            let p = bin.floats(&[0.0, 0.0, 0.0, 0.1, 0.0, 0.0, 0.0, 0.1, 0.0], "VEC3");
            let i = bin.u16s(&[0, 1, 2], "SCALAR");
            let j = bin.u16s(&[0; 12], "VEC4");
            let w = bin.floats(&[1.0, 0.0, 0.0, 0.0].repeat(3), "VEC4");
            meshes.push(
                json!({"name": format!("other{k}"), "primitives": [{"attributes":
                {"POSITION": p, "JOINTS_0": j, "WEIGHTS_0": w}, "indices": i}]}),
            );
            skins.push(json!({"joints": [second + k],
                "inverseBindMatrices": bin.floats(&world.inverse().to_cols_array(), "MAT4")}));
        }
    }
    doc_json["meshes"] = json!(meshes);
    doc_json["skins"] = json!(skins);
    for key in ["materials", "textures", "images", "samplers"] {
        doc_json.as_object_mut().unwrap().remove(key);
    }
    bin.finish(&mut doc_json);
    Some((glb(&doc_json, &bin.bytes), origin))
}

/// Each mesh's skinned positions at time `t` of the first clip (`posecast_proto`'s CPU
/// skinning), and the world matrices.
fn posed(asset: &Asset, t: f32) -> (Vec<Vec<Vec3>>, Vec<Mat4>) {
    let sk = &asset.skeleton;
    let mut locals = sk.rest().to_vec();
    asset.clips[0].sample(t, sk.rest(), &mut locals);
    let mut b = PoseBuffers::new(sk);
    b.update(sk, &locals);
    let meshes = asset
        .meshes
        .iter()
        .map(|m| {
            let n = m.mesh.vertex_count();
            let (mut p, mut nn) = (vec![Vec3::ZERO; n], vec![Vec3::ZERO; n]);
            skin_cpu(&m.mesh, &b.skinning, &mut p, &mut nn);
            p
        })
        .collect();
    (meshes, b.world.clone())
}

fn mesh(asset: &Asset, name: &str) -> usize {
    asset
        .meshes
        .iter()
        .position(|m| m.name.starts_with(name))
        .unwrap_or_else(|| panic!("no mesh {name} in {:?}", names(asset)))
}

fn names(asset: &Asset) -> Vec<&str> {
    asset.meshes.iter().map(|m| m.name.as_str()).collect()
}

#[test]
fn skins_of_one_skeleton_are_one_rig_posed_as_the_unsplit_file() {
    let Some((bytes, origin)) = split_cesium(Split::default()) else {
        return;
    };
    let original = gltf_import::from_slice(
        "CesiumMan.glb",
        &std::fs::read(require_testdata(CESIUM).unwrap()).unwrap(),
    )
    .unwrap()
    .remove(0);
    let assets = gltf_import::from_slice("split.glb", &bytes).unwrap();
    assert_eq!(
        assets.len(),
        1,
        "{:?}",
        assets.iter().map(|a| &a.name).collect::<Vec<_>>()
    );
    let asset = &assets[0];
    assert_eq!(asset.name, "split");
    assert_eq!(asset.skeleton.len(), original.skeleton.len());
    // Every vertex once: the parts hold the original's 3273, the hat its 3.
    assert_eq!(asset.meshes.len(), 4, "{:?}", names(asset));
    let skinned: usize = ["armR", "armL", "body"]
        .iter()
        .map(|n| asset.meshes[mesh(asset, n)].mesh.vertex_count())
        .sum();
    assert_eq!(skinned, original.meshes[0].mesh.vertex_count());
    assert_eq!(asset.meshes[mesh(asset, "hat")].mesh.vertex_count(), 3);
    let note = asset
        .source
        .notes
        .iter()
        .find(|n| n.contains("merged"))
        .unwrap_or_else(|| panic!("{:?}", asset.source.notes));
    assert!(note.starts_with("3 skins of one skeleton merged"), "{note}");

    let neck = |a: &Asset| {
        a.skeleton
            .names()
            .iter()
            .position(|n| n == "Skeleton_neck_joint_1")
            .unwrap()
    };
    for t in [0.0, 0.9, 1.7] {
        let (want, want_world) = posed(&original, t);
        let (got, _) = posed(asset, t);
        for (name, verts) in &origin {
            let m = mesh(asset, name);
            for (i, &v) in verts.iter().enumerate() {
                let d = (got[m][i] - want[0][v]).length();
                assert!(
                    d < 1e-4,
                    "t {t}: {name} vertex {i} (original {v}) off by {d}"
                );
            }
        }
        // The hat where the node hierarchy puts it: the neck's world times its local.
        let hat = want_world[neck(&original)] * hat_local();
        for (k, v) in [
            Vec3::ZERO,
            Vec3::new(0.1, 0.0, 0.0),
            Vec3::new(0.0, 0.1, 0.0),
        ]
        .iter()
        .enumerate()
        {
            let d = (got[mesh(asset, "hat")][k] - hat.transform_point3(*v)).length();
            assert!(d < 1e-4, "t {t}: hat vertex {k} off by {d}");
        }
    }
}

#[test]
fn disjoint_skeletons_stay_apart_each_merged() {
    let Some((bytes, _)) = split_cesium(Split {
        second: true,
        ..Split::default()
    }) else {
        return;
    };
    let assets = gltf_import::from_slice("two.glb", &bytes).unwrap();
    let listed: Vec<(&str, usize, usize)> = assets
        .iter()
        .map(|a| (a.name.as_str(), a.skeleton.len(), a.meshes.len()))
        .collect();
    assert_eq!(
        listed,
        [("two#armR", 19, 4), ("two#skin3", 2, 2)],
        "CesiumMan's 19 joints, 3 parts and hat; the second character's 2 joints and meshes"
    );
    for a in &assets {
        assert!(
            a.source.notes.iter().any(|n| n.contains("5 skins")),
            "{:?}",
            a.source.notes
        );
    }
}

#[test]
fn a_skin_bound_at_another_pose_stays_apart() {
    let Some((bytes, _)) = split_cesium(Split {
        other_pose: true,
        ..Split::default()
    }) else {
        return;
    };
    let assets = gltf_import::from_slice("pose.glb", &bytes).unwrap();
    // The skinned meshes; the hat hangs from a joint of both rigs and is in each.
    let listed: Vec<(&str, Vec<&str>)> = assets
        .iter()
        .map(|a| {
            let skinned = names(a)
                .into_iter()
                .filter(|n| !n.starts_with("hat"))
                .collect();
            (a.name.as_str(), skinned)
        })
        .collect();
    assert_eq!(
        listed,
        [
            ("pose#armR", vec!["armR", "armL"]),
            ("pose#body", vec!["body"])
        ]
    );
    assert!(
        assets[1]
            .source
            .notes
            .iter()
            .any(|n| n.contains("binds shared joints at another pose")),
        "{:?}",
        assets[1].source.notes
    );
}
