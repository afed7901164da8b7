//! The network client library: connect, hello, subscribe, keep descriptions, decode frames,
//! expose the latest and an interpolated pose per avatar, send commands, reconnect with
//! back-off and resubscribe. No GPU needed; usable in-process from tests.
//!
//! - [`client`]: the [`Client`] handle and its background connection task.
//! - [`transport`]: the websocket or WebTransport (frames as datagrams) under it.
//! - [`jitter`]: the adaptive jitter buffer.
//! - [`clock`]: clock offset and round-trip estimation from ping/pong.
//! - [`driver`]: [`Driver`], which drives avatars live with a stream of poses.

pub mod client;
pub mod clock;
pub mod driver;
pub mod jitter;
pub mod transport;

pub use client::{AvatarView, Client, ClientError, ClientOptions, Event, PoseSample, Stats};
pub use driver::Driver;
pub use transport::{Transport, TransportChoice};
