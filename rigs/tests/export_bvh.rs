//! BVH export round trip: a clip written by `export::bvh` and read back by the server's own
//! BVH importer reproduces, at every frame, the clip's local rotation of every joint within
//! 0.01° and every joint's local translation (the roots' motion included) within 0.1 mm —
//! on rigs whose rest rotations are not identity (the built-in avatar as imported, before
//! normalisation), on normalised rigs, on real motion capture (CMU 01_01) and on CSE169
//! Hermite curves (resampled).

#![allow(clippy::unwrap_used, clippy::expect_used)]

use glam::{Quat, Vec3};
use posecast_proto::testing::require_testdata;
use posecast_proto::{Skeleton, Transform};
use posecast_rigs::asset::Asset;
use posecast_rigs::builtin::AVATAR_GLB;
use posecast_rigs::clip::{Clip, RotationChannel};
use posecast_rigs::export::bvh::{self, CENTIMETRES_PER_METRE};
use posecast_rigs::import;
use posecast_rigs::rig::{PipelineOptions, normalise};

const MAX_DEGREES: f32 = 0.01;
const MAX_METRES: f32 = 1e-4;

/// Radians between two rotations, precise near zero (unlike `acos` of the dot product).
fn angle(a: Quat, b: Quat) -> f32 {
    let d = a.conjugate() * b;
    2.0 * Vec3::new(d.x, d.y, d.z).length().min(1.0).asin()
}

/// The worst rotation (degrees) and translation (metres) error over every frame and joint.
#[derive(Debug, Default)]
struct Worst {
    frames: usize,
    degrees: f32,
    metres: f32,
}

/// Writes `clip` as BVH, imports the text, and compares every frame with the clip.
fn round_trip(label: &str, skeleton: &Skeleton, clip: &Clip) -> Worst {
    let text = bvh::write(skeleton, clip, None).unwrap();
    let back = import::bvh::parse("export.bvh", &text)
        .unwrap_or_else(|e| panic!("{label}: the export does not import: {e}"));
    assert_eq!(back.skeleton.len(), skeleton.len(), "{label}");
    let index: Vec<usize> = skeleton
        .names()
        .iter()
        .map(|n| {
            back.skeleton
                .find(n)
                .unwrap_or_else(|| panic!("{label}: {n}"))
        })
        .collect();
    let dt: f64 = text
        .lines()
        .find_map(|l| l.strip_prefix("Frame Time: "))
        .unwrap()
        .parse()
        .unwrap();
    let frames: usize = text
        .lines()
        .find_map(|l| l.strip_prefix("Frames: "))
        .unwrap()
        .parse()
        .unwrap();
    let back_clip = &back.clips[0];
    let rest = skeleton.rest();
    let mut want = rest.to_vec();
    let mut got = vec![Transform::IDENTITY; back.skeleton.len()];
    let mut worst = Worst {
        frames,
        ..Worst::default()
    };
    // A keyed clip's frames are its keys; a resampled one's, the uniform grid.
    let keys = clip.channels().iter().find_map(|c| match &c.rotation {
        Some(RotationChannel::Keys(t)) if t.times().len() == frames => Some(t.times()),
        _ => None,
    });
    for i in 0..frames {
        let t = match keys {
            Some(keys) => keys[i],
            None => (f64::from(clip.start()) + i as f64 * dt).min(f64::from(clip.end())) as f32,
        };
        clip.sample(t, rest, &mut want);
        // The importer's key i sits at i · (its f32 frame time).
        back_clip.sample(i as f32 * dt as f32, back.skeleton.rest(), &mut got);
        for (j, w) in want.iter().enumerate() {
            let g = got[index[j]];
            let degrees = angle(w.rotation, g.rotation).to_degrees();
            let metres = (g.translation / CENTIMETRES_PER_METRE - w.translation).length();
            assert!(
                degrees <= MAX_DEGREES && metres <= MAX_METRES,
                "{label}: frame {i}, joint {}: {degrees}° {metres} m",
                skeleton.names()[j]
            );
            worst.degrees = worst.degrees.max(degrees);
            worst.metres = worst.metres.max(metres);
        }
    }
    eprintln!("{label}: {worst:?}");
    worst
}

