//! The ids every part of the protocol names things by: a scene's and an avatar's. Their own
//! module, below the messages, commands, descriptions, tokens and trackers that use them, so
//! none of those modules needs another to name an avatar (`msg` re-exports them under their
//! old paths). Checking an id's form is [`crate::msg::check_id`].

use serde::{Deserialize, Serialize};
use std::fmt;

/// A scene's id, chosen by whoever creates the scene (`"default"` for the built-in one).
#[derive(Debug, Clone, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[cfg_attr(feature = "ts", derive(ts_rs::TS))]
#[serde(transparent)]
pub struct SceneId(pub String);

/// An avatar's id, unique on the server.
#[derive(Debug, Clone, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[cfg_attr(feature = "ts", derive(ts_rs::TS))]
#[serde(transparent)]
pub struct AvatarId(pub String);

impl fmt::Display for SceneId {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.0)
    }
}

impl fmt::Display for AvatarId {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.0)
    }
}
