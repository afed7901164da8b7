//! glTF export checked by others: every exported `.glb` (a rig's mesh, a clip of the built-in
//! avatar, of a real glTF rig, of a CSE169 rig, and a recording) passes the Khronos glTF
//! validator (npm `gltf-validator`, run through `scripts/validate-gltf.mjs`) with no errors,
//! and imports back through the server's own glTF importer to the clip's poses.
//!
//! The validator needs `node` and the package under `target/npm` (`scripts/test` installs
//! it). Without them the validation is skipped with a message — and fails under `CI=true`.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use glam::{Quat, Vec3};
use posecast_proto::Transform;
use posecast_proto::description::AvatarDescription;
use posecast_proto::frame::AvatarPose;
use posecast_proto::msg::AvatarId;
use posecast_proto::placement::Placement;
use posecast_proto::testing::{assert_valid_gltf, require_testdata};
use posecast_server::asset::Asset;
use posecast_server::avatar::recording::{RecordLimits, Recorder};
use posecast_server::builtin::AVATAR_GLB;
use posecast_server::clip::{Clip, RotationChannel, VectorChannel};
use posecast_server::export;
use posecast_server::import;
use posecast_server::rig::Rig;
use posecast_server::rig::{PipelineOptions, normalise};

/// Largest difference allowed between a clip and its export read back: the export stores
/// f32 as computed, so this is rounding, far below the stream's quantisation.
const MAX_RADIANS: f32 = 1e-5;
const MAX_METRES: f32 = 1e-5;

/// A normalised rig, as the server makes it from an import.
fn rig(asset: Asset) -> Rig {
    let n = normalise(asset, &PipelineOptions::default()).unwrap();
    Rig::new(n.asset, n.steps, Vec::new(), n.hanim)
}

fn builtin() -> Rig {
    let mut asset = import::gltf::from_slice("avatar.glb", AVATAR_GLB)
        .unwrap()
        .remove(0);
    asset.name = "avatar".into();
    rig(asset)
}

fn testdata_rig(rel: &str) -> Option<Rig> {
    let path = require_testdata(rel)?;
    Some(rig(import::load_path(&path).unwrap().remove(0)))
}

/// Radians between two rotations, precise near zero.
fn angle(a: Quat, b: Quat) -> f32 {
    let d = a.conjugate() * b;
    2.0 * Vec3::new(d.x, d.y, d.z).length().min(1.0).asin()
}

/// Every key time of a clip's key tracks.
fn key_times(clip: &Clip) -> Vec<f32> {
    let mut times = Vec::new();
    for ch in clip.channels() {
        if let Some(RotationChannel::Keys(t)) = &ch.rotation {
            times.extend_from_slice(t.times());
        }
        for v in [&ch.translation, &ch.scale].into_iter().flatten() {
            if let VectorChannel::Keys(t) = v {
                times.extend_from_slice(t.times());
            }
        }
    }
    times.sort_by(f32::total_cmp);
    times.dedup();
    times
}

/// Imports `bytes` with the server's glTF importer and compares its one clip with `clip`
/// (the export's time 0 is the clip's start) at every key of the re-imported clip — where a
/// resampled clip equals its source — and, when `everywhere`, on a fine grid between them.
fn assert_reimports_as(label: &str, rig: &Rig, clip: &Clip, bytes: &[u8], everywhere: bool) {
    let back = import::gltf::from_slice("export.glb", bytes)
        .unwrap_or_else(|e| panic!("{label}: {e}"))
        .remove(0);
    assert_eq!(back.skeleton.names(), rig.skeleton().names(), "{label}");
    assert_eq!(back.skeleton.parents(), rig.skeleton().parents(), "{label}");
    let back_clip = &back.clips[0];
    assert_eq!(back_clip.name(), clip.name());
    assert!(
        (back_clip.duration() - clip.duration()).abs() < 1e-6,
        "{label}"
    );
    let mut times = key_times(back_clip);
    if everywhere {
        times.extend((0..=500).map(|i| i as f32 * clip.duration() / 500.0));
    }
    let rest = rig.skeleton().rest();
    let (mut want, mut got) = (rest.to_vec(), vec![Transform::IDENTITY; rest.len()]);
    let (mut worst_r, mut worst_t) = (0.0f32, 0.0f32);
    for tau in times {
        clip.sample(clip.start() + tau, rest, &mut want);
        back_clip.sample(tau, back.skeleton.rest(), &mut got);
        for (j, (w, g)) in want.iter().zip(&got).enumerate() {
            let r = angle(w.rotation, g.rotation);
            let t = (w.translation - g.translation).length();
            assert!(
                r <= MAX_RADIANS && t <= MAX_METRES,
                "{label}: joint {} at {tau}: {r} rad, {t} m",
                rig.skeleton().names()[j]
            );
            worst_r = worst_r.max(r);
            worst_t = worst_t.max(t);
        }
    }
    eprintln!("{label}: re-imported within {worst_r:e} rad, {worst_t:e} m");
}

