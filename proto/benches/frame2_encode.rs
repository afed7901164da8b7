//! Wire v2's cost per avatar-frame: quantising a pose into levels, coding a delta against the
//! receiver's last 8 frames, and decoding it — for a 31-joint rig (CMU 01_01's size) moving
//! like motion capture (every joint turning at a slowly wandering angular velocity, the root
//! walking), at the finest precision and on a 0.1° grid (protocol 5, and 6 with near-axis
//! steps), as a chunk of a kind 2 delta and of a packed one (protocol 7), over datagrams 4
//! ticks past the frames named (kinds 4 and 5, protocols 8 and 9), and putting a pose's levels
//! on that grid.
//!
//! `cargo bench -p posecast-proto --bench frame2_encode`

use criterion::{Criterion, black_box, criterion_group, criterion_main};
use glam::{Quat, Vec3};
use posecast_proto::frame::{AvatarPose, FrameHeader, FrameKind};
use posecast_proto::frame2::{self, Frame2Decoder, PackedDeltas, QuantPose, StreamEncoder};
use posecast_proto::placement::Placement;
use posecast_proto::precision::{self, Steps};
use std::sync::Arc;

const JOINTS: usize = 31;

/// `frames` poses of a rig of [`JOINTS`] joints moving smoothly (seeded, deterministic).
fn motion(frames: usize) -> Vec<AvatarPose> {
    let mut seed = 0x9e37_79b9_7f4a_7c15u64;
    let mut rnd = move || {
        seed ^= seed << 13;
        seed ^= seed >> 7;
        seed ^= seed << 17;
        (seed >> 11) as f32 / (1u64 << 53) as f32 * 2.0 - 1.0
    };
    let mut rotations: Vec<Quat> = (0..JOINTS)
        .map(|_| Quat::from_scaled_axis(Vec3::new(rnd(), rnd(), rnd())))
        .collect();
    let mut spin: Vec<Vec3> = (0..JOINTS).map(|_| Vec3::ZERO).collect();
    let mut root = Vec3::new(0.0, 0.9, 0.0);
    (0..frames)
        .map(|_| {
            for (q, w) in rotations.iter_mut().zip(&mut spin) {
                *w = (*w + Vec3::new(rnd(), rnd(), rnd()) * 0.004).clamp_length_max(0.05);
                *q = (Quat::from_scaled_axis(*w) * *q).normalize();
            }
            root += Vec3::new(0.02, 0.001 * rnd(), 0.0);
            AvatarPose {
                avatar_num: 1,
                hash: 7,
                rotations: rotations.clone(),
                translations: vec![root],
                scales: Vec::new(),
                placement: Placement::IDENTITY,
                weights: Vec::new(),
            }
        })
        .collect()
}

