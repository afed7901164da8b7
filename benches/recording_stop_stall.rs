//! How long stopping a 64 MiB recording stalls *other* scenes (issue 37: ~0.2 s).
//!
//! `cargo bench -p posecast --bench recording_stop_stall` — an in-process server at 60 Hz
//! with a data folder; avatar `avatar` of scene `default` holds a full 64 MiB take (built
//! directly in its recorder: 176,000 ticks of the built-in rig), and a client on a runtime
//! and thread of its own watches scene `other`. Prints the longest gap between the frames of
//! `other` in the second before the stop and while it runs, for two ways of stopping:
//!
//! - `inline`: the take finished on the async worker that runs the command
//!   (`control::execute`, what `stop_recording` did before issue 37);
//! - `offloaded`: `stop_recording` as clients send it (`control::execute_durable`): the
//!   recorder is taken under the scene's lock, the clip built, exported and stored on the
//!   blocking pool, then acknowledged.

use posecast_client::net::{Client, ClientOptions, Event};
use posecast_proto::command::Command;
use posecast_proto::frame::AvatarPose;
use posecast_proto::msg::{AvatarId, Encoding, SceneId};
use posecast_server::avatar::recording::{RecordLimits, Recorder};
use posecast_server::config::Config;
use posecast_server::startup::Server;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// Puts a full 64 MiB take named `clip` into the recorder of avatar `avatar`.
fn fill_recorder(server: &Server, avatar: &str, clip: &str) -> anyhow::Result<usize> {
    let id = AvatarId(avatar.into());
    let scene = server.state.world.find_avatar(&id)?;
    let mut s = scene.lock();
    let a = s
        .avatars
        .iter_mut()
        .find(|a| a.id == id)
        .ok_or_else(|| anyhow::anyhow!("no avatar {avatar}"))?;
    let d = a.description.clone();
    let limits = RecordLimits {
        max_seconds: 1e7,
        // `cargo bench` passes `--bench`; under `cargo test --all-targets` one small take
        // checks that the bench still runs.
        max_bytes: if std::env::args().any(|a| a == "--bench") {
            64 << 20
        } else {
            1 << 20
        },
    };
    let mut rec = Recorder::new(clip, &d, limits);
    let mut k = 0u64;
    while !rec.is_full() {
        let angle = (k as f32) * 1e-3;
        let pose = AvatarPose {
            avatar_num: d.num,
            hash: d.hash_u64(),
            rotations: (0..d.joint_names.len())
                .map(|j| glam::Quat::from_rotation_y(angle + j as f32 * 0.01))
                .collect(),
            translations: vec![glam::Vec3::ZERO; d.translated_joints.len()],
            scales: vec![glam::Vec3::ONE; d.scaled_joints.len()],
            placement: posecast_proto::placement::Placement::IDENTITY,
            weights: Vec::new(),
        };
        rec.push(k as f64 / 60.0, &pose)?;
        k += 1;
    }
    let frames = rec.frames();
    a.recording = Some(rec);
    Ok(frames)
}

/// Frame arrival times of scene `other`, seen by a client on its own thread and runtime.
fn watch(url: String) -> Arc<Mutex<Vec<Instant>>> {
    let seen = Arc::new(Mutex::new(Vec::new()));
    let out = seen.clone();
    std::thread::spawn(move || {
        let Ok(rt) = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
        else {
            return;
        };
        rt.block_on(async move {
            let mut options = ClientOptions::new(url, "other");
            options.encoding = Encoding::Binary;
            options.reconnect = false;
            let Ok(client) = Client::connect(options).await else {
                return;
            };
            let mut events = client.events();
            while let Ok(e) = events.recv().await {
                if let Event::Frame { .. } = e
                    && let Ok(mut s) = out.lock()
                {
                    s.push(Instant::now());
                }
            }
        });
    });
    seen
}

/// The longest gap between consecutive instants in `[from, to]`.
fn longest_gap(times: &[Instant], from: Instant, to: Instant) -> Duration {
    let inside: Vec<&Instant> = times.iter().filter(|t| **t >= from && **t <= to).collect();
    inside
        .windows(2)
        .map(|w| w[1].duration_since(*w[0]))
        .max()
        .unwrap_or_default()
}

#[tokio::main(flavor = "multi_thread", worker_threads = 2)]
async fn main() -> anyhow::Result<()> {
    let data = tempfile::tempdir_in(concat!(env!("CARGO_MANIFEST_DIR"), "/target"))?;
    let server = Server::start(Config {
        listen: "127.0.0.1:0".parse()?,
        tick_rate: 60.0,
        data_dir: Some(data.path().to_owned()),
        ..Config::default()
    })
    .await?;
    server.ready().await?;
    let state = server.state.clone();
    state.world.create_scene(SceneId("other".into()))?;
    state.world.add_avatar(
        &SceneId("other".into()),
        "avatar",
        Some(AvatarId("w".into())),
    )?;
    let seen = watch(server.ws_url());
    tokio::time::sleep(Duration::from_secs(2)).await;
    for (mode, clip) in [("inline", "big-inline"), ("offloaded", "big-offloaded")] {
        let frames = fill_recorder(&server, "avatar", clip)?;
        tokio::time::sleep(Duration::from_secs(1)).await;
        let before = Instant::now();
        let command = Command::StopRecording {
            avatar: AvatarId("avatar".into()),
        };
        let s = state.clone();
        let began = Instant::now();
        let result = if mode == "inline" {
            tokio::spawn(async move { posecast_server::control::execute(&s, &command) }).await?
        } else {
            tokio::spawn(
                async move { posecast_server::control::execute_durable(&s, &command).await },
            )
            .await?
        };
        let took = began.elapsed();
        result?;
        tokio::time::sleep(Duration::from_millis(300)).await;
        let after = Instant::now();
        let times = seen.lock().map(|s| s.clone()).unwrap_or_default();
        let baseline = longest_gap(&times, before - Duration::from_secs(1), before);
        let during = longest_gap(&times, before, after);
        println!(
            "{mode:>9}: {frames} ticks recorded; stop took {:.0} ms; longest gap of scene other: {:.1} ms before, {:.1} ms during the stop",
            took.as_secs_f64() * 1e3,
            baseline.as_secs_f64() * 1e3,
            during.as_secs_f64() * 1e3
        );
    }
    server.stop().await;
    Ok(())
}
