//! Helpers shared by the `rig_*` tests: the shared test rigs, random rigs, and the skinned
//! mesh / world joint positions of an asset at every key time of every clip.
#![allow(dead_code, clippy::expect_used, clippy::unwrap_used)]

use glam::{Mat4, Quat, Vec3};
use posecast_proto::fk::{PoseBuffers, forward_kinematics};
use posecast_proto::skinning::skin_cpu;
use posecast_proto::testing::{arb_parents, arb_quat, f32s, require_testdata};
use posecast_proto::{Skeleton, SkinnedMesh, Transform};
use posecast_rigs::asset::{Asset, AssetMesh, SourceFormat, SourceInfo};
use posecast_rigs::builtin::AVATAR_GLB;
use posecast_rigs::clip::{
    Clip, Interpolation, JointChannels, RotationChannel, Track, VectorChannel,
};
use posecast_rigs::import::{gltf, load_path};
use proptest::prelude::*;

/// Loads a shared test file (every asset in it); `None`, with a message, when it is missing.
pub fn load(rel: &str) -> Option<Vec<Asset>> {
    let path = require_testdata(rel)?;
    Some(load_path(&path).unwrap_or_else(|e| panic!("{rel}: {e}")))
}

/// The built-in avatar.
pub fn builtin() -> Asset {
    gltf::from_slice("avatar", AVATAR_GLB)
        .expect("built-in avatar loads")
        .remove(0)
}

/// Every rig in ../shared/testdata (a few of RecursiveSkeletons' 4) and the built-in avatar.
pub fn all_rigs() -> Vec<Asset> {
    let mut out = Vec::new();
    for rel in [
        "gltf/RiggedSimple/glTF-Binary/RiggedSimple.glb",
        "gltf/RiggedFigure/glTF-Binary/RiggedFigure.glb",
        "gltf/CesiumMan/glTF-Binary/CesiumMan.glb",
        "gltf/SimpleSkin/glTF/SimpleSkin.gltf",
        "cse169/wasp.skel",
        "cse169/tube.skel",
        "cse169/test.skel",
        "bvh/cmu/01_01.bvh",
        "bvh/fairmotion/sinusoidal.bvh",
        "bvh/bvh_anim/test_simple.bvh",
    ] {
        out.extend(load(rel).into_iter().flatten());
    }
    if let Some(rs) = load("gltf/RecursiveSkeletons/glTF-Binary/RecursiveSkeletons.glb") {
        // The first few, and a few with helper joints or scaled joints.
        let mut picked: Vec<Asset> = rs.iter().take(3).cloned().collect();
        picked.extend(
            rs.iter()
                .skip(3)
                .filter(|a| {
                    !a.source.helper_joints.is_empty()
                        || a.skeleton.rest().iter().any(|t| t.scale != Vec3::ONE)
                })
                .take(3)
                .cloned(),
        );
        out.extend(picked);
    }
    out.push(builtin());
    out
}

/// Every key time of every channel of a clip, with its start and end, sorted and deduplicated.
pub fn key_times(clip: &Clip) -> Vec<f32> {
    let mut t = vec![clip.start(), clip.end()];
    for ch in clip.channels() {
        match &ch.rotation {
            Some(RotationChannel::Keys(k)) => t.extend_from_slice(k.times()),
            Some(RotationChannel::Euler(c)) => {
                c.iter().for_each(|c| t.extend_from_slice(c.times()))
            }
            None => {}
        }
        for v in [&ch.translation, &ch.scale].into_iter().flatten() {
            match v {
                VectorChannel::Keys(k) => t.extend_from_slice(k.times()),
                VectorChannel::Curves(c) => c.iter().for_each(|c| t.extend_from_slice(c.times())),
            }
        }
    }
    t.sort_by(f32::total_cmp);
    t.dedup();
    t
}

