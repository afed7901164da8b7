//! Minted tokens (issue 39): what an app asks for when a user joins (`POST /api/tokens`), and
//! what it gets back — a signed token limited to rights, scenes, avatars and a lifetime.
//!
//! The server's side (signing, checking, revoking) is `services/src/auth/minted.rs`;
//! `docs/src/reference/access-control.md` describes the rules.

use crate::ids::{AvatarId, SceneId};
use serde::{Deserialize, Serialize};

/// One thing a token may do.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[cfg_attr(feature = "ts", derive(ts_rs::TS))]
#[serde(rename_all = "snake_case")]
pub enum Right {
    /// Subscribe to scenes and read them (needed only when views are not open to anyone).
    View,
    /// Every command that changes scenes and avatars (play, place, add, pose, …), `drive`
    /// included, within the token's scenes and avatars.
    Control,
    /// Drive avatars live (`drive`, live `pose` messages, IK goals, `look_at`) and nothing else.
    Drive,
    /// Upload assets (counted against the token's quota) and delete its own uploads.
    Upload,
    /// Record avatars into clips (`record`, `stop_recording`) and delete its own recordings.
    Record,
}

impl Right {
    /// Every right, in order.
    pub const ALL: [Self; 5] = [
        Self::View,
        Self::Control,
        Self::Drive,
        Self::Upload,
        Self::Record,
    ];
}

/// `POST /api/tokens`: a token for one user of an app. Only an unlimited control token the
/// operator configured (an *admin* token) may mint; a minted token never mints.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "ts", derive(ts_rs::TS))]
#[serde(deny_unknown_fields)]
pub struct MintRequest {
    /// Who holds it: logs, presence and the owner of what it uploads or records (tokens
    /// minted with one name share that name's quota). 1–64 characters, none of them control
    /// characters; not the name of a configured token.
    pub name: String,
    /// What it may do (default: `["view"]`).
    #[serde(default = "view_only")]
    #[cfg_attr(feature = "ts", ts(as = "Option<Vec<Right>>", optional))]
    pub rights: Vec<Right>,
    /// Only these scenes (and every avatar in them).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[cfg_attr(feature = "ts", ts(optional))]
    pub scenes: Option<Vec<SceneId>>,
    /// Only these avatars.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[cfg_attr(feature = "ts", ts(optional))]
    pub avatars: Option<Vec<AvatarId>>,
    /// Lifetime in seconds (default 3600; at most [`MAX_TTL_S`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[cfg_attr(feature = "ts", ts(optional))]
    pub ttl_s: Option<u64>,
    /// Bytes its name may store (uploads and recordings), within the server's own limit.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[cfg_attr(feature = "ts", ts(optional))]
    pub max_bytes: Option<u64>,
    /// Objects its name may store.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[cfg_attr(feature = "ts", ts(optional))]
    pub max_objects: Option<u64>,
}

fn view_only() -> Vec<Right> {
    vec![Right::View]
}

/// Default lifetime of a minted token: an hour.
pub const DEFAULT_TTL_S: u64 = 3600;
/// Longest lifetime of a minted token: 30 days.
pub const MAX_TTL_S: u64 = 30 * 24 * 3600;
/// Longest name of a minted token.
pub const MAX_NAME_CHARS: usize = 64;
/// Most scenes or avatars one minted token may list.
pub const MAX_LISTED: usize = 256;

/// What a minted token says of itself (its claims): the answer to `GET /api/tokens` lists
/// these, and `POST /api/tokens` returns them with the token.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "ts", derive(ts_rs::TS))]
pub struct TokenInfo {
    /// Its id: `DELETE /api/tokens/{id}` revokes it.
    pub id: String,
    /// Who holds it.
    pub name: String,
    /// What it may do.
    pub rights: Vec<Right>,
    /// Only these scenes.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[cfg_attr(feature = "ts", ts(optional))]
    pub scenes: Option<Vec<SceneId>>,
    /// Only these avatars.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[cfg_attr(feature = "ts", ts(optional))]
    pub avatars: Option<Vec<AvatarId>>,
    /// Unix time (seconds) it was minted.
    pub issued_at: u64,
    /// Unix time (seconds) from which it is refused.
    pub expires_at: u64,
    /// Bytes its name may store.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[cfg_attr(feature = "ts", ts(optional))]
    pub max_bytes: Option<u64>,
    /// Objects its name may store.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[cfg_attr(feature = "ts", ts(optional))]
    pub max_objects: Option<u64>,
}

/// The answer to `POST /api/tokens` (201).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "ts", derive(ts_rs::TS))]
pub struct MintedToken {
    /// The token to hand to the user (`Authorization: Bearer …`, the websocket `hello`'s
    /// `token`, or the dashboard's `?token=`). Shown once: the server keeps only its claims.
    pub token: String,
    /// What it allows.
    pub info: TokenInfo,
}
