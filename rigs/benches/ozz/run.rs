//! The bench itself: the cases, the correctness check, criterion, and the summary table.

use std::hint::black_box;
use std::time::{Duration, Instant};

use criterion::Criterion;
use glam::Mat4;
use posecast_proto::fk::forward_kinematics;
use posecast_proto::testing::require_testdata;
use posecast_proto::{Skeleton, Transform};
use posecast_rigs::clip::Clip;
use posecast_rigs::import;
use posecast_rigs::rig::{PipelineOptions, Rig};

use super::animation::Animation;
use super::builder::{RawAnimation, build, raw_from_clip};
use super::check::{Bounds, Worst, compare};
use super::local_to_model_job::{self, NO_PARENT};
use super::sampling_job::{self, Context};
use super::simd::SoaTransform;

/// Ticks per second of the server's simulation.
const TICK_HZ: f64 = 60.0;

/// One clip, ours and ozz's.
struct Case {
    name: &'static str,
    clip: Clip,
    skeleton: Skeleton,
    parents: Vec<i16>,
    raw: RawAnimation,
    animation: Animation,
}

impl Case {
    fn new(name: &'static str, clip: Clip, skeleton: Skeleton) -> Self {
        let raw = raw_from_clip(&clip, skeleton.rest()).expect("a linear BVH clip");
        let animation = build(&raw).expect("the builder accepts the clip");
        let parents = skeleton
            .parents()
            .iter()
            .map(|p| p.map_or(NO_PARENT, |p| i16::try_from(p).expect("≤ 1024 joints")))
            .collect();
        Self {
            name,
            clip,
            skeleton,
            parents,
            raw,
            animation,
        }
    }

    fn joints(&self) -> usize {
        self.skeleton.len()
    }
}

/// A looping layer's clip time at speed 1, seconds from the clip's start, as
/// `Layer::clip_time` computes it from the scene clock (f64, then f32).
fn clip_time(clip: &Clip, clock: f64) -> f32 {
    let d = f64::from(clip.duration().max(0.0));
    let t = if d > 0.0 {
        clock.rem_euclid(d).min(d)
    } else {
        0.0
    };
    t as f32
}

/// Buffers of one pose, both ways.
struct Poses {
    locals: Vec<Transform>,
    world: Vec<Mat4>,
    soa: Vec<SoaTransform>,
    models: Vec<Mat4>,
}

impl Poses {
    fn new(case: &Case) -> Self {
        let n = case.joints();
        Self {
            locals: case.skeleton.rest().to_vec(),
            world: vec![Mat4::IDENTITY; n],
            soa: vec![SoaTransform::IDENTITY; n.div_ceil(4)],
            models: vec![Mat4::IDENTITY; n],
        }
    }
}

/// Checks the port against ours: every 60 Hz tick over 1.1 loops (forward, then the wrap), the
/// middle of every 7th key interval, and 2,000 scrambled times (rewinds). Panics on the first
/// error out of bounds; then panics unless the check rejects a pose with two quaternion
/// components swapped.
fn check(case: &Case) -> Worst {
    let bounds = Bounds::new(&case.raw);
    let clip = &case.clip;
    let rest = case.skeleton.rest();
    let d = clip.duration();
    let mut sampler = clip.sampler();
    let mut context = Context::new(case.joints());
    let mut p = Poses::new(case);
    let mut worst = Worst::default();
    let mut eval = |t: f32, p: &mut Poses, worst: &mut Worst| {
        sampler.sample(clip, clip.start() + t, rest, &mut p.locals);
        forward_kinematics(&case.skeleton, &p.locals, &mut p.world);
        assert!(sampling_job::run(
            &case.animation,
            t / case.animation.duration,
            &mut context,
            &mut p.soa
        ));
        assert!(local_to_model_job::run(
            &case.parents,
            &p.soa,
            &mut p.models
        ));
        if let Err(e) = compare(
            &bounds,
            &case.skeleton,
            t,
            &p.locals,
            &p.world,
            &p.soa,
            &p.models,
            worst,
        ) {
            panic!("{}: the ozz port disagrees with posecast: {e}", case.name);
        }
    };
    let ticks = (f64::from(d) * TICK_HZ * 1.1) as usize;
    for k in 0..ticks {
        eval(clip_time(clip, k as f64 / TICK_HZ), &mut p, &mut worst);
    }
    let keys = case.raw.tracks[0].rotations.clone();
    for w in keys.windows(2).step_by(7) {
        eval((w[0].0 + w[1].0) / 2.0, &mut p, &mut worst);
    }
    let mut u = 0.0f64;
    for _ in 0..2000 {
        u = (u + 0.618_033_988_749_895).fract();
        eval((u * f64::from(d)) as f32, &mut p, &mut worst);
    }

    // Negative control: the same pose with y and z swapped in every rotation must fail.
    let mut broken = p.soa.clone();
    for s in &mut broken {
        std::mem::swap(&mut s.rotation.y, &mut s.rotation.z);
    }
    let mut models = p.models.clone();
    assert!(local_to_model_job::run(&case.parents, &broken, &mut models));
    let mut scratch = Worst::default();
    let rejected = compare(
        &bounds,
        &case.skeleton,
        0.0,
        &p.locals,
        &p.world,
        &broken,
        &models,
        &mut scratch,
    );
    assert!(
        rejected.is_err(),
        "{}: the check accepts a pose with rotation y and z swapped",
        case.name
    );
    worst
}

