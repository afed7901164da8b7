//! Live driving figures: pose in → pose out latency at a subscriber (p50 / p99) with 100
//! subscribers, and the CPU one live retargeted avatar costs per tick.
//!
//! `cargo bench -p posecast --bench live_drive` — an in-process server at 60 Hz; one driver
//! sends 120 poses a second for 5 s, each a distinct `l_elbow` angle, while 100 library
//! clients (binary frames) record when each pose first shows; latency = seen − sent (one
//! machine, one clock). Then, without a server, an avatar of the built-in rig driven from CMU
//! 01_01's skeleton (`../shared/testdata`) is ticked with a new pose every tick.

#[path = "common/drive.rs"]
mod drive;

use glam::Quat;
use posecast_proto::msg::AvatarId;
use posecast_server::auth::{AccessConfig, Role, Secret, TokenRule};
use posecast_server::config::Config;
use posecast_server::startup::Server;
use std::sync::Arc;
use std::time::{Duration, Instant};

const TOKEN: &str = "bench-control-token";
const SUBSCRIBERS: usize = 100;
const POSES: usize = 600;

fn percentile(sorted: &[Duration], p: f64) -> Duration {
    let i = ((sorted.len() as f64 - 1.0) * p).round() as usize;
    sorted.get(i).copied().unwrap_or_default()
}

async fn latency() -> anyhow::Result<()> {
    let mut access = AccessConfig::default();
    access
        .add(TokenRule::new("bench", Secret::new(TOKEN), Role::Control))
        .map_err(anyhow::Error::msg)?;
    let server = Server::start(Config {
        listen: "127.0.0.1:0".parse()?,
        tick_rate: 60.0,
        access,
        ..Config::default()
    })
    .await?;
    server.ready().await?;
    let mut l = drive::pose_latencies(drive::Run {
        watch: &server,
        scene: "default",
        drive_url: server.ws_url(),
        token: TOKEN,
        avatar: AvatarId("avatar".into()),
        clients: SUBSCRIBERS,
        poses: POSES,
    })
    .await?;
    l.sort();
    println!(
        "pose in -> pose out, {SUBSCRIBERS} subscribers, 120 Hz driver, 60 Hz ticks: {} samples, p50 {:.2} ms, p99 {:.2} ms, max {:.2} ms",
        l.len(),
        percentile(&l, 0.5).as_secs_f64() * 1e3,
        percentile(&l, 0.99).as_secs_f64() * 1e3,
        l.last().copied().unwrap_or_default().as_secs_f64() * 1e3,
    );
    server.stop().await;
    Ok(())
}

fn cpu_per_tick() -> anyhow::Result<()> {
    use posecast_server::avatar::Avatar;
    use posecast_server::avatar::live::{LivePose, ValidPose};
    use posecast_server::rig::PipelineOptions;
    let path = posecast_proto::testing::testdata("bvh/cmu/01_01.bvh");
    let Ok(text) = std::fs::read_to_string(&path) else {
        println!("{} absent: no retargeting figure", path.display());
        return Ok(());
    };
    let asset = posecast_server::import::bvh::parse("01_01", &text)?;
    let source = Arc::new(posecast_server::rig::Rig::from_asset(
        asset,
        &PipelineOptions::default(),
    )?);
    let target = Arc::new(posecast_server::builtin::rig().map_err(anyhow::Error::msg)?);
    let clip = source.clips[0].clone();
    let sk = source.skeleton();
    let frames: Vec<Vec<(usize, Quat)>> = (0..200)
        .map(|i| {
            let mut locals = sk.rest().to_vec();
            clip.sample(clip.start() + i as f32 / 60.0, sk.rest(), &mut locals);
            locals.iter().map(|l| l.rotation).enumerate().collect()
        })
        .collect();
    let mut a = Avatar::new(AvatarId("a".into()), 1, target.clone());
    let ticks = 20_000;
    let mut plain = Duration::ZERO;
    let start = Instant::now();
    for i in 0..ticks {
        a.tick(f64::from(i) / 60.0);
    }
    plain += start.elapsed();
    a.live = Some(LivePose::new(
        1,
        Default::default(),
        source.clone(),
        &target,
        &a.locals,
        Duration::from_secs(3600),
    )?);
    let start = Instant::now();
    for i in 0..ticks {
        if let Some(live) = &mut a.live {
            let pose = ValidPose {
                rotations: frames[i as usize % frames.len()].clone(),
                root_position: Some(glam::Vec3::new(0.0, 0.9, i as f32 * 1e-4)),
                time_us: None,
            };
            live.store(pose, Instant::now());
        }
        a.tick(f64::from(i) / 60.0);
    }
    let live = start.elapsed();
    let per = |d: Duration| d.as_secs_f64() * 1e6 / f64::from(ticks);
    println!(
        "avatar tick ({} joints, driven from {} joints, new pose every tick, root moving): {:.2} µs with live retargeting, {:.2} µs without a driver (rest pose, no clip); live retargeting costs {:.2} µs per avatar per tick",
        target.skeleton().len(),
        sk.len(),
        per(live),
        per(plain),
        per(live) - per(plain)
    );
    Ok(())
}

fn main() -> anyhow::Result<()> {
    cpu_per_tick()?;
    tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()?
        .block_on(latency())
}
