//! A first posecast integration test. Copy this file into your crate's `tests/` folder (and
//! leave out the `cfg_attr` line and `main`, which only serve this file's build as an example
//! program), with in `Cargo.toml`:
//!
//! ```toml
//! [dev-dependencies]
//! posecast-testkit = { path = "../posecast/testkit" }
//! posecast-proto = { path = "../posecast/proto" }
//! tokio = { version = "1", features = ["macros", "rt"] }
//! glam = "0.30"
//! ```

#![cfg_attr(not(test), allow(unused_imports))]

use posecast_proto::command::{Command, CommandResult};
use posecast_proto::msg::{AvatarId, ErrorCode};
use posecast_proto::quant::{MAX_ERROR_DEGREES, angle_between_degrees};
use posecast_testkit::{DEFAULT_TIMEOUT, KitError, TestServer};

/// The built-in avatar plays the clip it is told to: what streams is the clip, sampled by the
/// server's own code at the same time, within the wire's quantisation bound.
#[tokio::test]
async fn the_avatar_streams_the_clip_it_plays() -> Result<(), KitError> {
    let server = TestServer::builder().tick_rate(30.0).start().await?;
    let client = server.client().await?;
    let avatar = AvatarId("avatar".into());
    // Hold the walk still at 0.4 s (speed 0), so the pose to compare with does not move.
    client
        .command(Command::Play {
            avatar: avatar.clone(),
            clip: "walk".into(),
            from_asset: None,
            speed: Some(0.0),
            looping: None,
            start: Some(0.4),
            fade: Some(0.0),
            root_motion: None,
        })
        .await?;
    let pose = client.fresh_pose("avatar", DEFAULT_TIMEOUT).await?;
    let expected = server.clip_pose("avatar", "walk", 0.4)?;
    pose.assert_near(&expected, MAX_ERROR_DEGREES)?;
    // Commands answer with typed results.
    let CommandResult::Avatar(state) = client.command(Command::GetAvatar { avatar }).await? else {
        panic!("get_avatar answers with the avatar's state");
    };
    assert_eq!(state.clip.as_deref(), Some("walk"));
    server.stop().await;
    Ok(())
}

/// A live driver's pose reaches a subscriber; a refused command has a typed error.
#[tokio::test]
async fn a_driven_elbow_reaches_the_subscribers() -> Result<(), KitError> {
    let server = TestServer::start().await?;
    let client = server.client().await?;
    let driver = server.driver().await?;
    let avatar = AvatarId("avatar".into());
    driver.drive(&avatar, None, None).await?;
    let bent = glam::Quat::from_rotation_z(1.2);
    driver
        .send_pose(
            &avatar,
            [("l_elbow".to_string(), bent.to_array())],
            None,
            None,
        )
        .await?;
    let pose = client
        .wait_for_pose("avatar", DEFAULT_TIMEOUT, |p| {
            p.rotation("l_elbow")
                .is_some_and(|q| angle_between_degrees(q, bent) <= MAX_ERROR_DEGREES)
        })
        .await?;
    println!("the bent elbow streamed at tick {}", pose.seq());
    // While the driver holds the avatar, nobody else may drive it.
    let second = server.driver().await?;
    let refused = second
        .drive(&avatar, None, None)
        .await
        .map_err(KitError::from);
    assert_eq!(refused.unwrap_err().code(), Some(ErrorCode::Conflict));
    server.stop().await;
    Ok(())
}

/// Not part of a test file: `cargo build --examples` builds this one as a program too (`cargo
/// test -p posecast-testkit --example first_test` runs the tests).
#[cfg(not(test))]
fn main() {}
