//! The tracker solve against ground truth (issue 29, goal 5), and what it costs.
//!
//! Every humanoid BVH clip in `../shared/testdata/bvh` (CMU 01_01 today: 2,752 frames at
//! 120 Hz) gives the solver only what 3 trackers (head, hands) or 6 (and hips, feet) would see,
//! every frame at the clip's own rate (store, then solve at that frame's clock); the solved
//! body is measured against the captured one, beside the naive baseline (tracker rotations
//! copied onto their joints, the root at the hips tracker when there is one).
//! `sim/tests/support/tracker_quality.rs` defines every figure. The built-in avatar's authored
//! clips follow as supplementary rows (not motion capture; not in the summary).
//!
//! Then the cost of `Trackers::solve` alone, µs per avatar per tick on one core, against the
//! issue's goals (≤ 5 µs with 3 trackers, ≤ 10 µs with 6).
//!
//! Run: `cargo bench -p posecast-sim --bench trackers`. Under `cargo test --all-targets` (no
//! `--bench` argument) one short pass checks that it runs.

#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

#[path = "../tests/support/tracker_quality.rs"]
mod quality;

use quality::{Method, Metrics, Setup};

fn main() {
    let full = std::env::args().any(|a| a == "--bench");
    // A short pass when run as a test: the first second of each clip.
    let limit = (!full).then_some(120);
    let mocap = quality::mocap_subjects().unwrap_or_default();
    if mocap.is_empty() {
        eprintln!("no humanoid BVH clip under ../shared/testdata/bvh: built-in clips only");
    }
    let builtin = if full {
        let mut more = quality::gltf_subjects();
        more.extend(quality::builtin_subjects());
        more
    } else {
        Vec::new()
    };
    let setups = quality::setups();

    println!(
        "Tracker solve against ground truth (every frame at the clip's rate; H = body height: \
         skullbase above the lower ankle, standing in the neutral pose){}\n",
        if full {
            ""
        } else {
            " — a short check under cargo test (debug: the times mean nothing)"
        }
    );
    println!("{}", quality::header());
    let mut results: Vec<(Setup, Vec<Metrics>)> = setups.iter().map(|&s| (s, vec![])).collect();
    let mut truths = Vec::new();
    for (i, subject) in mocap.iter().chain(&builtin).enumerate() {
        if i == mocap.len() && !mocap.is_empty() {
            println!(
                "-- supplementary: authored clips of glTF samples and the built-in avatar (not \
                 motion capture)"
            );
        }
        let truth = quality::truth(subject, 1, limit);
        let planted = truth.planted.iter().flatten().filter(|&&p| p).count();
        println!(
            "{} ({}): {} frames at {} Hz, {:.1} s, H = {:.3} m, {} joints mapped, feet planted \
             in {:.0}% of foot-frames",
            subject.label,
            if subject.mocap {
                "motion capture"
            } else {
                "authored"
            },
            truth.times.len(),
            subject.fps,
            truth.dt * (truth.times.len() - 1) as f64,
            truth.height,
            truth.mapped.len(),
            100.0 * planted as f64 / (2 * truth.times.len()) as f64
        );
        for (setup, rows) in &mut results {
            let m = quality::evaluate(subject, &truth, *setup);
            println!("{}", quality::row(&subject.label, &setup.label(), &m));
            if subject.mocap {
                rows.push(m);
            }
        }
        truths.push(truth);
    }

    if !mocap.is_empty() {
        println!(
            "\nSummary over the motion capture ({} clip(s)):",
            mocap.len()
        );
        for (setup, rows) in &results {
            let m = quality::pool(&rows.iter().collect::<Vec<_>>());
            println!("{}", quality::row("all mocap", &setup.label(), &m));
        }
    }

    println!(
        "\nCost of Trackers::solve alone (µs per avatar per tick, one core; store and the pose \
         reset outside the timed region):"
    );
    let seconds = if full { 2.0 } else { 0.0 };
    for (subject, truth) in mocap.iter().chain(&builtin).zip(&truths) {
        for points in [3, 6] {
            for smoothing in [false, true] {
                let c = quality::cost(subject, truth, points, smoothing, seconds);
                let goal = if points == 3 { 5.0 } else { 10.0 };
                println!(
                    "{:<16} {:<18} mean {:>6.2}  p50 {:>6.2}  p99 {:>6.2}  max {:>7.1}  ({} calls; \
                     goal ≤ {goal} µs: {}; timer {:.3} µs included)",
                    subject.label,
                    Setup {
                        points,
                        method: Method::Solver { smoothing }
                    }
                    .label(),
                    c.mean_us,
                    c.p50_us,
                    c.p99_us,
                    c.max_us,
                    c.calls,
                    match (full, c.mean_us <= goal) {
                        (false, _) => "debug build",
                        (true, true) => "met",
                        (true, false) => "MISSED",
                    },
                    c.clock_us,
                );
            }
        }
    }
}