fn normalised(asset: Asset) -> Asset {
    normalise(asset, &PipelineOptions::default()).unwrap().asset
}

fn builtin() -> Asset {
    import::gltf::from_slice("avatar.glb", AVATAR_GLB)
        .unwrap()
        .remove(0)
}

#[test]
fn builtin_avatar_with_rotated_rest_frames_round_trips() {
    let raw = builtin();
    // The point of this rig: BVH has no rest rotation, so the export must bake it in.
    let turned = raw
        .skeleton
        .rest()
        .iter()
        .filter(|r| angle(r.rotation, Quat::IDENTITY) > 0.1)
        .count();
    assert!(turned > 5, "{turned} joints with a turned rest frame");
    for clip in &raw.clips {
        let w = round_trip(&format!("raw {}", clip.name()), &raw.skeleton, clip);
        // Keyed at 30 Hz: one frame per key.
        assert_eq!(w.frames, (clip.duration() * 30.0).round() as usize + 1);
    }
    let rig = normalised(raw);
    for clip in &rig.clips {
        round_trip(&format!("normalised {}", clip.name()), &rig.skeleton, clip);
    }
}

#[test]
fn cmu_motion_capture_round_trips_frame_for_frame() {
    let Some(path) = require_testdata("bvh/cmu/01_01.bvh") else {
        return;
    };
    let raw = import::load_path(&path).unwrap().remove(0);
    let w = round_trip("CMU 01_01", &raw.skeleton, &raw.clips[0]);
    // 2,752 frames at 120 Hz in the file: the export keeps them.
    assert_eq!(w.frames, 2752);
    let rig = normalised(raw);
    round_trip("CMU 01_01 normalised", &rig.skeleton, &rig.clips[0]);
}

#[test]
fn cse169_curves_are_sampled_at_sixty_hertz() {
    let Some(path) = require_testdata("cse169/wasp.skel") else {
        return;
    };
    let rig = normalised(import::load_path(&path).unwrap().remove(0));
    let clip = &rig.clips[0];
    let w = round_trip("wasp_walk", &rig.skeleton, clip);
    let duration = f64::from(clip.duration());
    assert_eq!(w.frames, (duration * 60.0).ceil() as usize + 1);
}

#[test]
fn the_text_follows_the_documented_conventions() {
    let raw = builtin();
    let text = bvh::write(&raw.skeleton, &raw.clips[0], None).unwrap();
    let lines: Vec<&str> = text.lines().collect();
    assert_eq!(lines[0], "HIERARCHY");
    assert_eq!(lines[1], format!("ROOT {}", raw.skeleton.names()[0]));
    assert_eq!(
        lines[4].trim(),
        "CHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation"
    );
    assert!(lines[5].trim_start().starts_with("JOINT "));
    assert_eq!(lines[8].trim(), "CHANNELS 3 Zrotation Yrotation Xrotation");
    assert!(!text.contains("-0.000000"), "negative zeros");
    // The root's OFFSET is its rest translation in centimetres.
    let offset: Vec<f32> = lines[3]
        .split_whitespace()
        .skip(1)
        .map(|v| v.parse().unwrap())
        .collect();
    let rest = raw.skeleton.rest()[0].translation * 100.0;
    assert!(Vec3::from_slice(&offset).abs_diff_eq(rest, 1e-4));
    assert_eq!(
        text.matches("End Site").count(),
        (0..raw.skeleton.len())
            .filter(|&j| raw.skeleton.children(j).next().is_none())
            .count()
    );
    assert!(text.contains("Frame Time: 0.033333"));
}
