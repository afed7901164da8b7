//! Drive an avatar live: take over the built-in avatar and wave its right arm for three
//! seconds at 60 poses a second, then hand it back to its clip.
//!
//! `POSECAST_TOKEN=… cargo run --example wave` (a control token; the server prints its
//! generated one at start). `POSECAST_URL` for a server other than `ws://127.0.0.1:8080/ws`.

use glam::{EulerRot, Quat};
use posecast_client::net::Driver;
use posecast_proto::msg::AvatarId;
use std::time::Duration;

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    let url = std::env::var("POSECAST_URL").unwrap_or_else(|_| "ws://127.0.0.1:8080/ws".into());
    let token = std::env::var("POSECAST_TOKEN").ok();
    let driver = Driver::connect(&url, token).await?;
    let avatar = AvatarId("avatar".into());
    // Poses name the avatar's own joints (H-Anim), in the frame the server normalised it to.
    let info = driver.drive(&avatar, None, None).await?;
    println!(
        "driving {} ({} joints, at most {} poses/s)",
        info.avatar,
        info.joints.len(),
        info.max_rate_hz
    );
    let mut tick = tokio::time::interval(Duration::from_secs_f32(1.0 / 60.0));
    for i in 0..180 {
        tick.tick().await;
        let t = i as f32 / 60.0;
        // The right upper arm raised sideways (about Z; the avatar faces +Z, its right is -X),
        // level with the shoulder, the forearm up and swinging from side to side.
        let shoulder = Quat::from_euler(EulerRot::XYZ, 0.0, 0.0, -1.5);
        let elbow = Quat::from_euler(EulerRot::XYZ, 0.0, 0.0, -1.2 + 0.5 * (t * 6.0).sin());
        let rotations = [("r_shoulder", shoulder), ("r_elbow", elbow)]
            .map(|(joint, q)| (joint.to_owned(), q.to_array()));
        driver.send_pose(&avatar, rotations, None, None).await?;
    }
    if let Some(error) = driver.next_error(Duration::from_millis(100)).await {
        anyhow::bail!(
            "the server refused a pose: {} ({:?})",
            error.message,
            error.code
        );
    }
    driver.release(&avatar).await?;
    println!("sent 180 poses; released {avatar}");
    Ok(())
}
