//! Faces (issue 30): what morph weights cost on the wire and to morph on the CPU.
//!
//! **Bytes.** Weight tracks at 60 Hz for 60 s go through the real v2 encoder and decoder
//! (`frame2::StreamEncoder`, a receiver that gets every frame; the server's deltas are against
//! the previous frame a receiver holds, so this is what a viewer keeping up receives). The
//! figure is the whole frames' bytes with the weights minus the same frames without them,
//! per frame; every decoded weight is checked against the stated bound (half of 1/1023).
//! - *talking face*: the 15 Oculus visemes at speech rate (a new viseme every 80 ms, each
//!   cross-faded in and out over 40 ms) and both eyes blinking (150 ms every 4 s), 17
//!   channels;
//! - *ARKit, 10 changing*: 52 channels of which 10 move every frame (issue 30's budget:
//!   ≤ 26 B a frame);
//! - *full ARKit*: 52 channels from a face tracker, every one moving every frame (slow
//!   expressions plus ±0.01 tracker noise).
//!
//! **CPU morphing**: `proto::morph::morph_cpu` (the reference the GPU path is tested against)
//! on Ready Player Me's head with all five targets active: ns per vertex per active target
//! (needs ../shared/testdata; skipped with a note when absent).
//!
//! Run: `cargo bench -p posecast-server --bench faces`. Prints a table; fails only when a
//! decoded weight is out of its bound.

use anyhow::{Result, bail};
use glam::{Quat, Vec3};
use posecast_proto::frame::AvatarPose;
use posecast_proto::frame2::{Frame2Decoder, StreamEncoder};
use posecast_proto::morph::{MAX_WEIGHT_ERROR, morph_cpu};
use posecast_proto::testing::require_testdata;
use std::time::Instant;

const RATE: f32 = 60.0;
const SECONDS: usize = 60;

/// A deterministic pseudo-random stream (xorshift), so runs compare.
struct Rng(u64);
impl Rng {
    fn next(&mut self) -> f32 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        (self.0 >> 40) as f32 / (1u64 << 24) as f32
    }
}

/// A triangular pulse: 0 outside `[start, start + 2·ramp]`, 1 at its middle.
fn pulse(t: f32, start: f32, ramp: f32) -> f32 {
    let x = (t - start) / ramp;
    if (0.0..=2.0).contains(&x) {
        1.0 - (x - 1.0).abs()
    } else {
        0.0
    }
}

fn talking(t: f32, rng_seq: &[usize]) -> Vec<f32> {
    let mut w = vec![0.0f32; 17];
    // A new viseme every 80 ms: each rises over 40 ms from its start and falls over the next.
    let slot = (t / 0.08) as usize;
    for k in [slot.saturating_sub(1), slot] {
        let v = rng_seq[k % rng_seq.len()];
        w[v] = w[v].max(pulse(t, k as f32 * 0.08, 0.04));
    }
    let blink = pulse(t % 4.0, 1.0, 0.075);
    w[15] = blink;
    w[16] = blink;
    w
}

fn arkit(t: f32, moving: usize, rng: &mut Rng) -> Vec<f32> {
    (0..52)
        .map(|c| {
            if c >= moving {
                return 0.2;
            }
            let slow = 0.5 + 0.4 * (t * (0.3 + 0.05 * c as f32) + c as f32).sin();
            (slow + 0.02 * (rng.next() - 0.5)).clamp(0.0, 1.0)
        })
        .collect()
}

struct Row {
    name: &'static str,
    channels: usize,
    mean: f64,
    max: usize,
    key: usize,
}

fn measure(name: &'static str, track: &mut dyn FnMut(f32) -> Vec<f32>) -> Result<Row> {
    let (mut with, mut without) = (StreamEncoder::new(), StreamEncoder::new());
    let mut decoder = Frame2Decoder::new();
    let pose = |weights: Vec<f32>| AvatarPose {
        avatar_num: 1,
        hash: 0xface,
        rotations: vec![Quat::IDENTITY; 3],
        translations: vec![Vec3::Y],
        scales: vec![],
        placement: Default::default(),
        weights,
    };
    let frames = SECONDS * RATE as usize;
    let (mut total, mut max, mut key, mut channels) = (0usize, 0usize, 0usize, 0);
    for i in 0..frames {
        let t = i as f32 / RATE;
        let w = track(t);
        channels = w.len();
        let first = i == 0;
        let (a, _) = with.encode(0, i as u64 + 1, 0, &[pose(w.clone())], first);
        let (b, _) = without.encode(0, i as u64 + 1, 0, &[pose(Vec::new())], first);
        let cost = a.len() - b.len();
        if first {
            key = cost;
        } else {
            total += cost;
            max = max.max(cost);
        }
        let got = decoder.decode(&a)?;
        for (d, s) in got.avatars[0].weights.iter().zip(&w) {
            if (d - s).abs() > MAX_WEIGHT_ERROR + 1e-7 {
                bail!("{name}: frame {i} decoded {d} for {s}");
            }
        }
    }
    Ok(Row {
        name,
        channels,
        mean: total as f64 / (frames - 1) as f64,
        max,
        key,
    })
}

fn morph_figure() -> Result<()> {
    let Some(path) = require_testdata("gltf/ReadyPlayerMe/PreviewMesh.glb") else {
        println!("CPU morphing: skipped (no ../shared/testdata)");
        return Ok(());
    };
    let asset = posecast_server::import::load_path(&path)?.remove(0);
    let Some(head) = asset.meshes.iter().find(|m| m.name == "Wolf3D_Head") else {
        bail!("Ready Player Me has no Wolf3D_Head");
    };
    let mesh = &head.mesh;
    let targets = mesh.targets().len();
    let n = mesh.vertex_count();
    let weights = vec![0.5; targets];
    let (mut p, mut nrm) = (vec![Vec3::ZERO; n], vec![Vec3::ZERO; n]);
    let runs = 400;
    let start = Instant::now();
    for _ in 0..runs {
        morph_cpu(mesh, &weights, &mut p, &mut nrm);
        std::hint::black_box(&p);
    }
    let per = start.elapsed().as_nanos() as f64 / f64::from(runs);
    println!(
        "CPU morphing (proto::morph::morph_cpu, Ready Player Me head: {n} vertices, {targets} \
         targets at 0.5): {:.1} µs a mesh, {:.2} ns per vertex per active target",
        per / 1e3,
        per / (n * targets) as f64
    );
    Ok(())
}

fn main() -> Result<()> {
    let mut rng = Rng(0x9e37_79b9_7f4a_7c15);
    let sequence: Vec<usize> = (0..1000)
        .map(|_| (rng.next() * 15.0) as usize % 15)
        .collect();
    let mut noise = Rng(42);
    let mut noise2 = Rng(7);
    let rows = [
        measure("talking face (15 visemes + 2 blinks)", &mut |t| {
            talking(t, &sequence)
        })?,
        measure("ARKit, 10 of 52 changing", &mut |t| {
            arkit(t, 10, &mut noise)
        })?,
        measure("full ARKit, all 52 changing", &mut |t| {
            arkit(t, 52, &mut noise2)
        })?,
    ];
    println!("| weights at 60 Hz | channels | B/frame (mean) | B/frame (max) | keyframe B |");
    println!("|---|---:|---:|---:|---:|");
    for r in &rows {
        println!(
            "| {} | {} | {:.2} | {} | {} |",
            r.name, r.channels, r.mean, r.max, r.key
        );
    }
    println!("every decoded weight within {MAX_WEIGHT_ERROR:.6} (1/2046) of the weight sent");
    morph_figure()
}
