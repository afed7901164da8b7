//! Playback features checked on the pose stream against the built-in clips sampled here:
//! cross-fades, negative speed, and ticks missed under load.
//!
//! The tests do not assume at which tick a command took effect. They find the clip time (or
//! the fade weight) each streamed pose shows, independently of the server, and check how it
//! moves from frame to frame: by `speed / tick_rate` of clip time per tick, or by
//! `1 / (tick_rate · fade)` of weight per tick.
//!
//! Servers, clients, fresh poses and the clips' sampling come from `posecast-testkit`.

#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use common::{http, kit_server};
use glam::Quat;
use posecast_proto::Transform;
use posecast_proto::command::Command;
use posecast_proto::msg::AvatarId;
use posecast_proto::quant::angle_between_degrees;
use posecast_server::rig::Rig;
use posecast_testkit::{DEFAULT_TIMEOUT, StreamedPose, TestClient, sample_clip};
use std::time::Duration;

const AVATAR: &str = "avatar";

fn avatar() -> AvatarId {
    AvatarId(AVATAR.into())
}

/// The clip sampled at clip time `t` (wrapped into one cycle: the clips loop).
fn sample(rig: &Rig, clip: &str, t: f32) -> Vec<Transform> {
    let duration = rig.clip(clip).unwrap().duration();
    sample_clip(rig, clip, t.rem_euclid(duration)).unwrap()
}

/// The worst rotation difference between two poses, degrees.
fn worst(a: &[Transform], b: &[Transform]) -> f64 {
    a.iter()
        .zip(b)
        .map(|(x, y)| angle_between_degrees(x.rotation, y.rotation))
        .fold(0.0, f64::max)
}

/// The clip time whose pose `locals` shows: a 1 ms grid over one cycle, then a golden-section
/// search around the best point. Returns the time and the worst joint's error there.
fn clip_time_of(rig: &Rig, clip: &str, locals: &[Transform]) -> (f32, f64) {
    let cost = |t: f32| -> f64 {
        sample(rig, clip, t)
            .iter()
            .zip(locals)
            .map(|(x, y)| angle_between_degrees(x.rotation, y.rotation).powi(2))
            .sum()
    };
    let duration = rig.clip(clip).unwrap().duration();
    let steps = (duration * 1000.0).round() as usize;
    let (best, _) = (0..steps)
        .map(|i| {
            let t = i as f32 / 1000.0;
            (t, cost(t))
        })
        .min_by(|a, b| a.1.total_cmp(&b.1))
        .unwrap();
    let (mut lo, mut hi) = (best - 1e-3, best + 1e-3);
    let ratio = (5f32.sqrt() - 1.0) / 2.0;
    for _ in 0..40 {
        let m1 = hi - ratio * (hi - lo);
        let m2 = lo + ratio * (hi - lo);
        if cost(m1) < cost(m2) {
            hi = m2;
        } else {
            lo = m1;
        }
    }
    let t = ((lo + hi) / 2.0).rem_euclid(duration);
    (t, worst(&sample(rig, clip, t), locals))
}

/// How far clip time `b` is from `a + expected`, both taken in one loop of `period`.
fn loop_distance(a: f32, b: f32, expected: f32, period: f32) -> f32 {
    let d = (b - a - expected).rem_euclid(period);
    d.min(period - d)
}

/// The seq before the first frame that shows every command acknowledged so far: every later
/// frame shows their effect.
async fn settle(c: &TestClient) -> u64 {
    c.fresh_pose(AVATAR, DEFAULT_TIMEOUT).await.unwrap().seq() - 1
}

/// Distinct poses streamed after seq `after`, for `secs` seconds.
async fn record(c: &TestClient, after: u64, secs: f32) -> Vec<StreamedPose> {
    c.collect_poses(AVATAR, after, Duration::from_secs_f32(secs))
        .await
}

