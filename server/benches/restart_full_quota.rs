//! Start-up time with a full upload quota (issue 37: a restart with 1 GiB of recordings took
//! 202 s).
//!
//! `cargo bench -p posecast-server --bench restart_full_quota` — writes, once, a data folder under
//! `target/` holding `POSECAST_BENCH_GIB` (default 1) GiB of recorded clips of the built-in
//! rig, each a 10 s take at 60 Hz (≈ 220 kB, the size of the 4,890 short
//! recordings), then starts an in-process server on it three times and prints the time from
//! `Server::start` to `Server::ready` (every recording back on its rig) and the clips
//! restored.

use posecast_server::clip::{Clip, Interpolation, JointChannels, RotationChannel, Track};
use posecast_server::config::Config;
use posecast_server::startup::Server;
use posecast_server::store::recordings;
use std::path::Path;
use std::time::Instant;

/// A 10 s take at 60 Hz over the rig's joints, every key different (nothing compresses).
fn take(name: &str, joints: usize, seed: u32) -> anyhow::Result<Clip> {
    let keys = 600;
    let times: Vec<f32> = (0..keys).map(|k| k as f32 / 60.0).collect();
    let channels = (0..joints)
        .map(|j| {
            let values = (0..keys)
                .map(|k| {
                    let a = (k as f32 * 0.01) + (j as f32) * 0.1 + seed as f32 * 1e-3;
                    glam::Quat::from_rotation_y(a.sin()) * glam::Quat::from_rotation_x(a.cos())
                })
                .collect();
            Ok(JointChannels {
                rotation: Some(RotationChannel::Keys(Track::new(
                    Interpolation::Linear,
                    times.clone(),
                    values,
                )?)),
                ..JointChannels::default()
            })
        })
        .collect::<anyhow::Result<Vec<_>>>()?;
    Ok(Clip::new(name, channels, None)?)
}

/// Fills `data` with `bytes` of recordings (skipped when a previous run left them).
fn generate(data: &Path, bytes: u64) -> anyhow::Result<usize> {
    let done = data.join("bench-generated");
    let rig = posecast_server::builtin::rig()?;
    let dir = data.join("recordings");
    if let Ok(n) = std::fs::read_to_string(&done) {
        return Ok(n.trim().parse()?);
    }
    std::fs::create_dir_all(&dir)?;
    let (mut written, mut n) = (0u64, 0usize);
    while written < bytes {
        let name = format!("take-{n:05}");
        let clip = take(&name, rig.skeleton().len(), n as u32)?;
        let glb = posecast_server::export::clip_glb(&rig, &clip)?;
        recordings::save(&dir, &rig.name, &name, &glb, Some("bench"))?;
        written += glb.len() as u64;
        n += 1;
    }
    std::fs::write(&done, n.to_string())?;
    Ok(n)
}

#[tokio::main(flavor = "multi_thread", worker_threads = 2)]
async fn main() -> anyhow::Result<()> {
    // `cargo bench` passes `--bench`; under `cargo test --all-targets` one start on a few
    // recordings checks that the bench still runs.
    let bench = std::env::args().any(|a| a == "--bench");
    let gib: f64 = std::env::var("POSECAST_BENCH_GIB")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(if bench { 1.0 } else { 0.002 });
    let data = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("..")
        .join("target")
        .join(format!("bench-restart-{gib}gib"));
    let began = Instant::now();
    let n = generate(&data, (gib * f64::from(1u32 << 30)) as u64)?;
    println!(
        "data folder: {n} recordings, {:.2} GiB ({} s to generate or find)",
        gib,
        began.elapsed().as_secs()
    );
    for run in 1..=(if bench { 3 } else { 1 }) {
        let started = Instant::now();
        let server = Server::start(Config {
            listen: "127.0.0.1:0".parse()?,
            data_dir: Some(data.clone()),
            ..Config::default()
        })
        .await?;
        server.ready().await?;
        let ready = started.elapsed();
        let clips = server
            .state
            .world
            .library
            .get("avatar")
            .map_or(0, |r| r.clips.len());
        println!(
            "run {run}: ready after {:.2} s with {clips} clips on the built-in rig",
            ready.as_secs_f64()
        );
        server.stop().await;
    }
    Ok(())
}
