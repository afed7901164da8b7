//! Publication: what leaves the server for its subscribers.
//!
//! - [`feed`]: a scene's subscribers, and each tick's frame encoded once per encoding and
//!   fanned out to them (with what a late joiner starts from).
//! - `publish`: a frame as per-avatar pieces in both encodings, made from the poses a tick
//!   copied under the scene lock ([`Snapshot`]).
//! - [`outbox`]: the bounded per-connection queue (newest frame wins).
//! - [`writer`]: the task that drains an outbox into its websocket.
//! - [`pace`]: a connection's adaptive frame rate (lowered until its link keeps up).
//! - [`relay`]: a published frame as bytes for another server (scale-out), and back.
//! - [`wire2`]: wire v2 frames (protocol version 2), shared by subscribers holding the same
//!   frames.

pub mod feed;
pub mod outbox;
pub mod pace;
mod publish;
pub mod relay;
pub mod wire2;
pub mod writer;

pub use publish::Snapshot;
