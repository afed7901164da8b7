//! `posecast-client vmc-relay`: a VTuber tool's VMC stream, received on the performer's own
//! machine, drives an avatar on a server anywhere over an authenticated websocket.
//!
//! VMC is OSC over UDP without authentication, meant for one machine or a local network
//! (`--vmc-in` binds to loopback for that reason). The relay listens where the tool sends
//! (loopback by default), decodes each datagram with the server's own VMC code
//! ([`posecast_server::vmc::input::Performer`]: Unity's frame and T-pose to posecast's), takes
//! the avatar with `drive … source "@vmc"` (the server's VMC performer rig, fitted to the
//! avatar, as a `--vmc-in` input does) and sends the poses as binary pose messages, at most the
//! drive's `max_rate_hz`. Only a holder of a token that may drive the avatar gets through;
//! the server retargets exactly as for a local VMC input. Blend shapes are not relayed yet.

use anyhow::{Context, bail};
use clap::Args;
use posecast_client::net::Driver;
use posecast_proto::live::{BinaryPose, VMC_SOURCE};
use posecast_proto::msg::AvatarId;
use posecast_server::metrics::vmc::VmcCounters;
use posecast_server::vmc::input::Performer;
use posecast_server::vmc::rig::VmcRig;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;
use tokio::net::UdpSocket;

/// `vmc-relay`'s flags.
#[derive(Debug, Args)]
pub struct VmcRelayArgs {
    /// The server's websocket URL.
    #[arg(long, env = "POSECAST_URL", default_value = "ws://127.0.0.1:8080/ws")]
    url: String,
    /// A token that may drive the avatar (required).
    #[arg(long, env = "POSECAST_TOKEN")]
    token: Option<String>,
    /// The avatar to drive.
    #[arg(long, default_value = "avatar")]
    avatar: String,
    /// Where the VTuber tool sends its VMC datagrams (UDP). Loopback by default: the tool runs
    /// on this machine.
    #[arg(long, default_value = "127.0.0.1:39539")]
    listen: SocketAddr,
    /// Stop after this many seconds (default: until interrupted).
    #[arg(long)]
    seconds: Option<f32>,
}

/// Runs the relay until interrupted (or `--seconds`), then releases the avatar.
///
/// # Errors
/// No token, the UDP port cannot be bound, the server refuses the connection or the drive, or
/// the connection fails.
pub async fn run(args: VmcRelayArgs) -> anyhow::Result<()> {
    let Some(token) = args.token.clone() else {
        bail!("the relay needs a token that may drive the avatar: --token or POSECAST_TOKEN");
    };
    let socket = UdpSocket::bind(args.listen)
        .await
        .with_context(|| format!("cannot listen for VMC on {}", args.listen))?;
    let driver = Driver::connect(&args.url, Some(token))
        .await
        .with_context(|| format!("cannot connect to {}", args.url))?;
    let avatar = AvatarId(args.avatar.clone());
    let info = driver
        .drive(&avatar, Some(VMC_SOURCE), None)
        .await
        .with_context(|| format!("cannot drive avatar {avatar}"))?;
    let listen = socket.local_addr().unwrap_or(args.listen);
    println!(
        "relaying VMC from {listen} to avatar {avatar} on {} (at most {} poses/s)",
        args.url, info.max_rate_hz
    );
    let mut performer = Performer::new(Arc::new(VmcRig::new()?));
    let counters = VmcCounters::standalone();
    let interval = Duration::from_secs_f32(1.0 / info.max_rate_hz.clamp(1.0, 1000.0));
    let mut next_send = tokio::time::Instant::now();
    let stop = tokio::time::sleep(Duration::from_secs_f32(
        args.seconds.unwrap_or(f32::MAX).clamp(0.0, 1e9),
    ));
    tokio::pin!(stop);
    let mut buf = vec![0u8; 65_536];
    let (mut received, mut sent) = (0u64, 0u64);
    loop {
        tokio::select! {
            r = socket.recv_from(&mut buf) => {
                let (n, _) = r.context("receiving VMC")?;
                received += 1;
                // A malformed datagram is dropped alone, as a `--vmc-in` input drops it.
                performer.datagram(buf.get(..n).unwrap_or_default(), &counters).ok();
            }
            () = tokio::time::sleep_until(next_send), if performer.pending() => {}
            () = &mut stop => break,
            _ = tokio::signal::ctrl_c() => break,
        }
        let now = tokio::time::Instant::now();
        if performer.pending() && now >= next_send {
            next_send = now + interval;
            let update = performer.take_pose();
            let rotations = update
                .pose
                .rotations
                .iter()
                .filter_map(|&(j, q)| Some((u16::try_from(j).ok()?, q)))
                .collect();
            driver
                .send_binary_pose(&BinaryPose {
                    avatar_num: info.avatar_num,
                    time_us: Some(now_us()),
                    root_position: update.pose.root_position,
                    rotations,
                    weights: Vec::new(),
                    trackers: Vec::new(),
                })
                .await
                .context("sending a pose")?;
            sent += 1;
        }
        if let Some(error) = driver.next_error(Duration::ZERO).await {
            bail!(
                "the server refused a pose: {} ({:?})",
                error.message,
                error.code
            );
        }
    }
    driver.release(&avatar).await.ok();
    println!("{received} datagrams in, {sent} poses sent; released {avatar}");
    driver.close().await;
    Ok(())
}

fn now_us() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| u64::try_from(d.as_micros()).unwrap_or(u64::MAX))
}
