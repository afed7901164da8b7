//! glTF importer on the sample models in ../shared/testdata/gltf: counts and clip ranges from
//! SOURCES.md, the bind-pose check `W_j(rest) · B_j⁻¹ = mesh node global` against the node
//! hierarchy read independently with the `gltf` crate, rest-pose skinning, and sampled joint
//! world matrices against the file's own keyframes composed node by node.

#![allow(clippy::unwrap_used)]

use std::path::PathBuf;

use glam::{Mat4, Quat, Vec3};
use posecast_proto::Transform;
use posecast_proto::fk::PoseBuffers;
use posecast_proto::skinning::skin_cpu;
use posecast_proto::testing::{require_testdata, testdata};
use posecast_rigs::asset::{Asset, UpAxis};
use posecast_rigs::import::{self, ImportError, gltf as gltf_import};

fn path(rel: &str) -> Option<PathBuf> {
    require_testdata(rel)
}

fn load(rel: &str) -> Option<Vec<Asset>> {
    path(rel).map(|p| import::load_path(&p).unwrap())
}

/// Independent reference: the file's node hierarchy through the `gltf` crate's own importer.
struct Reference {
    doc: gltf::Document,
    buffers: Vec<gltf::buffer::Data>,
    parent: Vec<Option<usize>>,
}

impl Reference {
    fn new(rel: &str) -> Self {
        let (doc, buffers, _) = gltf::import(testdata(rel)).unwrap();
        let mut parent = vec![None; doc.nodes().len()];
        for n in doc.nodes() {
            for c in n.children() {
                parent[c.index()] = Some(n.index());
            }
        }
        Self {
            doc,
            buffers,
            parent,
        }
    }

    fn local(&self, node: usize) -> Mat4 {
        let n = self.doc.nodes().nth(node).unwrap();
        Mat4::from_cols_array_2d(&n.transform().matrix())
    }

    /// Global matrix with `local` supplying each node's local matrix.
    fn global_with(&self, node: usize, local: &dyn Fn(usize) -> Mat4) -> Mat4 {
        match self.parent[node] {
            Some(p) => self.global_with(p, local) * local(node),
            None => local(node),
        }
    }

    fn global(&self, node: usize) -> Mat4 {
        self.global_with(node, &|n| self.local(n))
    }

    fn skinned_mesh_node(&self) -> usize {
        self.doc
            .nodes()
            .find(|n| n.skin().is_some() && n.mesh().is_some())
            .unwrap()
            .index()
    }

    /// Each node's local matrix at key `k` of animation 0 (only for files whose channels
    /// share their key times), read with the gltf crate's reader.
    fn animated_locals(&self, k: usize) -> Vec<Mat4> {
        let mut trs: Vec<(Vec3, Quat, Vec3)> = self
            .doc
            .nodes()
            .map(|n| {
                let (t, r, s) = n.transform().decomposed();
                (Vec3::from(t), Quat::from_array(r), Vec3::from(s))
            })
            .collect();
        let anim = self.doc.animations().next().unwrap();
        for ch in anim.channels() {
            let reader = ch.reader(|b| Some(&self.buffers[b.index()]));
            let node = ch.target().node().index();
            use gltf::animation::util::ReadOutputs;
            match reader.read_outputs().unwrap() {
                ReadOutputs::Translations(mut it) => trs[node].0 = Vec3::from(it.nth(k).unwrap()),
                ReadOutputs::Rotations(it) => {
                    trs[node].1 = Quat::from_array(it.into_f32().nth(k).unwrap())
                }
                ReadOutputs::Scales(mut it) => trs[node].2 = Vec3::from(it.nth(k).unwrap()),
                ReadOutputs::MorphTargetWeights(_) => {}
            }
        }
        trs.iter()
            .map(|&(t, r, s)| Mat4::from_scale_rotation_translation(s, r, t))
            .collect()
    }

    fn key_time(&self, k: usize) -> f32 {
        let anim = self.doc.animations().next().unwrap();
        let ch = anim.channels().next().unwrap();
        let reader = ch.reader(|b| Some(&self.buffers[b.index()]));
        reader.read_inputs().unwrap().nth(k).unwrap()
    }
}

fn max_abs_diff(a: &Mat4, b: &Mat4) -> f32 {
    (*a - *b)
        .to_cols_array()
        .iter()
        .fold(0.0f32, |m, v| m.max(v.abs()))
}

