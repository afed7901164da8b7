//! The built-in avatar, read back through the `gltf` crate and `posecast_proto` only: the
//! committed file is what the generator makes, its rig is consistent (rest == bind), and its
//! clips do what their names say.

// The helpers that read the file are test code too: a malformed file should fail loudly.
#![allow(clippy::expect_used)]

use glam::{Mat3, Mat4, Quat, Vec3};
use gltf::animation::util::ReadOutputs;
use posecast_proto::fk::PoseBuffers;
use posecast_proto::skinning::skin_cpu;
use posecast_proto::{Skeleton, SkinnedMesh, Transform};
use posecast_rigs::builtin::{AVATAR_GLB, generate};

/// H-Anim (ISO/IEC 19774) joint names for the body, spine and limbs, without the hands'
/// and face's finer joints, which the built-in avatar does not use.
const H_ANIM_JOINTS: &[&str] = &[
    "humanoid_root",
    "sacroiliac",
    "vl5",
    "vl4",
    "vl3",
    "vl2",
    "vl1",
    "vt12",
    "vt11",
    "vt10",
    "vt9",
    "vt8",
    "vt7",
    "vt6",
    "vt5",
    "vt4",
    "vt3",
    "vt2",
    "vt1",
    "vc7",
    "vc6",
    "vc5",
    "vc4",
    "vc3",
    "vc2",
    "vc1",
    "skullbase",
    "l_hip",
    "l_knee",
    "l_talocrural",
    "l_ankle",
    "l_subtalar",
    "l_midtarsal",
    "l_metatarsal",
    "l_tarsometatarsal_1",
    "r_hip",
    "r_knee",
    "r_talocrural",
    "r_ankle",
    "r_subtalar",
    "r_midtarsal",
    "r_metatarsal",
    "r_tarsometatarsal_1",
    "l_sternoclavicular",
    "l_acromioclavicular",
    "l_shoulder",
    "l_elbow",
    "l_radiocarpal",
    "l_wrist",
    "l_midcarpal_1",
    "r_sternoclavicular",
    "r_acromioclavicular",
    "r_shoulder",
    "r_elbow",
    "r_radiocarpal",
    "r_wrist",
    "r_midcarpal_1",
];

/// Everything the tests read from the file.
struct Avatar {
    skeleton: Skeleton,
    mesh: SkinnedMesh,
    /// Skin joint index of each joint node.
    node_to_joint: Vec<Option<usize>>,
    raw_joints: Vec<[u16; 4]>,
    raw_weights: Vec<[f32; 4]>,
    clips: Vec<Clip>,
}

struct Clip {
    name: String,
    times: Vec<f32>,
    /// `(joint, keys)`.
    rotations: Vec<(usize, Vec<Quat>)>,
    translations: Vec<(usize, Vec<Vec3>)>,
}

impl Clip {
    fn keys(&self) -> usize {
        self.times.len()
    }

    /// The locals at key `k`: rest, overridden by every channel.
    fn locals(&self, skeleton: &Skeleton, k: usize) -> Vec<Transform> {
        let mut locals = skeleton.rest().to_vec();
        for (j, keys) in &self.rotations {
            locals[*j].rotation = keys[k];
        }
        for (j, keys) in &self.translations {
            locals[*j].translation = keys[k];
        }
        locals
    }
}