/// The four per-tick workloads of a case, each running `n` ticks.
type Load<'a> = (String, Box<dyn FnMut(u64) + 'a>);

fn loads(case: &Case) -> Vec<Load<'_>> {
    let clip = &case.clip;
    let rest = case.skeleton.rest();
    let step = 1.0 / TICK_HZ;

    let mut ours = Poses::new(case);
    let mut sampler = clip.sampler();
    let mut clock = 0.0f64;
    let ours_sampling = move |n: u64| {
        for _ in 0..n {
            clock += step;
            let t = clip.start() + clip_time(clip, clock);
            sampler.sample(clip, black_box(t), rest, &mut ours.locals);
            black_box(&ours.locals);
        }
    };

    let mut theirs = Poses::new(case);
    let mut context = Context::new(case.joints());
    let mut clock = 0.0f64;
    let animation = &case.animation;
    let ozz_sampling = move |n: u64| {
        for _ in 0..n {
            clock += step;
            let ratio = clip_time(clip, clock) / animation.duration;
            sampling_job::run(animation, black_box(ratio), &mut context, &mut theirs.soa);
            black_box(&theirs.soa);
        }
    };

    // FK on one mid-clip pose (its cost does not depend on the pose).
    let mut ours = Poses::new(case);
    let mut theirs = Poses::new(case);
    let t = clip.duration() * 0.37;
    clip.sample(clip.start() + t, rest, &mut ours.locals);
    let mut context = Context::new(case.joints());
    sampling_job::run(
        animation,
        t / animation.duration,
        &mut context,
        &mut theirs.soa,
    );
    let skeleton = &case.skeleton;
    let ours_fk = move |n: u64| {
        for _ in 0..n {
            forward_kinematics(skeleton, black_box(&ours.locals), &mut ours.world);
            black_box(&ours.world);
        }
    };
    let parents = &case.parents;
    let ozz_fk = move |n: u64| {
        for _ in 0..n {
            local_to_model_job::run(parents, black_box(&theirs.soa), &mut theirs.models);
            black_box(&theirs.models);
        }
    };
    vec![
        ("sampling/posecast".into(), Box::new(ours_sampling)),
        ("sampling/ozz".into(), Box::new(ozz_sampling)),
        ("fk/posecast".into(), Box::new(ours_fk)),
        ("fk/ozz".into(), Box::new(ozz_fk)),
    ]
}