fn rest_buffers(a: &Asset) -> PoseBuffers {
    let mut b = PoseBuffers::new(&a.skeleton);
    b.update(&a.skeleton, a.skeleton.rest());
    b
}

fn skin_joints(a: &Asset) -> usize {
    a.skeleton.len() - a.source.helper_joints.len()
}

fn vertex_and_triangle_counts(a: &Asset) -> (usize, usize) {
    a.meshes.iter().fold((0, 0), |(v, t), m| {
        (v + m.mesh.vertex_count(), t + m.mesh.indices().len() / 3)
    })
}

#[test]
fn figures_match_sources() {
    // (file, skin joints, vertices, triangles, clip start, clip end, up axis)
    let cases: [(&str, usize, usize, usize, f32, f32, UpAxis); 7] = [
        (
            "gltf/RiggedSimple/glTF-Binary/RiggedSimple.glb",
            2,
            160,
            188,
            0.0417,
            2.0833,
            UpAxis::Z,
        ),
        (
            "gltf/RiggedSimple/glTF/RiggedSimple.gltf",
            2,
            160,
            188,
            0.0417,
            2.0833,
            UpAxis::Z,
        ),
        (
            "gltf/RiggedFigure/glTF-Binary/RiggedFigure.glb",
            19,
            370,
            256,
            0.0,
            1.25,
            UpAxis::Z,
        ),
        (
            "gltf/CesiumMan/glTF-Binary/CesiumMan.glb",
            19,
            3273,
            4672,
            0.0417,
            2.0,
            UpAxis::Z,
        ),
        (
            "gltf/SimpleSkin/glTF/SimpleSkin.gltf",
            2,
            10,
            8,
            0.0,
            5.5,
            UpAxis::Y,
        ),
        (
            "gltf/SimpleSkin/glTF-Embedded/SimpleSkin.gltf",
            2,
            10,
            8,
            0.0,
            5.5,
            UpAxis::Y,
        ),
        (
            "gltf/RecursiveSkeletons/glTF-Binary/RecursiveSkeletons.glb",
            210,
            840,
            1596,
            0.0,
            2.0,
            UpAxis::Y,
        ),
    ];
    for (rel, joints, verts, tris, start, end, up) in cases {
        let Some(assets) = load(rel) else { return };
        let a = &assets[0];
        assert_eq!(skin_joints(a), joints, "{rel}");
        assert_eq!(vertex_and_triangle_counts(a), (verts, tris), "{rel}");
        assert_eq!(a.clips.len(), 1, "{rel}");
        let c = &a.clips[0];
        assert!(
            (c.start() - start).abs() < 1e-3 && (c.end() - end).abs() < 1e-3,
            "{rel}: {} – {}",
            c.start(),
            c.end()
        );
        assert_eq!(a.source.up_axis, up, "{rel}");
    }
}

/// Its README: "4 large skeleton armatures, 84 skin bindings", the one 40-vertex mesh bound
/// 21 times to each skeleton: one rig per skeleton, each instance once.
#[test]
fn recursive_skeletons_gives_one_asset_per_skeleton() {
    let Some(assets) = load("gltf/RecursiveSkeletons/glTF-Binary/RecursiveSkeletons.glb") else {
        return;
    };
    assert_eq!(assets.len(), 4);
    let names: std::collections::HashSet<&str> = assets.iter().map(|a| a.name.as_str()).collect();
    assert_eq!(names.len(), 4);
    for a in &assets {
        assert_eq!(skin_joints(a), 210, "{}", a.name);
        assert_eq!(a.meshes.len(), 21, "{}", a.name);
        for m in &a.meshes {
            assert_eq!(
                (m.mesh.vertex_count(), m.mesh.indices().len() / 3),
                (40, 76)
            );
        }
        assert_eq!(a.clips[0].name(), "Track0");
        assert!(
            a.source
                .notes
                .iter()
                .any(|n| n.starts_with("21 skins of one skeleton merged")),
            "{:?}",
            a.source.notes
        );
    }
}