fn load(bytes: &[u8]) -> Avatar {
    let gltf = gltf::Gltf::from_slice(bytes).expect("valid glb");
    let blob = gltf.blob.clone().expect("a BIN chunk");
    let buffers = |b: gltf::Buffer<'_>| match b.source() {
        gltf::buffer::Source::Bin => Some(blob.as_slice()),
        gltf::buffer::Source::Uri(_) => None,
    };
    let skin = gltf.skins().next().expect("one skin");
    let joint_nodes: Vec<usize> = skin.joints().map(|n| n.index()).collect();
    let mut node_to_joint = vec![None; gltf.nodes().len()];
    for (j, &n) in joint_nodes.iter().enumerate() {
        node_to_joint[n] = Some(j);
    }
    let mut parents = vec![None; joint_nodes.len()];
    for node in gltf.nodes() {
        for child in node.children() {
            if let (Some(c), Some(p)) = (node_to_joint[child.index()], node_to_joint[node.index()])
            {
                parents[c] = Some(p);
            }
        }
    }
    let names: Vec<String> = skin
        .joints()
        .map(|n| n.name().expect("named joint").to_owned())
        .collect();
    let rest: Vec<Transform> = skin
        .joints()
        .map(|n| {
            let (t, r, s) = n.transform().decomposed();
            Transform {
                translation: Vec3::from(t),
                rotation: Quat::from_array(r),
                scale: Vec3::from(s),
            }
        })
        .collect();
    let inverse_binds: Vec<Mat4> = skin
        .reader(buffers)
        .read_inverse_bind_matrices()
        .expect("inverse binds")
        .map(|m| Mat4::from_cols_array_2d(&m))
        .collect();
    let skeleton = Skeleton::new(names, parents, rest, inverse_binds).expect("valid skeleton");

    let primitive = gltf
        .meshes()
        .next()
        .and_then(|m| m.primitives().next())
        .expect("one primitive");
    let attribute = |s: gltf::Semantic| primitive.get(&s).expect("attribute");
    assert_eq!(
        attribute(gltf::Semantic::Joints(0)).data_type(),
        gltf::accessor::DataType::U16
    );
    assert_eq!(
        attribute(gltf::Semantic::Weights(0)).data_type(),
        gltf::accessor::DataType::F32
    );
    let reader = primitive.reader(buffers);
    let positions: Vec<Vec3> = reader
        .read_positions()
        .expect("positions")
        .map(Vec3::from)
        .collect();
    let normals: Vec<Vec3> = reader
        .read_normals()
        .expect("normals")
        .map(Vec3::from)
        .collect();
    let indices: Vec<u32> = reader.read_indices().expect("indices").into_u32().collect();
    let raw_joints: Vec<[u16; 4]> = reader.read_joints(0).expect("joints").into_u16().collect();
    let raw_weights: Vec<[f32; 4]> = reader
        .read_weights(0)
        .expect("weights")
        .into_f32()
        .collect();
    let mesh = SkinnedMesh::new(
        positions,
        normals,
        indices,
        4,
        raw_joints.iter().flatten().copied().collect(),
        raw_weights.iter().flatten().copied().collect(),
        skeleton.len(),
    )
    .expect("valid mesh");

    let clips = gltf
        .animations()
        .map(|animation| {
            let mut clip = Clip {
                name: animation.name().expect("named clip").to_owned(),
                times: Vec::new(),
                rotations: Vec::new(),
                translations: Vec::new(),
            };
            for channel in animation.channels() {
                assert_eq!(
                    channel.sampler().interpolation(),
                    gltf::animation::Interpolation::Linear
                );
                let joint = node_to_joint[channel.target().node().index()].expect("joint target");
                let reader = channel.reader(buffers);
                let times: Vec<f32> = reader.read_inputs().expect("inputs").collect();
                if clip.times.is_empty() {
                    clip.times = times.clone();
                }
                assert_eq!(times, clip.times, "{}: channels share key times", clip.name);
                match reader.read_outputs().expect("outputs") {
                    ReadOutputs::Rotations(r) => clip
                        .rotations
                        .push((joint, r.into_f32().map(Quat::from_array).collect())),
                    ReadOutputs::Translations(t) => {
                        clip.translations.push((joint, t.map(Vec3::from).collect()))
                    }
                    _ => panic!("{}: unexpected channel", clip.name),
                }
            }
            clip
        })
        .collect();

    Avatar {
        skeleton,
        mesh,
        node_to_joint,
        raw_joints,
        raw_weights,
        clips,
    }
}

fn avatar() -> Avatar {
    load(AVATAR_GLB)
}

fn clip<'a>(avatar: &'a Avatar, name: &str) -> &'a Clip {
    avatar
        .clips
        .iter()
        .find(|c| c.name == name)
        .unwrap_or_else(|| panic!("no clip {name}"))
}

fn joint(avatar: &Avatar, name: &str) -> usize {
    avatar
        .skeleton
        .find(name)
        .unwrap_or_else(|| panic!("no joint {name}"))
}

/// Joint centres (model space) at key `k` of `clip`.
fn joint_positions(avatar: &Avatar, clip: &Clip, k: usize) -> Vec<Vec3> {
    let mut buffers = PoseBuffers::new(&avatar.skeleton);
    buffers.update(&avatar.skeleton, &clip.locals(&avatar.skeleton, k));
    buffers.world.iter().map(|w| w.w_axis.truncate()).collect()
}

fn skinned(avatar: &Avatar, locals: &[Transform]) -> (Vec<Vec3>, Vec<Vec3>) {
    let mut buffers = PoseBuffers::new(&avatar.skeleton);
    buffers.update(&avatar.skeleton, locals);
    let n = avatar.mesh.vertex_count();
    let (mut p, mut nn) = (vec![Vec3::ZERO; n], vec![Vec3::ZERO; n]);
    skin_cpu(&avatar.mesh, &buffers.skinning, &mut p, &mut nn);
    (p, nn)
}

#[test]
fn generator_is_deterministic_and_matches_the_committed_file() {
    let first = generate();
    assert!(first == generate(), "two runs of the generator differ");
    assert!(
        first == AVATAR_GLB,
        "assets/avatar.glb is stale: run `cargo run -p posecast-tools --bin make-avatar` \
         and commit the result"
    );
}

