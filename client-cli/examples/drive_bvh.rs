//! Drive an avatar from a BVH file: upload the file as the source rig, take over the built-in
//! avatar, stream the file's motion at 60 poses a second for three seconds (the server
//! retargets it from the file's skeleton onto the avatar's), then hand the avatar back.
//!
//! `POSECAST_TOKEN=… cargo run -p posecast-client-cli --example drive_bvh -- FILE.bvh` (a control token; without a
//! file, the server's own walk exported as BVH). `POSECAST_URL` for a server other than
//! `ws://127.0.0.1:8080/ws`. The command line's `posecast-client drive` does the same with
//! more options.

use anyhow::Context;
use posecast_client::net::Driver;
use posecast_client::view_source::fetch;
use posecast_proto::msg::AvatarId;
use posecast_server::import::bvh;
use posecast_server::rig::{PipelineOptions, Rig};
use std::time::Duration;

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    let url = std::env::var("POSECAST_URL").unwrap_or_else(|_| "ws://127.0.0.1:8080/ws".into());
    let token = std::env::var("POSECAST_TOKEN").context("set POSECAST_TOKEN to a control token")?;
    let bytes = match std::env::args().nth(1) {
        Some(path) => std::fs::read(&path).with_context(|| format!("cannot read {path}"))?,
        None => fetch::get(&fetch::resolve(&url, "/api/assets/avatar/clips/walk.bvh")?).await?,
    };
    // The file normalised here as the server normalises it on upload, so the rotations sampled
    // below are in the frames the server's copy of the rig expects.
    let rig = Rig::from_asset(
        bvh::parse("motion.bvh", std::str::from_utf8(&bytes)?)?,
        &PipelineOptions::default(),
    )?;
    let clip = rig.clips.first().context("the file has no motion")?.clone();
    // Named after the file's contents: the same file again finds its asset there (409).
    let name = format!("motion-{:012x}", fnv1a(&bytes) >> 16);
    let bearer = format!("Bearer {token}");
    let upload = fetch::resolve(&url, &format!("/api/assets/{name}?format=bvh"))?;
    let headers = [("Authorization", bearer.as_str())];
    let answer = fetch::request("POST", &upload, &headers, &bytes).await?;
    anyhow::ensure!(
        matches!(answer.status, 200 | 409),
        "upload refused: HTTP {}",
        answer.status
    );

    let driver = Driver::connect(&url, Some(token)).await?;
    let avatar = AvatarId("avatar".into());
    let info = driver.drive(&avatar, Some(&name), None).await?;
    println!(
        "driving {avatar} from {} ({} joints)",
        info.source,
        info.joints.len()
    );
    let mut sampler = clip.sampler();
    let mut locals = rig.skeleton().rest().to_vec();
    let mut tick = tokio::time::interval(Duration::from_secs_f32(1.0 / 60.0));
    for i in 0..180 {
        tick.tick().await;
        let time = clip.start() + (i as f32 / 60.0) % clip.duration().max(1e-3);
        sampler.sample(&clip, time, rig.skeleton().rest(), &mut locals);
        // Rotations by joint name, the root's translation in metres.
        let rotations = rig
            .skeleton()
            .names()
            .iter()
            .zip(&locals)
            .map(|(name, t)| (name.clone(), t.rotation.normalize().to_array()));
        let root = locals[rig.skeleton().roots().next().unwrap_or(0)].translation;
        driver
            .send_pose(&avatar, rotations, Some(root.to_array()), None)
            .await?;
    }
    if let Some(error) = driver.next_error(Duration::from_millis(100)).await {
        anyhow::bail!("the server refused a pose: {}", error.message);
    }
    driver.release(&avatar).await?;
    println!("sent 180 poses; released {avatar}");
    Ok(())
}

/// FNV-1a, 64 bits.
fn fnv1a(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0xcbf2_9ce4_8422_2325, |h, &b| {
        (h ^ u64::from(b)).wrapping_mul(0x0000_0100_0000_01b3)
    })
}
