//! The network client library: connect, hello, subscribe, keep descriptions, decode frames,
//! expose the latest and an interpolated pose per avatar, send commands, reconnect with
//! back-off and resubscribe. No GPU needed; usable in-process from tests.
//!
//! - [`client`]: the [`Client`] handle and its background connection task.
//! - [`jitter`]: the adaptive jitter buffer.
//! - [`clock`]: clock offset and round-trip estimation from ping/pong.

pub mod client;
pub mod clock;
pub mod jitter;

pub use client::{AvatarView, Client, ClientError, ClientOptions, Event, PoseSample, Stats};