#[test]
fn exports_pass_the_khronos_validator_and_reimport_to_the_same_poses() {
    let avatar = builtin();
    let walk = avatar.clip("walk").unwrap().clone();
    let mut files = vec![
        (
            "avatar-mesh",
            export::mesh_glb(avatar.skeleton(), &avatar.asset.meshes).unwrap(),
        ),
        ("avatar-walk", export::clip_glb(&avatar, &walk).unwrap()),
    ];
    assert_reimports_as("avatar walk", &avatar, &walk, &files[1].1, true);
    if let Some(cesium) = testdata_rig("gltf/CesiumMan/glTF-Binary/CesiumMan.glb") {
        let clip = cesium.clips[0].clone();
        let bytes = export::clip_glb(&cesium, &clip).unwrap();
        assert_reimports_as("CesiumMan", &cesium, &clip, &bytes, true);
        files.push(("CesiumMan", bytes));
    }
    if let Some(wasp) = testdata_rig("cse169/wasp.skel") {
        // Hermite Euler curves: resampled, equal at every written key.
        let clip = wasp.clips[0].clone();
        let bytes = export::clip_glb(&wasp, &clip).unwrap();
        assert_reimports_as("wasp_walk", &wasp, &clip, &bytes, false);
        files.push(("wasp_walk", bytes));
    }
    if let Some(rpm) = testdata_rig("gltf/ReadyPlayerMe/PreviewMesh.glb") {
        let bytes = export::mesh_glb(rpm.skeleton(), &rpm.asset.meshes).unwrap();
        assert_morph_targets_as(&rpm, &bytes);
        let rpm = std::sync::Arc::new(rpm);
        // The avatar's description lists the channels and the standard names found on them.
        let avatar = posecast_server::avatar::Avatar::new(AvatarId("rpm".into()), 1, rpm);
        let d = &avatar.description;
        assert_eq!(d.morph_targets.len(), 5);
        for (standard, own) in [
            ("blink", "eyesClosed"),
            ("aa", "mouthOpen"),
            ("jawOpen", "mouthOpen"),
            ("happy", "mouthSmile"),
            ("lookUp", "eyesLookUp"),
            ("lookDown", "eyesLookDown"),
        ] {
            assert_eq!(d.expressions.get(standard).map(String::as_str), Some(own));
        }
        d.to_skeleton().unwrap();
        files.push(("ReadyPlayerMe-mesh", bytes));
    }
    assert_valid_gltf(&files);
}