#[test]
fn joints_are_h_anim_and_unique() {
    let a = avatar();
    let names = a.skeleton.names();
    assert!((20..=30).contains(&names.len()), "{} joints", names.len());
    for (i, name) in names.iter().enumerate() {
        assert!(
            H_ANIM_JOINTS.contains(&name.as_str()),
            "{name} is not an H-Anim joint"
        );
        assert!(!names[..i].contains(name), "{name} twice");
    }
    for required in [
        "humanoid_root",
        "l_hip",
        "r_knee",
        "skullbase",
        "l_shoulder",
        "r_wrist",
    ] {
        assert!(a.skeleton.find(required).is_some(), "no {required}");
    }
    assert_eq!(
        a.skeleton.roots().collect::<Vec<_>>(),
        vec![joint(&a, "humanoid_root")]
    );
    assert_eq!(a.node_to_joint.iter().flatten().count(), names.len());
}

#[test]
fn mesh_is_big_enough_and_smoothly_weighted() {
    let a = avatar();
    assert!(
        a.mesh.vertex_count() >= 2000,
        "{} vertices",
        a.mesh.vertex_count()
    );
    assert!(!a.mesh.indices().is_empty() && a.mesh.indices().len().is_multiple_of(3));
    let mut blended = 0;
    let mut three_or_more = 0;
    for (v, (joints, weights)) in a.raw_joints.iter().zip(&a.raw_weights).enumerate() {
        let used: Vec<(u16, f32)> = joints
            .iter()
            .copied()
            .zip(weights.iter().copied())
            .filter(|p| p.1 != 0.0)
            .collect();
        assert!(!used.is_empty() && used.len() <= 4, "vertex {v}");
        let sum: f32 = weights.iter().sum();
        assert!((sum - 1.0).abs() <= 1e-5, "vertex {v} weights sum to {sum}");
        for (j, w) in used {
            assert!(w > 0.0 && usize::from(j) < a.skeleton.len(), "vertex {v}");
        }
        if weights.iter().filter(|&&w| w > 0.05).count() >= 2 {
            blended += 1;
        }
        if weights.iter().filter(|&&w| w > 0.0).count() >= 3 {
            three_or_more += 1;
        }
    }
    // Smooth, not rigid: a good share of vertices is shared between joints.
    assert!(
        blended * 10 > a.raw_weights.len(),
        "only {blended} blended vertices"
    );
    // Where the limbs meet the torso, more than two joints share a vertex.
    assert!(
        three_or_more >= 50,
        "only {three_or_more} vertices with 3+ influences"
    );
    for n in a.mesh.normals() {
        assert!((n.length() - 1.0).abs() < 1e-4);
    }
}

#[test]
fn bind_matrices_are_rotated() {
    let a = avatar();
    let rotated = a
        .skeleton
        .inverse_bind()
        .iter()
        .filter(|ib| !Mat3::from_mat4(**ib).abs_diff_eq(Mat3::IDENTITY, 1e-3))
        .count();
    assert!(
        rotated >= a.skeleton.len() / 2,
        "only {rotated} rotated bind frames"
    );
    // So identity locals (what a naive client sends) do not give the bind pose.
    let identity: Vec<Transform> = a
        .skeleton
        .rest()
        .iter()
        .map(|r| Transform::from_translation(r.translation))
        .collect();
    let (posed, _) = skinned(&a, &identity);
    let moved = posed
        .iter()
        .zip(a.mesh.positions())
        .map(|(p, q)| p.distance(*q))
        .fold(0.0f32, f32::max);
    assert!(moved > 0.1, "identity locals moved the mesh only {moved} m");
}

#[test]
fn rest_pose_reproduces_the_mesh_at_human_size() {
    let a = avatar();
    let (positions, normals) = skinned(&a, a.skeleton.rest());
    for (v, (p, q)) in positions.iter().zip(a.mesh.positions()).enumerate() {
        assert!(p.distance(*q) < 1e-5, "vertex {v}: {p} vs {q}");
    }
    for (n, m) in normals.iter().zip(a.mesh.normals()) {
        assert!(n.distance(*m) < 1e-4);
    }
    let (lo, hi) = a.mesh.bounds();
    assert!((hi.y - 1.75).abs() < 0.03, "height {}", hi.y);
    assert!(lo.y.abs() < 0.005, "feet at {}", lo.y);
    // T-pose: arm span about the height, the avatar's left at +X, feet pointing +Z.
    assert!((hi.x - lo.x - 1.8).abs() < 0.15, "span {}", hi.x - lo.x);
    let world = joint_positions(&a, &rest_clip(), 0);
    assert!(world[joint(&a, "l_wrist")].x > 0.5);
    let foot = world[joint(&a, "l_midtarsal")] - world[joint(&a, "l_ankle")];
    assert!(foot.z > 0.05);
}

