//! [`KitError`]: everything a kit call can fail with, each variant naming what it was about.

use posecast_client::net::ClientError;
use posecast_proto::msg::{ErrorCode, ProtocolError};
use std::time::Duration;

/// A kit call failed. The messages are written for a failing test's output: they name the
/// avatar, command, joint or address concerned and what was seen.
#[derive(Debug, thiserror::Error)]
pub enum KitError {
    /// The server did not start (a busy port, a data folder it cannot write, a bad token).
    #[error("the test server did not start: {0}")]
    Start(String),
    /// A set-up command of [`crate::TestServerBuilder`] was refused.
    #[error("set-up command `{op}` was refused: {error}")]
    Setup {
        /// The command's `op`.
        op: String,
        /// The server's typed error.
        error: ProtocolError,
    },
    /// Connecting a client or driver failed, or its connection failed.
    #[error(transparent)]
    Client(ClientError),
    /// The server refused a command with a typed error (match on [`KitError::code`]).
    #[error("command `{op}` was refused: {} ({:?})", error.message, error.code)]
    Refused {
        /// The command's `op`.
        op: String,
        /// The server's typed error.
        error: ProtocolError,
    },
    /// A command's answer did not have the shape its command promises.
    #[error("command `{op}` answered {value}, not a {expected}: {message}")]
    UnexpectedResult {
        /// The command's `op`.
        op: String,
        /// The shape expected.
        expected: &'static str,
        /// The answer.
        value: serde_json::Value,
        /// Why it did not fit.
        message: String,
    },
    /// No streamed pose of the avatar satisfied the condition in time.
    #[error(
        "timed out after {waited:?} waiting for avatar `{avatar}` ({what}); last pose seen: {last}"
    )]
    Timeout {
        /// The avatar.
        avatar: String,
        /// What was waited for.
        what: String,
        /// How long.
        waited: Duration,
        /// The last pose seen, written out (`none` when none arrived).
        last: String,
    },
    /// A streamed pose differs from the expected one by more than the tolerance.
    #[error(
        "avatar `{avatar}` at tick {seq}: joint `{joint}` is {degrees:.4}° off the expected pose (tolerance {tolerance}°)"
    )]
    PoseMismatch {
        /// The avatar.
        avatar: String,
        /// The tick of the streamed pose.
        seq: u64,
        /// The joint that is furthest off.
        joint: String,
        /// How far off it is, degrees.
        degrees: f64,
        /// The tolerance, degrees.
        tolerance: f64,
    },
    /// Two poses have different joint counts (different rigs).
    #[error("avatar `{avatar}` has {streamed} joints but the expected pose has {expected}")]
    JointCount {
        /// The avatar.
        avatar: String,
        /// Joints streamed.
        streamed: usize,
        /// Joints expected.
        expected: usize,
    },
    /// The server has no rig by that name.
    #[error("no asset `{0}` is loaded")]
    UnknownAsset(String),
    /// The rig has no joint by that name.
    #[error("asset `{asset}` has no joint `{joint}`")]
    UnknownJoint {
        /// The rig.
        asset: String,
        /// The joint asked for.
        joint: String,
    },
    /// The rig has no clip by that name.
    #[error("asset `{asset}` has no clip `{clip}` (it has: {available})")]
    UnknownClip {
        /// The rig.
        asset: String,
        /// The clip asked for.
        clip: String,
        /// The clips it has, comma-separated.
        available: String,
    },
}

impl KitError {
    /// The server's error code, when the server refused something.
    ///
    /// ```
    /// use posecast_proto::msg::{ErrorCode, ProtocolError};
    /// use posecast_testkit::KitError;
    /// let e = KitError::Refused {
    ///     op: "play".into(),
    ///     error: ProtocolError { code: ErrorCode::UnknownClip, message: "no clip".into(), id: None, retry_after_ms: None, details: None },
    /// };
    /// assert_eq!(e.code(), Some(ErrorCode::UnknownClip));
    /// ```
    #[must_use]
    pub fn code(&self) -> Option<ErrorCode> {
        match self {
            Self::Refused { error, .. } | Self::Setup { error, .. } => Some(error.code),
            Self::Client(ClientError::Server(e)) => Some(e.code),
            _ => None,
        }
    }
}

impl From<ClientError> for KitError {
    fn from(e: ClientError) -> Self {
        Self::Client(e)
    }
}
