//! CPU time of a scene's tick per avatar — sample the clip, apply overrides and limits, then
//! quantise and encode the frame (binary, once for every subscriber) and hand it to the
//! subscribers' outboxes — and whether a scene of 4,000 avatars holds 60 Hz on one core.
//!
//! A scene of N avatars (the built-in avatar, 23 joints, or CMU 01_01, 31 joints), each playing
//! its clip from a different start, with one binary subscriber (so frames are encoded; more
//! subscribers share the same encoded bytes). The tick runs exactly as the scene's ticker runs
//! it (`Scene::tick`: a keyframe every 60 ticks, deltas between), on this thread. Also with a
//! JSON subscriber added, which costs the JSON encoding the binary-only scene does not do; and
//! with one wire-v2 subscriber (protocol version 2, or 7 with packed deltas) instead, whose
//! frames are coded against the previous frame (its outbox emptied every tick, as a writer keeping up would); and while a
//! take of the scene is recorded (`+ take`: each frame's bytes handed to the take's writer
//! thread, whose own time is not the tick's).
//!
//! Times are this thread's CPU time (`CLOCK_THREAD_CPUTIME_ID`), so other work on the shared
//! cores does not inflate them. Run: `cargo bench -p posecast-server --bench tick`. Prints a
//! table; asserts nothing. Arguments after `--` keep only the rows whose clip, avatar count
//! and subscribers (e.g. `walk 4000 binary v2`) contain one of them — for profiling one row.
//!
//! The last two columns are wall time per tick: the whole tick, which is how long the scene
//! lock was held before the tick published outside it (every command on the scene waited for
//! all of it), and how long it is held now (`Scene::tick`'s return: moving the avatars and
//! copying their poses; encoding and fan-out run under the feed's lock after it). The rows
//! with 500 subscribers are where fan-out dominates.

use anyhow::{Context, Result, bail};
use futures_util::FutureExt;
use posecast_proto::msg::{AvatarId, Encoding, SceneId};
use posecast_proto::testing::testdata;
use posecast_server::avatar::Avatar;
use posecast_server::avatar::playback::Layer;
use posecast_server::builtin::AVATAR_GLB;
use posecast_server::import;
use posecast_server::metrics::Metrics;
use posecast_server::rig::Rig;
use posecast_server::scene::Scene;
use posecast_server::stream::feed::Subscriber;
use posecast_server::stream::outbox::Outbox;
use std::sync::Arc;
use std::time::{Duration, Instant};

const RATE: f64 = 60.0;
const KEY_INTERVAL: u64 = 60;

/// A subscriber's encoding and protocol version (2: wire v2 binary frames).
type Sub = (Encoding, u32);

/// A scene of `n` avatars of `rig` playing `clip`, with subscribers `subs`, and their outboxes.
fn scene(rig: &Arc<Rig>, clip: &str, n: usize, subs: &[Sub]) -> Result<(Scene, Vec<Arc<Outbox>>)> {
    let scene = Scene::new(
        SceneId("bench".into()),
        1,
        Arc::new(Metrics::new()),
        RATE as f32,
    );
    let c = rig.clip(clip).context("no such clip")?.clone();
    for i in 0..n {
        let mut avatar = Avatar::new(AvatarId(format!("a{i}")), i as u32 + 1, rig.clone());
        let start = (i as f32 * 0.137) % c.duration().max(1e-3);
        avatar.play(Layer::new(c.clone(), None, start, 1.0, true), 0.0);
        scene.add_avatar(avatar)?;
    }
    let mut outboxes = Vec::new();
    for (k, &(encoding, version)) in subs.iter().enumerate() {
        let outbox = Arc::new(Outbox::new());
        let sub =
            Subscriber::new(k as u64 + 1, outbox.clone(), encoding, None, 1).with_version(version);
        scene.subscribe(sub)?;
        outboxes.push(outbox);
    }
    Ok((scene, outboxes))
}

/// This thread's CPU time: what the tick costs, not what other processes on the shared cores
/// take from it.
fn thread_cpu() -> Duration {
    let t = rustix::time::clock_gettime(rustix::time::ClockId::ThreadCPUTime);
    Duration::new(
        u64::try_from(t.tv_sec).unwrap_or(0),
        u32::try_from(t.tv_nsec).unwrap_or(0),
    )
}

/// Mean CPU time of one tick over about `budget` of it (after a second of warm-up ticks). The
/// outboxes are emptied after each tick, as their writers would (a wire-v2 subscriber whose
/// frame was never taken would get keyframes only).
fn time_ticks(scene: &Scene, outboxes: &[Arc<Outbox>], budget: Duration) -> Times {
    let mut seq = 0u64;
    // The wall time of the ticks run and of their part under the scene lock.
    let mut run = |ticks: u64| {
        let (mut whole, mut held) = (Duration::ZERO, Duration::ZERO);
        for _ in 0..ticks {
            seq += 1;
            let began = Instant::now();
            held += scene.tick(
                seq,
                seq as f64 / RATE,
                1_700_000_000_000_000 + seq * 16_667,
                KEY_INTERVAL,
            );
            whole += began.elapsed();
            for outbox in outboxes {
                let _ = outbox.next().now_or_never();
            }
        }
        (whole, held)
    };
    run(60);
    let (mut whole, mut held) = (Duration::ZERO, Duration::ZERO);
    let mut ticks = 0u64;
    let start = thread_cpu();
    let wall = Instant::now();
    while (thread_cpu() - start < budget && wall.elapsed() < 10 * budget) || ticks < 60 {
        let (w, h) = run(60);
        whole += w;
        held += h;
        ticks += 60;
    }
    let n = u32::try_from(ticks).unwrap_or(u32::MAX);
    Times {
        cpu: (thread_cpu() - start) / n,
        whole: whole / n,
        held: held / n,
    }
}