/// A one-key clip with no channels: the rest pose.
fn rest_clip() -> Clip {
    Clip {
        name: "rest".into(),
        times: vec![0.0],
        rotations: Vec::new(),
        translations: Vec::new(),
    }
}

#[test]
fn clips_are_named_finite_unit_and_looping() {
    let a = avatar();
    let names: Vec<&str> = a.clips.iter().map(|c| c.name.as_str()).collect();
    assert_eq!(names, ["idle", "walk", "wave"]);
    for (clip, seconds) in a.clips.iter().zip([4.0, 1.0, 2.0]) {
        let end = clip.times.last().copied().unwrap_or_default();
        assert!((end - seconds).abs() < 1e-5, "{} lasts {end}", clip.name);
        assert!(clip.times.windows(2).all(|t| t[1] > t[0]));
        assert!(
            clip.keys() >= 20 * seconds as usize,
            "{}: too few keys",
            clip.name
        );
        assert!(clip.rotations.len() >= 4, "{} moves too little", clip.name);
        for (j, keys) in &clip.rotations {
            assert!(
                keys.iter()
                    .all(|q| q.is_finite() && (q.length() - 1.0).abs() < 1e-5)
            );
            assert_eq!(
                keys.first(),
                keys.last(),
                "{} joint {j} does not loop",
                clip.name
            );
        }
        for (_, keys) in &clip.translations {
            assert!(keys.iter().all(|t| t.is_finite()));
            assert_eq!(
                keys.first(),
                keys.last(),
                "{}: root does not loop",
                clip.name
            );
        }
    }
    let root = joint(&a, "humanoid_root");
    for name in ["idle", "walk"] {
        let translated: Vec<usize> = clip(&a, name).translations.iter().map(|t| t.0).collect();
        assert_eq!(translated, [root], "{name}");
    }
}

#[test]
fn walk_plants_a_foot_and_swings_the_legs() {
    let a = avatar();
    let walk = clip(&a, "walk");
    let rest = joint_positions(&a, &rest_clip(), 0);
    let (l, r) = (joint(&a, "l_ankle"), joint(&a, "r_ankle"));
    let mut stride: Vec<f32> = Vec::new();
    for k in 0..walk.keys() {
        let p = joint_positions(&a, walk, k);
        let low = p[l].y.min(p[r].y);
        assert!(
            (low - rest[l].y).abs() < 0.01,
            "key {k}: lower ankle at {low}"
        );
        stride.push(p[l].z - p[r].z);
        for wrist in ["l_wrist", "r_wrist"] {
            assert!(p[joint(&a, wrist)].y < 1.0, "key {k}: {wrist} not hanging");
        }
    }
    let (min, max) = stride
        .iter()
        .fold((f32::MAX, f32::MIN), |(lo, hi), &s| (lo.min(s), hi.max(s)));
    assert!(
        min < -0.2 && max > 0.2,
        "legs do not alternate: {min}..{max}"
    );
    // The skinned mesh stays on the floor at the double-support key.
    let (posed, _) = skinned(&a, &walk.locals(&a.skeleton, walk.keys() / 4));
    let floor = posed.iter().map(|p| p.y).fold(f32::MAX, f32::min);
    assert!(floor.abs() < 0.02, "lowest vertex at {floor}");
}

#[test]
fn wave_raises_the_right_hand_above_the_head() {
    let a = avatar();
    let wave = clip(&a, "wave");
    let mut highest = f32::MIN;
    for k in 0..wave.keys() {
        let p = joint_positions(&a, wave, k);
        let wrist = p[joint(&a, "r_wrist")];
        assert!(
            wrist.y > p[joint(&a, "skullbase")].y + 0.05,
            "key {k}: {wrist}"
        );
        assert!(wrist.x < 0.0, "the right hand is at -X");
        assert!(p[joint(&a, "l_wrist")].y < 1.0);
        highest = highest.max(wrist.y);
    }
    assert!(highest > 1.75, "the hand never clears the head: {highest}");
}

#[test]
fn idle_keeps_the_feet_planted() {
    let a = avatar();
    let idle = clip(&a, "idle");
    let rest = joint_positions(&a, &rest_clip(), 0);
    let mut sway = 0.0f32;
    for k in 0..idle.keys() {
        let p = joint_positions(&a, idle, k);
        for ankle in ["l_ankle", "r_ankle"] {
            let j = joint(&a, ankle);
            assert!(p[j].distance(rest[j]) < 0.002, "key {k}: {ankle} slid");
        }
        sway = sway.max((p[0] - rest[0]).length());
        assert!(p[joint(&a, "r_wrist")].y < 1.0);
    }
    assert!(sway > 0.005, "idle does not sway");
}
