//! The small ones of issue 18 (item 7): a clip of constant tracks keeps the file's time range,
//! a centimetre glTF is guessed as centimetres (and the guess is reported and overridable),
//! CSE169 `.anim` channels may carry their index (`channel 0 {`).

// Helpers outside #[test] fns unwrap too: a failure there is a test failure.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod gltf_support;

use gltf_support::{Bin, builtin_skeleton_glb, glb, triangle};
use posecast_rigs::builtin::skeleton::JOINTS;
use posecast_rigs::import::{anim, gltf, skel};
use posecast_rigs::rig::{PipelineOptions, normalise};
use serde_json::json;

#[test]
fn a_clip_of_constant_tracks_keeps_the_files_time_range() {
    let mut bin = Bin::default();
    let (pos, idx) = triangle(&mut bin);
    let joints = bin.u16s(&[0; 12], "VEC4");
    let weights = bin.floats(&[1.0, 0.0, 0.0, 0.0].repeat(3), "VEC4");
    // Two keys of one value, 0.5 s and 2.5 s: the pose holds for 2 s.
    let times = bin.floats(&[0.5, 2.5], "SCALAR");
    let values = bin.floats(&[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0], "VEC4");
    let mut doc = json!({
        "asset": {"version": "2.0"},
        "scenes": [{"nodes": [0, 1]}],
        "nodes": [{"name": "root"}, {"name": "body", "mesh": 0, "skin": 0}],
        "skins": [{"joints": [0]}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": pos, "JOINTS_0": joints, "WEIGHTS_0": weights}, "indices": idx}]}],
        "animations": [{"name": "hold", "channels": [{"sampler": 0, "target": {"node": 0, "path": "rotation"}}],
                        "samplers": [{"input": times, "output": values}]}]
    });
    bin.finish(&mut doc);
    let asset = gltf::from_slice("hold.glb", &glb(&doc, &bin.bytes))
        .unwrap()
        .remove(0);
    let clip = &asset.clips[0];
    assert_eq!((clip.start(), clip.end()), (0.5, 2.5));
    assert_eq!(clip.duration(), 2.0);
}

#[test]
fn a_centimetre_gltf_is_guessed_and_the_guess_can_be_overridden() {
    // The built-in skeleton 100 times larger: ~157 "metres" tall by the file's word.
    let bytes = builtin_skeleton_glb(100.0, |j| JOINTS[j].name.to_owned(), &[], None);
    let asset = gltf::from_slice("cm.glb", &bytes).unwrap().remove(0);
    let n = normalise(asset.clone(), &PipelineOptions::default()).unwrap();
    let step = n.steps.iter().find(|s| s.starts_with("units")).unwrap();
    println!("{step}");
    assert!(
        step.contains("centimetres") && step.contains("x0.01"),
        "{step}"
    );
    assert_eq!(n.units.metres_per_unit, 0.01);
    assert_eq!(n.units.source, "guessed");
    assert!(
        (150.0..170.0).contains(&n.units.height),
        "{}",
        n.units.height
    );
    let (lo, hi) = n.asset.meshes[0].mesh.bounds();
    assert!(hi.max_element() - lo.min_element() < 3.0, "metres now");
    // Overridden.
    let keep = PipelineOptions {
        metres_per_unit: Some(1.0),
        ..PipelineOptions::default()
    };
    let n = normalise(asset, &keep).unwrap();
    assert_eq!(n.units.source, "configured");
    assert_eq!(n.world_change.1, 1.0);
}

#[test]
fn anim_channels_may_carry_their_index() {
    let skel = skel::parse(
        "arm.skel",
        "balljoint root {\n offset 0 0 0\n balljoint tip {\n offset 0 1 0\n }\n}\n",
    )
    .unwrap();
    let channel = |k: usize, v: f32| {
        format!(
            "channel {k} {{\n extrapolate constant constant\n keys 1 {{\n 0 {v} flat flat\n }}\n}}\n"
        )
    };
    let text = format!(
        "animation {{\n range 0 1\n numchannels 9\n{}}}\n",
        (0..9)
            .map(|k| channel(k, k as f32 * 0.1))
            .collect::<String>()
    );
    let clip = anim::parse("indexed.anim", &text, &skel.skeleton).unwrap();
    let mut locals = skel.skeleton.rest().to_vec();
    clip.sample(0.0, skel.skeleton.rest(), &mut locals);
    // Channel 7 is the tip's y rotation: 0.7 rad.
    let (_, y, _) = locals[1].rotation.to_euler(glam::EulerRot::ZYX);
    assert!((y - 0.7).abs() < 1e-5, "{y}");
    // An index out of place is refused, naming it.
    let wrong = text.replace("channel 3 {", "channel 4 {");
    let e = anim::parse("wrong.anim", &wrong, &skel.skeleton).unwrap_err();
    assert!(e.to_string().contains("channel 4 where channel 3"), "{e}");
}