#[test]
fn bind_pose_check_equals_mesh_node_global() {
    for rel in [
        "gltf/RiggedFigure/glTF-Binary/RiggedFigure.glb",
        "gltf/CesiumMan/glTF-Binary/CesiumMan.glb",
    ] {
        let Some(assets) = load(rel) else { return };
        let a = &assets[0];
        let r = Reference::new(rel);
        let mesh_global = r.global(r.skinned_mesh_node());
        let b = rest_buffers(a);
        for j in 0..a.skeleton.len() {
            let d = max_abs_diff(&b.skinning[j], &mesh_global);
            assert!(d < 1e-4, "{rel} joint {j}: {d}");
        }
        // Skinning the rest pose therefore places the mesh as its node would.
        let mesh = &a.meshes[0].mesh;
        let mut p = vec![Vec3::ZERO; mesh.vertex_count()];
        let mut n = vec![Vec3::ZERO; mesh.vertex_count()];
        skin_cpu(mesh, &b.skinning, &mut p, &mut n);
        for (got, v) in p.iter().zip(mesh.positions()) {
            assert!((*got - mesh_global.transform_point3(*v)).length() < 1e-4);
        }
    }
}

#[test]
fn rigged_simple_uses_z_up_not_mesh_node() {
    let rel = "gltf/RiggedSimple/glTF-Binary/RiggedSimple.glb";
    let Some(assets) = load(rel) else { return };
    let a = &assets[0];
    let r = Reference::new(rel);
    // SOURCES.md: glob(J)·IBM equals the root Z_UP matrix, not the mesh node's global.
    let z_up = r
        .doc
        .nodes()
        .find(|n| n.name() == Some("Z_UP"))
        .unwrap()
        .index();
    let z_up_m = r.global(z_up);
    let b = rest_buffers(a);
    for j in 0..a.skeleton.len() {
        assert!(max_abs_diff(&b.skinning[j], &z_up_m) < 1e-4, "joint {j}");
    }
    assert!(max_abs_diff(&z_up_m, &r.global(r.skinned_mesh_node())) > 0.5);
}

#[test]
fn simple_skin_rest_and_t0_reproduce_the_mesh() {
    for rel in [
        "gltf/SimpleSkin/glTF/SimpleSkin.gltf",
        "gltf/SimpleSkin/glTF-Embedded/SimpleSkin.gltf",
    ] {
        let Some(assets) = load(rel) else { return };
        let a = &assets[0];
        let mesh = &a.meshes[0].mesh;
        let mut pose = a.skeleton.rest().to_vec();
        a.clips[0].sample(0.0, a.skeleton.rest(), &mut pose);
        for locals in [a.skeleton.rest().to_vec(), pose] {
            let mut b = PoseBuffers::new(&a.skeleton);
            b.update(&a.skeleton, &locals);
            let mut p = vec![Vec3::ZERO; mesh.vertex_count()];
            let mut n = vec![Vec3::ZERO; mesh.vertex_count()];
            skin_cpu(mesh, &b.skinning, &mut p, &mut n);
            for (got, v) in p.iter().zip(mesh.positions()) {
                assert!((*got - *v).length() < 1e-5, "{rel}: {got} vs {v}");
            }
        }
    }
}

#[test]
fn sampled_worlds_match_the_files_keyframes() {
    // CesiumMan: all 57 channels share 48 key times; compose the file's own TRS at key k
    // through the node tree (Z_UP and Armature included) and compare joint world matrices.
    for rel in [
        "gltf/CesiumMan/glTF-Binary/CesiumMan.glb",
        "gltf/RiggedFigure/glTF-Binary/RiggedFigure.glb",
        "gltf/RiggedSimple/glTF-Binary/RiggedSimple.glb",
    ] {
        let Some(assets) = load(rel) else { return };
        let a = &assets[0];
        let r = Reference::new(rel);
        let skin = r.doc.skins().next().unwrap();
        for k in [0usize, 1] {
            let locals = r.animated_locals(k);
            let t = r.key_time(k);
            let mut pose = vec![Transform::IDENTITY; a.skeleton.len()];
            a.clips[0].sample(t, a.skeleton.rest(), &mut pose);
            let mut b = PoseBuffers::new(&a.skeleton);
            b.update(&a.skeleton, &pose);
            for joint in skin.joints() {
                let want = r.global_with(joint.index(), &|n| locals[n]);
                let name = joint.name().unwrap();
                let j = a.skeleton.find(name).unwrap();
                let d = max_abs_diff(&b.world[j], &want);
                assert!(d < 1e-4, "{rel} key {k} joint {name}: {d}");
            }
        }
    }
}

