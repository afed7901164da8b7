//! Publication: what leaves the server for its subscribers (the crate `posecast-stream`).
//!
//! It takes poses ([`Snapshot`]s, copied by the server's scenes under their lock) and turns
//! them into frames on every subscriber's connection. It knows avatars (`posecast-sim`) but no
//! scenes, no sockets beyond the websocket message type, and no other server: relaying to one
//! is a [`feed::Tap`] the server's cluster layer installs. What it counts goes through
//! [`Counters`], which the server's metrics implement.
//!
//! - [`feed`]: a scene's subscribers, and each tick's frame encoded once per encoding and
//!   fanned out to them (with what a late joiner starts from).
//! - `publish`: a frame as per-avatar pieces in both encodings, made from the poses a tick
//!   copied under the scene lock ([`Snapshot`]).
//! - [`outbox`]: the bounded per-connection queue (newest frame wins).
//! - [`writer`]: the task that drains an outbox into its websocket.
//! - [`direct`]: an outbox that writes into its socket itself, from whatever queued the
//!   message (the tick's fan-out), with websocket frames built once per message.
//! - [`pace`]: a connection's adaptive frame rate (lowered until its link keeps up).
//! - [`probes`]: the one clock every connection's round-trip probes follow.
//! - [`relay`]: a published frame as bytes for another server (scale-out), and back.
//! - [`take`]: the file format of a scene's take (its encoded frames and avatar lists,
//!   append-only and readable up to the last whole record after a crash).
//! - [`wire2`]: wire v2 frames (protocol version 2), shared by subscribers holding the same
//!   frames.

#![warn(missing_docs)]
pub mod direct;
pub mod feed;
pub mod outbox;
pub mod pace;
pub mod probes;
mod publish;
pub mod relay;
pub mod take;
pub mod wire2;
pub mod writer;

pub use publish::Snapshot;

/// What the stream layer counts (the server's `/metrics` implements it).
pub trait Counters: Send + Sync + std::fmt::Debug {
    /// `frames` frames offered to outboxes this tick, `bytes` of them.
    fn frames_offered(&self, frames: u64, bytes: u64);
    /// A tick (or a JSON late joiner) serialised `poses` avatar poses to JSON.
    fn json_encoded(&self, poses: u64);
    /// A writer sent `messages` websocket messages, `bytes` of them.
    fn sent(&self, messages: u64, bytes: u64);
    /// A writer task woke to write: [`writer::run_writer`] for each batch it takes, and
    /// [`direct::run_direct`] when its socket was full or the connection closed.
    fn writer_woke(&self) {}
}