/// Skinned vertices (all meshes) and world joint positions of a pose.
pub fn snapshot(asset: &Asset, locals: &[Transform]) -> (Vec<Vec3>, Vec<Vec3>) {
    let sk = &asset.skeleton;
    let mut b = PoseBuffers::new(sk);
    b.update(sk, locals);
    let mut verts = Vec::new();
    for m in &asset.meshes {
        let n = m.mesh.vertex_count();
        let mut p = vec![Vec3::ZERO; n];
        let mut nn = vec![Vec3::ZERO; n];
        skin_cpu(&m.mesh, &b.skinning, &mut p, &mut nn);
        verts.extend(p);
    }
    let joints = b.world.iter().map(|w| w.w_axis.truncate()).collect();
    (verts, joints)
}

/// Snapshots of the rest pose and of every key time of every clip.
pub fn all_poses(asset: &Asset) -> Vec<(Vec<Vec3>, Vec<Vec3>)> {
    let sk = &asset.skeleton;
    let mut out = vec![snapshot(asset, sk.rest())];
    let mut locals = sk.rest().to_vec();
    for clip in &asset.clips {
        for t in key_times(clip) {
            clip.sample(t, sk.rest(), &mut locals);
            out.push(snapshot(asset, &locals));
        }
    }
    out
}

/// The largest extent of the rest pose's vertices and joints (the model's height, whatever
/// its up axis).
pub fn model_size(asset: &Asset) -> f32 {
    let (v, j) = snapshot(asset, asset.skeleton.rest());
    let (lo, hi) = v.iter().chain(&j).fold(
        (Vec3::splat(f32::MAX), Vec3::splat(f32::MIN)),
        |(lo, hi), &p| (lo.min(p), hi.max(p)),
    );
    (hi - lo).max_element().max(1e-6)
}

/// The largest distance, over all poses, between `after`'s points and `f` of `before`'s,
/// relative to the model's size: (vertices, joints). Both assets must have the same clips.
pub fn deviation(before: &Asset, after: &Asset, f: impl Fn(Vec3) -> Vec3) -> (f32, f32) {
    let size = model_size(before);
    let (a, b) = (all_poses(before), all_poses(after));
    assert_eq!(a.len(), b.len(), "{}: pose counts differ", before.name);
    let mut worst = (0.0f32, 0.0f32);
    for ((av, aj), (bv, bj)) in a.iter().zip(&b) {
        for (x, y) in av.iter().zip(bv) {
            worst.0 = worst.0.max((f(*x) - *y).length() / size);
        }
        for (x, y) in aj.iter().zip(bj) {
            worst.1 = worst.1.max((f(*x) - *y).length() / size);
        }
    }
    worst
}

/// A random rig: rigid joints with uniform scale, a bind pose that differs from the rest
/// pose by a random rotation per joint (or equals it), a mesh skinned to two joints per
/// vertex, and a clip rotating every joint and translating the root.
pub fn arb_asset(
    joints: std::ops::Range<usize>,
    rest_is_bind: bool,
) -> impl Strategy<Value = Asset> {
    arb_parents(joints).prop_flat_map(move |parents| {
        let n = parents.len();
        (
            Just(parents),
            prop::collection::vec(
                (
                    prop::array::uniform3(f32s(-1.0..1.0)),
                    arb_quat(),
                    f32s(0.8..1.25),
                    arb_quat(),
                ),
                n,
            ),
            prop::collection::vec(
                (
                    prop::array::uniform3(f32s(-2.0..2.0)),
                    0u16..1000,
                    0u16..1000,
                    f32s(0.0..1.0),
                ),
                1..40,
            ),
            prop::collection::vec((arb_quat(), arb_quat()), n),
            prop::array::uniform3(f32s(-1.0..1.0)),
        )
            .prop_map(move |(parents, joints, verts, keys, root_move)| {
                build_asset(
                    parents,
                    &joints,
                    &verts,
                    &keys,
                    Vec3::from(root_move),
                    rest_is_bind,
                )
            })
    })
}