fn bench(c: &mut Criterion) {
    let poses = motion(600);
    let levels: Vec<QuantPose> = poses.iter().map(QuantPose::from_pose).collect();
    c.bench_function("quantise a 31-joint pose (QuantPose::from_pose)", |b| {
        let mut i = 0;
        b.iter(|| {
            i = (i + 1) % poses.len();
            black_box(QuantPose::from_pose(black_box(&poses[i])))
        })
    });
    let mut out = Vec::with_capacity(256);
    // Over datagrams (protocols 8 and 9): a delta 4 ticks past the newest of the 8 frames it
    // names (a round trip at 25 ms each way), predicted a tick on (kind 4) or over the ticks
    // between (kind 5).
    for kind in [
        frame2::ReferencedKind::Frames,
        frame2::ReferencedKind::Ticks,
    ] {
        let label = match kind {
            frame2::ReferencedKind::Frames => "kind 4",
            frame2::ReferencedKind::Ticks => "kind 5",
        };
        let bytes: usize = (12..levels.len())
            .map(|i| {
                let refs: Vec<u64> = (0..8).map(|k| (i - 4 - k) as u64).collect();
                let history: Vec<&QuantPose> = refs.iter().map(|&r| &levels[r as usize]).collect();
                out.clear();
                let spacing = kind.spacing(i as u64, &refs);
                frame2::encode_referenced_delta(1, &levels[i], &history, spacing, &mut out);
                out.len()
            })
            .sum();
        println!(
            "{label}, 4 ticks on: {:.2} B/joint/frame",
            bytes as f64 / (levels.len() - 12) as f64 / JOINTS as f64
        );
        c.bench_function(
            &format!("{label} delta 4 ticks on, depth 8, 31 joints"),
            |b| {
                let mut i = 12;
                b.iter(|| {
                    i = if i + 1 >= levels.len() { 12 } else { i + 1 };
                    let refs: [u64; 8] = std::array::from_fn(|k| (i - 4 - k) as u64);
                    let history: [&QuantPose; 8] =
                        std::array::from_fn(|k| &levels[refs[k] as usize]);
                    out.clear();
                    let spacing = kind.spacing(i as u64, &refs);
                    frame2::encode_referenced_delta(
                        1,
                        black_box(&levels[i]),
                        &history,
                        spacing,
                        &mut out,
                    );
                    black_box(out.len())
                })
            },
        );
    }
    for (label, steps) in [
        ("finest", None),
        (
            "0.1°",
            Some(Arc::new(Steps {
                rotations: vec![precision::rotation_step_for(0.1); JOINTS],
                translation: 1,
                near: Vec::new(),
            })),
        ),
        (
            "0.1°, near-axis steps (protocol 6)",
            Some(Arc::new(Steps {
                rotations: vec![precision::rotation_step_for(0.1); JOINTS],
                translation: 1,
                near: vec![precision::near_rotation_step_for(0.1); JOINTS],
            })),
        ),
    ] {
        if let Some(s) = &steps {
            // Putting a tick's levels on the grid: once per tick, avatar and precision.
            c.bench_function(&format!("grid values of a 31-joint pose, {label}"), |b| {
                let mut i = 0;
                b.iter(|| {
                    i = (i + 1) % levels.len();
                    black_box(levels[i].coarsen(black_box(s)))
                })
            });
        }
        let levels: Vec<QuantPose> = match &steps {
            Some(s) => levels.iter().map(|l| l.coarsen(s)).collect(),
            None => levels.clone(),
        };
        c.bench_function(&format!("delta of depth 8, 31 joints, {label}"), |b| {
            let mut i = 8;
            b.iter(|| {
                i = if i + 1 >= levels.len() { 8 } else { i + 1 };
                let history: [&QuantPose; 8] = std::array::from_fn(|k| &levels[i - 1 - k]);
                out.clear();
                frame2::encode_delta(1, black_box(&levels[i]), &history, &mut out);
                black_box(out.len())
            })
        });
        // The same as one chunk of a packed delta (protocol 7), its header included.
        c.bench_function(
            &format!("packed delta of depth 8, 31 joints, {label}"),
            |b| {
                let mut i = 8;
                b.iter(|| {
                    i = if i + 1 >= levels.len() { 8 } else { i + 1 };
                    let history: [&QuantPose; 8] = std::array::from_fn(|k| &levels[i - 1 - k]);
                    out.clear();
                    let header = FrameHeader {
                        kind: FrameKind::Delta,
                        scene_num: 1,
                        seq: i as u64 + 1,
                        server_time_us: 1_750_000_000_000_000 + i as u64 * 16_667,
                        base_seq: i as u64,
                    };
                    let base_time = header.server_time_us - 16_667;
                    let mut packed = PackedDeltas::new(&header, base_time, 1, &mut out);
                    packed.push(1, black_box(&levels[i]), &history);
                    packed.finish();
                    black_box(out.len())
                })
            },
        );
        let mut encoder = StreamEncoder::new();
        if let Some(s) = &steps {
            encoder.set_steps(1, s.clone());
        }
        let frames: Vec<Vec<u8>> = poses
            .iter()
            .enumerate()
            .map(|(i, p)| {
                encoder
                    .encode(1, i as u64 + 1, 0, std::slice::from_ref(p), i % 60 == 0)
                    .0
            })
            .collect();
        let bytes: usize = frames.iter().map(Vec::len).sum();
        println!(
            "{label}: {:.2} B/joint/frame over {} frames (keyframe a second)",
            bytes as f64 / frames.len() as f64 / JOINTS as f64,
            frames.len()
        );
        c.bench_function(&format!("decode 600 frames, 31 joints, {label}"), |b| {
            b.iter(|| {
                let mut d = Frame2Decoder::new();
                for f in &frames {
                    black_box(d.decode_levels(f).is_ok());
                }
            })
        });
    }
}

criterion_group!(benches, bench);
criterion_main!(benches);
