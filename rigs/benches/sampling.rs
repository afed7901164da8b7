//! Clip sampling cost per pose: exact random access (`Clip::sample`) against the cursor
//! `Sampler` in forward playback, on CMU 01_01 (31 joints, 2,752 frames at 120 fps) and a
//! 65-joint clip made of CMU 01_01's channels repeated.
//!
//! Run: `cargo bench -p posecast-server --bench sampling` (needs ../shared/testdata).

#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use posecast_proto::Transform;
use posecast_proto::testing::testdata;
use posecast_rigs::clip::Clip;
use posecast_rigs::import;

fn cases() -> Option<Vec<(String, Clip, Vec<Transform>)>> {
    let path = testdata("bvh/cmu/01_01.bvh");
    if !path.exists() {
        eprintln!("skipping: {} is absent", path.display());
        return None;
    }
    let asset = import::load_path(&path).unwrap().remove(0);
    let clip = asset.clips[0].clone();
    let rest = asset.skeleton.rest().to_vec();
    let n = 65;
    let source: Vec<Option<usize>> = (0..n).map(|i| Some(i % rest.len())).collect();
    let big = clip.remap_joints(&source);
    let big_rest = (0..n).map(|i| rest[i % rest.len()]).collect();
    Some(vec![
        (format!("cmu_01_01_{}j", rest.len()), clip, rest),
        (format!("cmu_x2_{n}j"), big, big_rest),
    ])
}

fn sampling(c: &mut Criterion) {
    let Some(cases) = cases() else { return };
    for (name, clip, rest) in &cases {
        let mut out = vec![Transform::IDENTITY; rest.len()];
        let step = 1.0 / 60.0;
        let mut t = clip.start();
        c.bench_function(&format!("{name}/exact_forward"), |b| {
            b.iter(|| {
                t = clip.wrap_time(t + step, posecast_rigs::clip::Wrap::Loop);
                clip.sample(black_box(t), rest, &mut out);
                black_box(&out);
            })
        });
        // Random access: a scrambled time sequence (golden-ratio stride).
        let mut u = 0.0f32;
        c.bench_function(&format!("{name}/exact_random"), |b| {
            b.iter(|| {
                u = (u + 0.618_034).fract();
                clip.sample(
                    black_box(clip.start() + u * clip.duration()),
                    rest,
                    &mut out,
                );
                black_box(&out);
            })
        });
        let mut sampler = clip.sampler();
        let mut t = clip.start();
        c.bench_function(&format!("{name}/sampler_forward"), |b| {
            b.iter(|| {
                t = clip.wrap_time(t + step, posecast_rigs::clip::Wrap::Loop);
                sampler.sample(clip, black_box(t), rest, &mut out);
                black_box(&out);
            })
        });
    }
}

criterion_group!(benches, sampling);
criterion_main!(benches);