type JointSeed = ([f32; 3], Quat, f32, Quat);
type VertexSeed = ([f32; 3], u16, u16, f32);

fn build_asset(
    parents: Vec<Option<usize>>,
    joints: &[JointSeed],
    verts: &[VertexSeed],
    keys: &[(Quat, Quat)],
    root_move: Vec3,
    rest_is_bind: bool,
) -> Asset {
    let n = parents.len();
    let rest: Vec<Transform> = joints
        .iter()
        .map(|(t, r, s, _)| Transform {
            translation: Vec3::from(*t),
            rotation: *r,
            scale: Vec3::splat(*s),
        })
        .collect();
    let names: Vec<String> = (0..n).map(|j| format!("j{j}")).collect();
    let provisional = Skeleton::new(
        names.clone(),
        parents.clone(),
        rest.clone(),
        vec![Mat4::IDENTITY; n],
    )
    .expect("valid");
    let mut world = vec![Mat4::IDENTITY; n];
    forward_kinematics(&provisional, &rest, &mut world);
    let inverse_bind = world
        .iter()
        .zip(joints)
        .map(|(w, (_, _, _, x))| {
            let bind = if rest_is_bind {
                *w
            } else {
                *w * Mat4::from_quat(*x)
            };
            bind.inverse()
        })
        .collect();
    let skeleton = Skeleton::new(names, parents, rest, inverse_bind).expect("valid");
    let mesh = SkinnedMesh::new(
        verts.iter().map(|v| Vec3::from(v.0)).collect(),
        verts
            .iter()
            .map(|v| Vec3::new(v.0[1], v.0[2], v.0[0] + 3.0).normalize())
            .collect(),
        vec![],
        2,
        verts
            .iter()
            .flat_map(|v| [v.1 % n as u16, v.2 % n as u16])
            .collect(),
        verts.iter().flat_map(|v| [v.3, 1.0 - v.3]).collect(),
        n,
    )
    .expect("valid mesh");
    let channels = keys
        .iter()
        .enumerate()
        .map(|(j, (a, b))| JointChannels {
            rotation: Some(RotationChannel::Keys(
                Track::new(Interpolation::Linear, vec![0.0, 0.5, 1.0], vec![*a, *b, *a])
                    .expect("valid track"),
            )),
            translation: (j == 0).then(|| {
                VectorChannel::Keys(
                    Track::new(
                        Interpolation::Linear,
                        vec![0.0, 1.0],
                        vec![Vec3::ZERO, root_move],
                    )
                    .expect("valid track"),
                )
            }),
            ..Default::default()
        })
        .collect();
    let clip = Clip::new("random", channels, None).expect("valid clip");
    Asset {
        name: "random".into(),
        skeleton,
        meshes: vec![AssetMesh {
            name: "mesh".into(),
            mesh,
        }],
        clips: vec![clip],
        source: SourceInfo::new(SourceFormat::Gltf),
        boxes: None,
        expressions: Vec::new(),
    }
}

/// The same asset with every joint scale set to one and binds at rest (a rigid rig).
pub fn rigid(asset: Asset) -> Asset {
    let sk = &asset.skeleton;
    let rest: Vec<Transform> = sk
        .rest()
        .iter()
        .map(|t| Transform {
            scale: Vec3::ONE,
            ..*t
        })
        .collect();
    let provisional = Skeleton::new(
        sk.names().to_vec(),
        sk.parents().to_vec(),
        rest.clone(),
        vec![Mat4::IDENTITY; sk.len()],
    )
    .expect("valid");
    let mut world = vec![Mat4::IDENTITY; sk.len()];
    forward_kinematics(&provisional, &rest, &mut world);
    let skeleton = Skeleton::new(
        sk.names().to_vec(),
        sk.parents().to_vec(),
        rest,
        world.iter().map(Mat4::inverse).collect(),
    )
    .expect("valid");
    Asset { skeleton, ..asset }
}
