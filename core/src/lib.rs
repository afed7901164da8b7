//! What every layer of the posecast server shares, and nothing else.
//!
//! - [`error`]: the typed [`error::Error`] every layer returns; it becomes the wire's
//!   `ProtocolError` (a stable code, a message, structured fields) in one place
//!   (`From<&Error> for ProtocolError`), so no layer spells an error code by hand.
//! - [`quota`]: the deployment's limits ([`quota::Quotas`]: joints per rig, clip sizes,
//!   scenes, subscribers, rates) and the token buckets that enforce the rates, each limit
//!   with its own typed "exceeded" error.
//!
//! It depends only on `posecast-proto`: the crates above it (`posecast-rigs`,
//! `posecast-sim`, `posecast-server`) may use it, never the other way round.

#![warn(missing_docs)]
pub mod error;
pub mod quota;