/// Per tick: this thread's CPU time, and the wall time of the whole tick and of the part
/// under the scene lock.
struct Times {
    cpu: Duration,
    whole: Duration,
    held: Duration,
}

fn load(path: &std::path::Path) -> Result<Arc<Rig>> {
    let mut assets = import::load_path(path)?;
    if assets.is_empty() {
        bail!("{} holds no rig", path.display());
    }
    Ok(Arc::new(Rig::from_asset(
        assets.remove(0),
        &Default::default(),
    )?))
}

fn main() -> Result<()> {
    let mut assets = import::gltf::from_slice("avatar.glb", AVATAR_GLB)?;
    if assets.is_empty() {
        bail!("the built-in avatar holds no rig");
    }
    let builtin = Arc::new(Rig::from_asset(assets.remove(0), &Default::default())?);
    let mut rigs = vec![("built-in walk", builtin, "walk".to_owned())];
    let path = testdata("bvh/cmu/01_01.bvh");
    if path.exists() {
        let cmu = load(&path)?;
        let clip = cmu
            .clips
            .first()
            .context("CMU 01_01 has no clip")?
            .name()
            .to_owned();
        rigs.push(("CMU 01_01", cmu, clip));
    } else if std::env::var("CI").as_deref() == Ok("true") {
        bail!("{} is missing", path.display());
    } else {
        eprintln!("skipping CMU 01_01: {} is absent", path.display());
    }
    // Row filters: what follows `--` on the command line, less the harness's own flags.
    let only: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| !a.starts_with("--"))
        .collect();
    println!(
        "| clip | joints | avatars | subscribers | tick | per avatar | per joint | ticks/s on one core | whole tick (wall; the lock before) | scene lock held (wall) |"
    );
    println!("|---|---:|---:|---|---:|---:|---:|---:|---:|---:|");
    for (name, rig, clip) in &rigs {
        let joints = rig.skeleton().len();
        let v1 = (Encoding::Binary, 1);
        let v2 = (Encoding::Binary, 2);
        // Protocol version 7: wire v2 with packed deltas.
        let v7 = (Encoding::Binary, 7);
        let json = (Encoding::Json, 1);
        let label = |(e, v): &Sub| match (e, v) {
            (Encoding::Binary, 2) => "binary v2".to_owned(),
            (Encoding::Binary, 7) => "binary v2 packed (protocol 7)".to_owned(),
            (e, _) => format!("{e:?}").to_lowercase(),
        };
        for (n, subs, take) in [
            (1, vec![v1], false),
            (100, vec![v1], false),
            (100, vec![v1], true),
            (4000, vec![v1], false),
            (100, vec![v1, json], false),
            (100, vec![v2], false),
            (100, vec![v7], false),
            (4000, vec![v2], false),
            (4000, vec![v7], false),
            (100, vec![v1; 500], false),
            (100, vec![v2; 500], false),
        ] {
            let mut subs_label = if subs.len() > 2 {
                format!("{} × {}", subs.len(), label(&subs[0]))
            } else {
                subs.iter().map(label).collect::<Vec<_>>().join(" + ")
            };
            if take {
                subs_label.push_str(" + take");
            }
            let row = format!("{name} {n} {subs_label}");
            if !only.is_empty() && !only.iter().any(|o| row.contains(o.as_str())) {
                continue;
            }
            let (scene, outboxes) = scene(rig, clip, n, &subs)?;
            // Recording a take of the scene (`record_scene`): its frames go to a writer thread
            // (memory here), whose time is not the tick's.
            let takes = posecast_server::takes::Takes::new(None);
            if take {
                let limits = posecast_server::takes::TakeLimits {
                    max_frames: u64::MAX,
                    max_bytes: u64::MAX,
                };
                let sink = takes.begin(&scene.id, "bench", RATE as f32, limits)?;
                scene.feed().record(Some(Box::new(sink)));
            }
            let times = time_ticks(&scene, &outboxes, Duration::from_secs(2));
            let tick = times.cpu;
            let per_avatar = tick.as_secs_f64() * 1e6 / n as f64;
            let subs = subs_label;
            println!(
                "| {name} | {joints} | {n} | {subs} | {:.3} ms | {per_avatar:.2} µs | {:.0} ns | {:.0} | {:.3} ms | {:.3} ms |",
                tick.as_secs_f64() * 1e3,
                per_avatar * 1e3 / joints as f64,
                1.0 / tick.as_secs_f64(),
                times.whole.as_secs_f64() * 1e3,
                times.held.as_secs_f64() * 1e3,
            );
        }
    }
    Ok(())
}
