//! VMC gateway figures: datagrams per second one VMC input takes at under half a core, and
//! VMC-out bytes per frame against posecast's binary frame of the same avatar.
//!
//! `cargo bench -p posecast --bench vmc` — an in-process server (release), Linux only (CPU
//! time from `/proc/self/task`).
//!
//! 1. One `--vmc-in`: a sender thread paces full performer frames (one bundle: `OK`, `T`,
//!    `Root/Pos`, all 55 `HumanBodyBones`, 12 blend shapes and `Apply`, as VSeeFace sends them)
//!    at each rate for 3 s; the server's CPU is every thread's but the sender's (the scene's
//!    60 Hz ticks included), from `/proc/self/task/*/stat`.
//! 2. The built-in avatar walking, sent by `--vmc-out` to a local socket, against the bytes
//!    per frame a binary subscriber of the same scene is offered (keyframes and deltas).

use glam::{EulerRot, Quat};
use posecast_client::net::{Client, ClientOptions};
use posecast_proto::command::Command;
use posecast_proto::msg::{AvatarId, Encoding};
use posecast_server::auth::{AccessConfig, Role, Secret, TokenRule};
use posecast_server::config::Config;
use posecast_server::metrics::vmc::PacketDrop;
use posecast_server::startup::Server;
use posecast_server::vmc::unity::HUMAN_BODY_BONES;
use posecast_server::vmc::{VmcIn, VmcOut};
use rosc::{OscBundle, OscMessage, OscPacket, OscTime, OscType};
use std::time::{Duration, Instant};

const TOKEN: &str = "bench-control-token";
const SENDER: &str = "vmc-sender";
const SECONDS: f64 = 3.0;

fn access() -> anyhow::Result<AccessConfig> {
    let mut access = AccessConfig::default();
    access
        .add(TokenRule::new("bench", Secret::new(TOKEN), Role::Control))
        .map_err(anyhow::Error::msg)?;
    Ok(access)
}

fn message(addr: &str, args: Vec<OscType>) -> OscPacket {
    OscPacket::Message(OscMessage {
        addr: addr.into(),
        args,
    })
}

/// A full performer frame at time `t`.
fn performer_frame(t: f32) -> anyhow::Result<Vec<u8>> {
    let pose = |name: &str, q: Quat| {
        let mut args = vec![OscType::String(name.into())];
        args.extend([0.0f32, 0.1, 0.0].map(OscType::Float));
        args.extend(q.to_array().map(OscType::Float));
        args
    };
    let mut content = vec![
        message("/VMC/Ext/OK", vec![OscType::Int(1)]),
        message("/VMC/Ext/T", vec![OscType::Float(t)]),
        message("/VMC/Ext/Root/Pos", pose("root", Quat::IDENTITY)),
    ];
    for (i, name) in HUMAN_BODY_BONES.iter().enumerate() {
        let a = t + i as f32;
        let q = Quat::from_euler(EulerRot::XYZ, 0.3 * a.sin(), 0.2 * a.cos(), 0.1 * a.sin());
        content.push(message("/VMC/Ext/Bone/Pos", pose(name, q)));
    }
    for name in [
        "Neutral", "A", "I", "U", "E", "O", "Blink", "Blink_L", "Blink_R", "Joy", "Angry", "Sorrow",
    ] {
        content.push(message(
            "/VMC/Ext/Blend/Val",
            vec![
                OscType::String(name.into()),
                OscType::Float(0.5 + 0.5 * t.sin()),
            ],
        ));
    }
    content.push(message("/VMC/Ext/Blend/Apply", Vec::new()));
    Ok(rosc::encoder::encode(&OscPacket::Bundle(OscBundle {
        timetag: OscTime {
            seconds: 0,
            fractional: 1,
        },
        content,
    }))?)
}

/// CPU seconds (user + system) of this process's threads, and of the one named `SENDER`.
fn cpu_seconds() -> (f64, f64) {
    let (mut all, mut sender) = (0.0, 0.0);
    let Ok(tasks) = std::fs::read_dir("/proc/self/task") else {
        return (0.0, 0.0);
    };
    for task in tasks.flatten() {
        let Ok(stat) = std::fs::read_to_string(task.path().join("stat")) else {
            continue;
        };
        let (Some(open), Some(close)) = (stat.find('('), stat.rfind(')')) else {
            continue;
        };
        let name = &stat[open + 1..close];
        let fields: Vec<&str> = stat[close + 2..].split_whitespace().collect();
        // After the name: state is field 3, utime field 14, stime field 15 (1-based).
        let ticks = |i: usize| fields.get(i - 3).and_then(|v| v.parse::<f64>().ok());
        let secs = (ticks(14).unwrap_or(0.0) + ticks(15).unwrap_or(0.0)) / 100.0;
        all += secs;
        if name == SENDER {
            sender += secs;
        }
    }
    (all, sender)
}