fn play(clip: &str, start: f32, speed: f32, fade: f32) -> Command {
    Command::Play {
        avatar: avatar(),
        clip: clip.into(),
        from_asset: None,
        speed: Some(speed),
        looping: Some(true),
        start: Some(start),
        fade: Some(fade),
        // The authored root translation (these tests compare with raw clip samples; the
        // clocks here never wrap, so nothing accumulates).
        root_motion: Some(posecast_proto::command::RootMotion::Accumulate),
    }
}

/// Shortest-arc slerp, written here rather than taken from the server.
fn slerp(a: Quat, b: Quat, w: f32) -> Quat {
    let b = if a.dot(b) < 0.0 { -b } else { b };
    a.slerp(b, w).normalize()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_cross_fade_streams_the_slerp_of_both_clips() {
    let rate = 30.0f32;
    let fade = 1.0f32;
    let rig = posecast_server::builtin::rig().unwrap();
    let server = kit_server(rate).await;
    let c = server.client().await.unwrap();
    c.first_pose(AVATAR, DEFAULT_TIMEOUT).await.unwrap();
    // Both clips frozen (speed 0), so only the fade weight moves.
    let from = sample(&rig, "walk", 0.3);
    let to = sample(&rig, "wave", 0.8);
    c.command(play("walk", 0.3, 0.0, 0.0)).await.unwrap();
    let after = settle(&c).await;
    let held = record(&c, after, 0.2).await;
    assert!(!held.is_empty());
    assert!(worst(held[0].locals(), &from) <= 0.01, "not the walk pose");
    c.command(play("wave", 0.8, 0.0, fade)).await.unwrap();
    let after = settle(&c).await;
    let streamed = record(&c, after, 1.6).await;
    // The weight each pose shows, from the joint that turns most between the two poses:
    // slerp turns at a constant rate, so w = angle(from, pose) / angle(from, to).
    let (j, span) = from
        .iter()
        .zip(&to)
        .map(|(a, b)| angle_between_degrees(a.rotation, b.rotation))
        .enumerate()
        .max_by(|a, b| a.1.total_cmp(&b.1))
        .unwrap();
    assert!(span > 20.0, "the clips barely differ ({span}°)");
    let mut weights = Vec::new();
    for p in &streamed {
        let w = (angle_between_degrees(from[j].rotation, p.locals()[j].rotation) / span) as f32;
        let w = w.min(1.0);
        // Every joint is on its own slerp at that weight, the root translation on its lerp.
        let expected: Vec<Transform> = from
            .iter()
            .zip(&to)
            .map(|(a, b)| Transform {
                translation: a.translation.lerp(b.translation, w),
                rotation: slerp(a.rotation, b.rotation, w),
                scale: a.scale,
            })
            .collect();
        let err = worst(p.locals(), &expected);
        assert!(
            err < 0.03,
            "seq {} (w {w:.3}): {err}° off the slerp",
            p.seq()
        );
        let moved = p
            .locals()
            .iter()
            .zip(&expected)
            .map(|(a, b)| a.translation.distance(b.translation))
            .fold(0.0, f32::max);
        assert!(
            moved < 1e-4,
            "seq {}: a translation {moved} m off the lerp",
            p.seq()
        );
        weights.push((p.seq(), w));
    }
    // The weight grows by 1 / (rate · fade) per tick, from 0 to 1.
    let fading: Vec<(u64, f32)> = weights
        .iter()
        .copied()
        .filter(|&(_, w)| w > 0.02 && w < 0.98)
        .collect();
    assert!(
        fading.len() >= 10,
        "only {} frames during a {fade} s fade at {rate} Hz: {weights:?}",
        fading.len()
    );
    for pair in fading.windows(2) {
        let ((s1, w1), (s2, w2)) = (pair[0], pair[1]);
        let expected = (s2 - s1) as f32 / (rate * fade);
        assert!(
            (w2 - w1 - expected).abs() < 0.005,
            "w went {w1:.4} → {w2:.4} from tick {s1} to {s2}, expected +{expected:.4}"
        );
    }
    let last = streamed.last().unwrap();
    assert!(
        worst(last.locals(), &to) <= 0.01,
        "the fade did not end on the wave pose"
    );
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn negative_speed_runs_the_clip_backwards() {
    let rate = 60.0f32;
    let speed = -1.5f32;
    let rig = posecast_server::builtin::rig().unwrap();
    let period = rig.clip("walk").unwrap().duration();
    let server = kit_server(rate).await;
    let c = server.client().await.unwrap();
    c.first_pose(AVATAR, DEFAULT_TIMEOUT).await.unwrap();
    c.command(play("walk", 0.6, speed, 0.0)).await.unwrap();
    let after = settle(&c).await;
    let streamed = record(&c, after, 0.6).await;
    assert!(streamed.len() >= 10, "only {} frames", streamed.len());
    let times: Vec<(u64, f32)> = streamed
        .iter()
        .map(|p| {
            let (t, err) = clip_time_of(&rig, "walk", p.locals());
            assert!(
                err < 0.02,
                "seq {}: no walk pose ({err}° off at best)",
                p.seq()
            );
            (p.seq(), t)
        })
        .collect();
    // Clip time goes down by |speed| · dt per tick.
    for pair in times.windows(2) {
        let ((s1, t1), (s2, t2)) = (pair[0], pair[1]);
        let expected = speed * (s2 - s1) as f32 / rate;
        let off = loop_distance(t1, t2, expected, period);
        assert!(
            off < 1e-3,
            "clip time {t1:.4} → {t2:.4} from tick {s1} to {s2}, expected {expected:+.4}"
        );
    }
    server.stop().await;
}

/// A counter from `/metrics`.
async fn metric(server: &posecast_server::startup::Server, name: &str) -> u64 {
    let (status, body) = http(server, "GET", "/metrics", None).await;
    assert_eq!(status, 200);
    body.lines()
        .find_map(|l| l.strip_prefix(name)?.strip_prefix(' ')?.parse().ok())
        .unwrap_or_else(|| panic!("no {name} in /metrics"))
}

// The default, single-threaded test runtime: blocking it stops the server's ticker.
#[tokio::test]
async fn ticks_missed_while_blocked_are_counted_and_covered() {
    let rate = 60.0f32;
    let rig = posecast_server::builtin::rig().unwrap();
    let period = rig.clip("walk").unwrap().duration();
    let server = kit_server(rate).await;
    let c = server.client().await.unwrap();
    c.first_pose(AVATAR, DEFAULT_TIMEOUT).await.unwrap();
    c.command(play("walk", 0.0, 1.0, 0.0)).await.unwrap();
    let after = settle(&c).await;
    let before = record(&c, after, 0.1).await.pop().expect("no frame");
    let missed_before = metric(&server, "posecast_ticks_missed_total").await;
    // Nothing runs for 300 ms: about 18 ticks are due meanwhile.
    std::thread::sleep(Duration::from_millis(300));
    let after = c
        .wait_for_pose(AVATAR, Duration::from_secs(2), |p| {
            p.seq() > before.seq() + 18
        })
        .await
        .unwrap();
    let missed = metric(&server, "posecast_ticks_missed_total").await - missed_before;
    assert!(missed >= 10, "{missed} ticks counted as missed");
    // The pose after the gap is the clip at the time that covers it: the clock advanced by
    // every tick, skipped or not.
    let (t1, e1) = clip_time_of(&rig, "walk", before.locals());
    let (t2, e2) = clip_time_of(&rig, "walk", after.locals());
    assert!(e1 < 0.02 && e2 < 0.02, "not walk poses ({e1}°, {e2}°)");
    let expected = (after.seq() - before.seq()) as f32 / rate;
    let off = loop_distance(t1, t2, expected, period);
    assert!(
        off < 1e-3,
        "clip time {t1:.4} → {t2:.4} over ticks {} → {}, expected {expected:+.4}",
        before.seq(),
        after.seq()
    );
    server.stop().await;
}