/// A served `mesh.glb` read with the `gltf` crate: one morph target per channel on every
/// primitive (zeros where a part lacks the channel), named in `mesh.extras.targetNames`, each
/// the normalised rig's own displacements.
fn assert_morph_targets_as(rig: &Rig, bytes: &[u8]) {
    let channels = posecast_proto::morph::channels(rig.asset.meshes.iter().map(|m| &m.mesh));
    assert_eq!(
        channels,
        [
            "mouthOpen",
            "mouthSmile",
            "eyesClosed",
            "eyesLookUp",
            "eyesLookDown"
        ]
    );
    let (doc, buffers, _) = gltf::import_slice(bytes).unwrap();
    let mesh = doc.meshes().next().unwrap();
    let extras: serde_json::Value =
        serde_json::from_str(mesh.extras().as_ref().unwrap().get()).unwrap();
    assert_eq!(extras["targetNames"], serde_json::json!(channels));
    assert_eq!(mesh.weights(), Some(&[0.0; 5][..]));
    let mut moving = std::collections::BTreeSet::new();
    for (prim, ours) in mesh.primitives().zip(&rig.asset.meshes) {
        let reader = prim.reader(|b| Some(&buffers[b.index()]));
        let targets: Vec<Vec<Vec3>> = reader
            .read_morph_targets()
            .map(|(p, _, _)| p.unwrap().map(Vec3::from).collect())
            .collect();
        assert_eq!(targets.len(), channels.len(), "{}", ours.name);
        for (name, file) in channels.iter().zip(&targets) {
            match ours.mesh.targets().iter().find(|t| t.name == *name) {
                Some(t) => {
                    assert_eq!(*file, t.positions, "{} {name}", ours.name);
                    if !t.is_empty() {
                        moving.insert(name.clone());
                    }
                }
                None => assert!(file.iter().all(|d| *d == Vec3::ZERO), "{}", ours.name),
            }
        }
    }
    assert_eq!(
        moving.len(),
        channels.len(),
        "every channel moves some part: {moving:?}"
    );
}

/// What `Avatar::evaluate` streams when the avatar shows `locals`.
fn streamed(d: &AvatarDescription, locals: &[Transform], placement: Placement) -> AvatarPose {
    AvatarPose {
        avatar_num: d.num,
        hash: d.hash_u64(),
        rotations: locals.iter().map(|t| t.rotation).collect(),
        translations: d
            .translated_joints
            .iter()
            .map(|&j| locals[usize::from(j)].translation)
            .collect(),
        scales: d
            .scaled_joints
            .iter()
            .map(|&j| locals[usize::from(j)].scale)
            .collect(),
        placement,
        weights: Vec::new(),
    }
}

#[test]
fn a_recording_exports_valid_gltf_and_bvh_that_reimport_as_the_stream() {
    let avatar = builtin();
    let d = AvatarDescription::new(
        AvatarId("avatar".into()),
        1,
        avatar.name.clone(),
        avatar.skeleton(),
        &avatar.translated,
        &avatar.scaled,
        None,
    );
    // Two seconds at 60 Hz: walk, with an override on the left elbow growing tick by tick.
    let walk = avatar.clip("walk").unwrap();
    let elbow = avatar.skeleton().find("l_elbow").unwrap();
    let rest = avatar.skeleton().rest();
    let mut locals = rest.to_vec();
    let mut recorder = Recorder::new("take", &d, RecordLimits::DEFAULT);
    let mut stream = Vec::new();
    for k in 0..=120 {
        let time = 50.0 + f64::from(k) / 60.0;
        walk.sample(
            walk.wrap_time(time as f32, posecast_server::clip::Wrap::Loop),
            rest,
            &mut locals,
        );
        locals[elbow].rotation = Quat::from_rotation_x(0.01 * k as f32);
        recorder
            .push(time, &streamed(&d, &locals, Placement::IDENTITY))
            .unwrap();
        stream.push((f64::from(k) / 60.0, locals.clone()));
    }
    let take = recorder.finish().unwrap();
    let bytes = export::clip_glb(&avatar, &take).unwrap();
    assert_reimports_as("recording", &avatar, &take, &bytes, true);
    // And against the stream itself, tick by tick.
    let back = import::gltf::from_slice("take.glb", &bytes)
        .unwrap()
        .remove(0);
    let mut got = rest.to_vec();
    for (t, want) in &stream {
        back.clips[0].sample(*t as f32, back.skeleton.rest(), &mut got);
        for (w, g) in want.iter().zip(&got) {
            assert!(angle(w.rotation, g.rotation) <= MAX_RADIANS, "at {t}");
            assert!(
                (w.translation - g.translation).length() <= MAX_METRES,
                "at {t}"
            );
        }
    }
    // The BVH export of the take keeps its 60 Hz ticks as frames.
    let text = export::clip_bvh(&avatar, &take).unwrap();
    assert!(
        text.contains("Frames: 121\n"),
        "{}",
        &text[text.find("MOTION").unwrap()..][..60]
    );
    assert_valid_gltf(&[("recording", bytes)]);
}
