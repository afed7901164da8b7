//! posecast clients: [`net`], the network client library (no GPU needed, usable in-process),
//! and, with the `render` feature, `render`, the wgpu renderer (GPU skinning, offscreen and
//! windowed), and `view_source`, which feeds the renderer from the network client.
//!
//! # Example
//!
//! Watch scene `lobby` on a server and print each avatar's newest pose (needs a running
//! server, so it is compiled here, not run):
//!
//! ```rust,no_run
//! use posecast_client::net::{Client, ClientOptions, Event};
//!
//! async fn watch() -> Result<(), Box<dyn std::error::Error>> {
//!     // Binary frames, reconnecting with back-off, resubscribing after every reconnect.
//!     let options = ClientOptions::new("ws://127.0.0.1:8080/ws", "lobby");
//!     let client = Client::connect(options).await?;
//!     let mut events = client.events();
//!     // Descriptions come before frames, so after the first frame the avatars are known.
//!     while !matches!(events.recv().await?, Event::Frame { .. }) {}
//!     for avatar in client.avatars() {
//!         let id = &avatar.description.id;
//!         if let Some(pose) = client.latest(id) {
//!             // Local transforms D_j, one per joint; the placement says where it stands.
//!             assert_eq!(pose.locals.len(), avatar.skeleton.len());
//!             println!("{id}: tick {}, at {} m", pose.seq, pose.placement.position);
//!         }
//!     }
//!     Ok(())
//! }
//! ```

#![warn(missing_docs)]
pub mod net;
#[cfg(feature = "render")]
pub mod render;
#[cfg(feature = "render")]
pub mod view_source;