#[test]
fn bytes_api_refuses_external_buffers_but_reads_embedded() {
    let Some(ext) = path("gltf/SimpleSkin/glTF/SimpleSkin.gltf") else {
        return;
    };
    let bytes = std::fs::read(ext).unwrap();
    let e = gltf_import::from_slice("SimpleSkin.gltf", &bytes).unwrap_err();
    assert!(matches!(e, ImportError::Buffer { .. }), "{e}");
    assert!(e.to_string().contains("SimpleSkin.gltf"));
    let emb = std::fs::read(testdata("gltf/SimpleSkin/glTF-Embedded/SimpleSkin.gltf")).unwrap();
    assert_eq!(
        gltf_import::from_slice("SimpleSkin.gltf", &emb)
            .unwrap()
            .len(),
        1
    );
    let glb = std::fs::read(testdata("gltf/CesiumMan/glTF-Binary/CesiumMan.glb")).unwrap();
    assert_eq!(
        gltf_import::from_slice("CesiumMan.glb", &glb)
            .unwrap()
            .len(),
        1
    );
}

/// Ready Player Me's face, eyes and teeth keep their five named morph targets, and each target
/// moves every vertex where the file says: at rest, the imported displacement skinned by the
/// imported rig equals the file's displacement (read by the `gltf` crate) skinned by the file's
/// own `Σ wₖ · G(jₖ) · IBMₖ`.
#[test]
fn ready_player_me_targets_reproduce_the_files_displacements() {
    use posecast_proto::skinning::blend_matrix;
    let rel = "gltf/ReadyPlayerMe/PreviewMesh.glb";
    let Some(assets) = load(rel) else { return };
    let a = &assets[0];
    let r = Reference::new(rel);
    let b = rest_buffers(a);
    let names = [
        "mouthOpen",
        "mouthSmile",
        "eyesClosed",
        "eyesLookUp",
        "eyesLookDown",
    ];
    let (mut checked, mut moved) = (0, 0);
    for node in r.doc.nodes() {
        let (Some(skin), Some(mesh)) = (node.skin(), node.mesh()) else {
            continue;
        };
        let ibms: Vec<Mat4> = skin
            .reader(|b| Some(&r.buffers[b.index()]))
            .read_inverse_bind_matrices()
            .unwrap()
            .map(|m| Mat4::from_cols_array_2d(&m))
            .collect();
        let joint_world: Vec<Mat4> = skin
            .joints()
            .zip(&ibms)
            .map(|(j, ibm)| r.global(j.index()) * *ibm)
            .collect();
        for prim in mesh.primitives() {
            let reader = prim.reader(|b| Some(&r.buffers[b.index()]));
            let targets: Vec<Vec<Vec3>> = reader
                .read_morph_targets()
                .map(|(p, _, _)| p.unwrap().map(Vec3::from).collect())
                .collect();
            if targets.is_empty() {
                continue;
            }
            let ours = &a
                .meshes
                .iter()
                .find(|m| m.name == mesh.name().unwrap())
                .unwrap()
                .mesh;
            let got: Vec<&str> = ours.targets().iter().map(|t| t.name.as_str()).collect();
            assert_eq!(got, names, "{:?}", mesh.name());
            let joints: Vec<[u16; 4]> = reader.read_joints(0).unwrap().into_u16().collect();
            let weights: Vec<[f32; 4]> = reader.read_weights(0).unwrap().into_f32().collect();
            for (k, target) in targets.iter().enumerate() {
                for (v, d) in target.iter().enumerate() {
                    let blend: Mat4 = (0..4)
                        .map(|i| joint_world[joints[v][i] as usize] * weights[v][i])
                        .fold(Mat4::ZERO, |s, m| s + m);
                    let want = blend.transform_vector3(*d);
                    let ours_d = ours.targets()[k].positions[v];
                    let have = blend_matrix(ours, &b.skinning, v).transform_vector3(ours_d);
                    assert!(
                        (want - have).length() < 1e-6,
                        "{:?} target {k} vertex {v}: {have} vs {want}",
                        mesh.name()
                    );
                    checked += 1;
                    moved += usize::from(want.length() > 1e-4);
                }
            }
        }
    }
    println!("{checked} displacements checked, {moved} of them move a vertex > 0.1 mm");
    assert!(moved > 1000, "{moved}");
}