/// This thread's CPU time (ns) from `/proc/thread-self/schedstat`, where available.
fn thread_cpu_ns() -> Option<u64> {
    let s = std::fs::read_to_string("/proc/thread-self/schedstat").ok()?;
    s.split_whitespace().next()?.parse().ok()
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// Median wall and thread-CPU ns per tick of each load, the loads interleaved round by round
/// so a change of machine load hits all of them alike.
fn measure(loads: &mut [Load<'_>], rounds: usize, batch: Duration) -> Vec<(f64, Option<f64>)> {
    // Ticks per batch from a short calibration run.
    let sizes: Vec<u64> = loads
        .iter_mut()
        .map(|(_, f)| {
            f(1_000);
            let start = Instant::now();
            f(10_000);
            let per = start.elapsed().as_secs_f64() / 10_000.0;
            ((batch.as_secs_f64() / per) as u64).max(100)
        })
        .collect();
    let mut wall = vec![Vec::new(); loads.len()];
    let mut cpu = vec![Vec::new(); loads.len()];
    for _ in 0..rounds {
        for (i, (_, f)) in loads.iter_mut().enumerate() {
            let n = sizes[i];
            let c0 = thread_cpu_ns();
            let start = Instant::now();
            f(n);
            let w = start.elapsed().as_nanos() as f64 / n as f64;
            let c1 = thread_cpu_ns();
            wall[i].push(w);
            if let (Some(a), Some(b)) = (c0, c1) {
                cpu[i].push((b - a) as f64 / n as f64);
            }
        }
    }
    wall.into_iter()
        .zip(cpu)
        .map(|(w, c)| (median(w), (!c.is_empty()).then(|| median(c))))
        .collect()
}

pub fn main() {
    let Some(path) = require_testdata("bvh/cmu/01_01.bvh") else {
        return;
    };
    let asset = import::load_path(&path).unwrap().remove(0);
    let imported = Case::new("imported", asset.clips[0].clone(), asset.skeleton.clone());
    let rig = Rig::from_asset(asset, &PipelineOptions::default()).unwrap();
    let server = Case::new(
        "server rig",
        (*rig.clips[0]).clone(),
        rig.skeleton().clone(),
    );
    let cases = [server, imported];

    for case in &cases {
        let worst = check(case);
        let a = &case.animation;
        println!(
            "{}: {} joints, {} time points; ozz keys T/R/S {}/{}/{} ({} bytes); \
             check passed at {} poses: worst rotation {:.2e} rad ({:.0} % of bound), |q| − 1 \
             {:.1e}, translation {:.2e} ({:.0} %), model columns {:.2e} ({:.0} %), origins \
             {:.2e} ({:.0} %); a pose with y and z swapped is rejected",
            case.name,
            case.joints(),
            a.timepoints.len(),
            a.translations.values.len(),
            a.rotations.values.len(),
            a.scales.values.len(),
            a.size_bytes(),
            worst.samples,
            worst.rotation,
            100.0 * worst.rotation_share,
            worst.norm,
            worst.translation,
            100.0 * worst.translation_share,
            worst.columns,
            100.0 * worst.columns_share,
            worst.origin,
            100.0 * worst.origin_share,
        );
    }

    if !std::env::args().any(|a| a == "--bench") {
        return;
    }

    let mut c = Criterion::default()
        .configure_from_args()
        .warm_up_time(Duration::from_secs(1))
        .measurement_time(Duration::from_secs(2));
    for case in &cases {
        for (name, mut f) in loads(case) {
            c.bench_function(&format!("cmu_01_01/{}/{name}", case.name), |b| {
                b.iter(|| f(1))
            });
        }
    }
    c.final_summary();

    println!();
    println!(
        "Summary: CMU 01_01, forward playback at 60 Hz, ns per joint per tick (median of 21 \
         interleaved batches of ~20 ms; wall / this thread's CPU)"
    );
    println!(
        "| clip | step | posecast wall | ozz port wall | ratio wall | posecast CPU | ozz port CPU \
         | ratio CPU |"
    );
    println!("|---|---|---:|---:|---:|---:|---:|---:|");
    for case in &cases {
        let mut l = loads(case);
        let m = measure(&mut l, 21, Duration::from_millis(20));
        let j = case.joints() as f64;
        let fmt = |x: Option<f64>| x.map_or("–".to_owned(), |x| format!("{:.2}", x / j));
        let ratio = |a: Option<f64>, b: Option<f64>| match (a, b) {
            (Some(a), Some(b)) => format!("{:.2}×", a / b),
            _ => "–".to_owned(),
        };
        for (step, ours, theirs) in [("sampling", 0, 1), ("forward kinematics", 2, 3)] {
            let (ow, oc) = m[ours];
            let (zw, zc) = m[theirs];
            println!(
                "| {} | {step} | {:.2} | {:.2} | {:.2}× | {} | {} | {} |",
                case.name,
                ow / j,
                zw / j,
                ow / zw,
                fmt(oc),
                fmt(zc),
                ratio(oc, zc),
            );
        }
    }
}