async fn input_throughput() -> anyhow::Result<()> {
    let server = Server::start(Config {
        listen: "127.0.0.1:0".parse()?,
        tick_rate: 60.0,
        access: access()?,
        vmc_in: vec![
            "127.0.0.1:0=avatar"
                .parse::<VmcIn>()
                .map_err(anyhow::Error::msg)?,
        ],
        ..Config::default()
    })
    .await?;
    server.ready().await?;
    let to = server.vmc.inputs[0];
    let frames: Vec<Vec<u8>> = (0..64)
        .map(|i| performer_frame(i as f32 * 0.1))
        .collect::<anyhow::Result<_>>()?;
    println!(
        "VMC in: one input, full performer frames of {} bytes (55 bones, 12 blend shapes)",
        frames[0].len()
    );
    println!(
        "{:>10} {:>12} {:>12} {:>12} {:>14}",
        "sent/s", "received/s", "decoded/s", "poses/s", "server CPU"
    );
    let m = server.state.metrics.clone();
    let mut best: Option<(f64, f64, f64)> = None;
    for rate in [1_000.0f64, 2_000.0, 5_000.0, 10_000.0, 20_000.0, 40_000.0] {
        let (p0, f0, poses0) = (
            m.vmc.packets(),
            m.vmc.dropped_total(PacketDrop::Flood),
            m.vmc.poses(),
        );
        let (cpu0, send0) = cpu_seconds();
        let started = Instant::now();
        let frames = frames.clone();
        let sender = std::thread::Builder::new().name(SENDER.into()).spawn(
            move || -> std::io::Result<u64> {
                let s = std::net::UdpSocket::bind("127.0.0.1:0")?;
                let start = Instant::now();
                let mut sent = 0u64;
                while start.elapsed().as_secs_f64() < SECONDS {
                    let due = (start.elapsed().as_secs_f64() * rate) as u64;
                    while sent < due {
                        s.send_to(&frames[(sent % 64) as usize], to).ok();
                        sent += 1;
                    }
                    std::thread::sleep(Duration::from_micros(500));
                }
                Ok(sent)
            },
        )?;
        let sent = tokio::task::spawn_blocking(move || sender.join())
            .await?
            .map_err(|_| anyhow::anyhow!("the sender panicked"))??;
        tokio::time::sleep(Duration::from_millis(100)).await;
        let secs = started.elapsed().as_secs_f64();
        let (cpu1, send1) = cpu_seconds();
        let server_cpu = ((cpu1 - cpu0) - (send1 - send0)) / secs;
        let received = (m.vmc.packets() - p0) as f64 / secs;
        let decoded = received - (m.vmc.dropped_total(PacketDrop::Flood) - f0) as f64 / secs;
        let poses = (m.vmc.poses() - poses0) as f64 / secs;
        println!(
            "{:>10.0} {:>12.0} {:>12.0} {:>12.0} {:>13.1}%",
            sent as f64 / SECONDS,
            received,
            decoded,
            poses,
            100.0 * server_cpu
        );
        if server_cpu < 0.5 && best.is_none_or(|(d, _, _)| decoded > d) {
            best = Some((decoded, server_cpu, received / (sent as f64 / SECONDS)));
        }
    }
    if let Some((decoded, cpu, got)) = best {
        println!(
            "=> one VMC input takes {decoded:.0} datagrams/s (full frames) at {:.0}% of a core \
             (received: {:.0}% of the sending rate)",
            100.0 * cpu,
            100.0 * got
        );
    }
    server.stop().await;
    Ok(())
}

async fn output_bytes() -> anyhow::Result<()> {
    let listener = tokio::net::UdpSocket::bind("127.0.0.1:0").await?;
    let server = Server::start(Config {
        listen: "127.0.0.1:0".parse()?,
        tick_rate: 60.0,
        access: access()?,
        vmc_out: vec![VmcOut {
            avatar: AvatarId("avatar".into()),
            addr: listener.local_addr()?,
        }],
        ..Config::default()
    })
    .await?;
    server.ready().await?;
    let mut options = ClientOptions::new(server.ws_url(), "default");
    options.encoding = Encoding::Binary;
    options.reconnect = false;
    options.token = Some(TOKEN.into());
    let client = Client::connect(options).await?;
    client
        .command(Command::Play {
            avatar: AvatarId("avatar".into()),
            clip: "walk".into(),
            from_asset: None,
            speed: None,
            looping: None,
            fade: None,
            start: None,
            root_motion: None,
        })
        .await?;
    tokio::time::sleep(Duration::from_millis(500)).await;
    let m = server.state.metrics.clone();
    let (frames0, bytes0) = (m.frames_offered_total(), m.frame_bytes_offered_total());
    let mut buf = vec![0u8; 65_536];
    let mut sizes = Vec::new();
    while sizes.len() < 180 {
        let (n, _) = listener.recv_from(&mut buf).await?;
        sizes.push(n);
    }
    let frames = m.frames_offered_total() - frames0;
    let bytes = m.frame_bytes_offered_total() - bytes0;
    let vmc = sizes.iter().sum::<usize>() as f64 / sizes.len() as f64;
    let binary = bytes as f64 / frames.max(1) as f64;
    println!(
        "VMC out, built-in avatar walking (22 bones): {vmc:.0} bytes per frame; posecast binary \
         frame of the same scene: {binary:.0} bytes per frame (keyframes and deltas, 32-byte \
         header included): VMC is {:.1}x larger",
        vmc / binary
    );
    server.stop().await;
    Ok(())
}

fn main() -> anyhow::Result<()> {
    let rt = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()?;
    rt.block_on(async {
        output_bytes().await?;
        input_throughput().await
    })
}
