//! # posecast-testkit: posecast inside your integration tests
//!
//! For teams whose virtual-human app talks to posecast and who want to test it end to end
//! without a separate process: start a real server in the test's own process on a free port,
//! connect the real client library, and check what streams.
//!
//! - [`TestServer`] / [`TestServerBuilder`]: a server in one call, with the built-in avatar by
//!   default, or your assets folder, scenes, avatars, tick rate and tokens; stopped by
//!   [`TestServer::stop`], or by dropping it — so a test that panics still closes its
//!   websockets and listener.
//! - [`TestClient`]: posecast's own [`posecast_client::net::Client`] (it derefs to one),
//!   subscribed to a scene in binary or JSON, with the waits a test needs:
//!   [`TestClient::wait_for_pose`] (a predicate, a timeout, and an error naming the avatar and
//!   the last pose seen), [`TestClient::fresh_pose`] (a pose computed after your commands),
//!   [`TestClient::wait_until_near`], and [`TestClient::command`] with typed results
//!   ([`posecast_proto::command::CommandResult`]) and typed errors ([`KitError::code`]).
//! - Expected poses from the server's own clip sampling ([`TestServer::clip_pose`],
//!   [`sample_clip`]) and a comparison in degrees that names the worst joint
//!   ([`StreamedPose::assert_near`]).
//! - Live driving: [`TestServer::driver`] gives the library's
//!   [`posecast_client::net::Driver`] holding the control token.
//!
//! ## Why a crate, not a `testing` feature
//!
//! A test kit needs the server *and* the client. As a feature of `posecast-server` it would
//! make the server depend on the client (or the reverse), and every helper would become API of
//! a crate whose users never test with it. As its own crate it depends on both as they are —
//! the client without its `render` feature, so tests need no GPU and build no wgpu — neither
//! crate gains test-only API, and a user adds one line to `[dev-dependencies]`. The repository's
//! own end-to-end tests (`tests/`) use it too, so it is exercised on every run.
//!
//! ## A whole test
//!
//! ```
//! use posecast_proto::command::Command;
//! use posecast_proto::msg::AvatarId;
//! use posecast_testkit::TestServer;
//! use std::time::Duration;
//!
//! # #[tokio::main(flavor = "current_thread")]
//! # async fn main() -> Result<(), posecast_testkit::KitError> {
//! let server = TestServer::builder().tick_rate(30.0).start().await?;
//! let client = server.client().await?;
//! let avatar = AvatarId("avatar".into());
//! // Hold the walk at 0.4 s, then check what streams against the clip sampled there.
//! client.command(Command::Play {
//!     avatar: avatar.clone(), clip: "walk".into(), from_asset: None, speed: Some(0.0),
//!     looping: None, start: Some(0.4), fade: Some(0.0), root_motion: None,
//! }).await?;
//! let pose = client.fresh_pose("avatar", Duration::from_secs(10)).await?;
//! pose.assert_near(&server.clip_pose("avatar", "walk", 0.4)?, posecast_proto::quant::MAX_ERROR_DEGREES)?;
//! server.stop().await;
//! # Ok(()) }
//! ```
//!
//! Timeouts: the waits take one; [`DEFAULT_TIMEOUT`] (10 s) is generous enough for a loaded
//! CI machine. A `#[tokio::test]` runs the server on the test's runtime: the default
//! single-threaded one is enough.

#![deny(missing_docs)]

mod client;
mod command;
mod error;
pub mod pose;
mod server;

pub use client::{ClientBuilder, TestClient};
pub use command::{op, typed_result};
pub use error::KitError;
pub use pose::{PoseDiff, StreamedPose, sample_clip};
pub use server::{DEFAULT_CONTROL_TOKEN, TestServer, TestServerBuilder};

/// A timeout for the waits that is generous on a loaded 2-core CI machine: 10 s.
///
/// ```
/// assert_eq!(posecast_testkit::DEFAULT_TIMEOUT.as_secs(), 10);
/// ```
pub const DEFAULT_TIMEOUT: std::time::Duration = std::time::Duration::from_secs(10);
