//! Watch a scene: connect, subscribe, and print where each avatar's head is, ten times a
//! second, for three seconds.
//!
//! `cargo run --example watch` (a server on `ws://127.0.0.1:8080/ws`; `POSECAST_URL` for
//! another, `POSECAST_SCENE` for a scene other than `default`).

use posecast_client::net::{Client, ClientOptions};
use posecast_proto::fk::forward_kinematics;
use std::time::Duration;

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    let url = std::env::var("POSECAST_URL").unwrap_or_else(|_| "ws://127.0.0.1:8080/ws".into());
    let scene = std::env::var("POSECAST_SCENE").unwrap_or_else(|_| "default".into());
    let client = Client::connect(ClientOptions::new(url, &scene)).await?;
    for _ in 0..30 {
        tokio::time::sleep(Duration::from_millis(100)).await;
        for avatar in client.avatars() {
            let Some(pose) = &avatar.latest else { continue };
            // World matrices from the streamed local rotations, the avatar's placement included.
            let mut world = vec![glam::Mat4::IDENTITY; avatar.skeleton.len()];
            forward_kinematics(
                &avatar.skeleton,
                &pose.placed_locals(&avatar.skeleton),
                &mut world,
            );
            let head = avatar
                .skeleton
                .find("skullbase")
                .unwrap_or(avatar.skeleton.len() - 1);
            let p = world[head].w_axis;
            println!(
                "{} tick {}: head at ({:.3}, {:.3}, {:.3}) m",
                avatar.description.id.0, pose.seq, p.x, p.y, p.z
            );
        }
    }
    Ok(())
}
