//! The answers of a scene's latest commands that carried an idempotency key (PROTOCOL.md,
//! "Idempotency"): a retry of an acknowledged command is answered with the first answer and
//! not applied again; the same key used for another op is a `conflict`. The table lives with
//! the scene and in its snapshot (`posecast_services::store::snapshot::SceneFile::recent`), so a retry
//! after a restart — or, in a cluster, after another server took the scene over — is answered
//! too. A server on its own keeps it in [`super::Scene`] (its keyed commands on one scene run
//! one at a time, [`super::Scene::keyed`]); a cluster's owner keeps it beside its commit lock
//! (`cluster::commit`) with the same functions.

use posecast_core::error::Error;
use posecast_proto::command::{Command, CommandResult};
use serde::{Deserialize, Serialize};
use std::collections::VecDeque;

/// How many keyed commands' answers a scene keeps (the oldest is forgotten first): enough for
/// every client of a scene to retry its last few commands, small enough that the snapshot
/// stays a few kilobytes.
pub const RECENT: usize = 256;

/// A command that carried an idempotency key, and its answer.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RecentCommand {
    /// The client's key.
    pub key: String,
    /// The command's `op` (a key used again for another command is refused, not answered).
    pub op: String,
    /// The result it was acknowledged with, tagged with its kind (a snapshot of before tagged
    /// results holds the bare value, read by its shape).
    #[serde(deserialize_with = "tagged_or_bare")]
    pub result: CommandResult,
}

fn tagged_or_bare<'de, D: serde::Deserializer<'de>>(d: D) -> Result<CommandResult, D::Error> {
    let value = serde_json::Value::deserialize(d)?;
    CommandResult::from_tagged_or_bare(value).map_err(serde::de::Error::custom)
}

/// The answers of a scene's latest keyed commands, oldest first.
pub type Recent = VecDeque<RecentCommand>;

/// The op of a command, as on the wire (`add_avatar`).
#[must_use]
pub fn op_of(command: &Command) -> String {
    serde_json::to_value(command)
        .ok()
        .and_then(|v| v.get("op").and_then(|o| o.as_str()).map(str::to_owned))
        .unwrap_or_default()
}

/// The answer of a keyed command already acknowledged, or `None` when the key is new.
#[must_use]
pub fn answered(recent: &Recent, key: &str, op: &str) -> Option<Result<CommandResult, Error>> {
    let done = recent.iter().find(|r| r.key == key)?;
    if done.op != op {
        return Some(Err(Error::Conflict(format!(
            "idempotency key {key} was used for a {} command: choose a new key for each command",
            done.op
        ))));
    }
    Some(Ok(done.result.clone()))
}

/// Remembers `result` as the answer to `key`, forgetting the oldest past [`RECENT`].
pub fn remember(recent: &mut Recent, key: &str, op: String, result: &CommandResult) {
    recent.push_back(RecentCommand {
        key: key.to_owned(),
        op,
        result: result.clone(),
    });
    while recent.len() > RECENT {
        recent.pop_front();
    }
}

/// Forgets the answer to `key` (its command's change could not be stored).
pub fn forget(recent: &mut Recent, key: &str) {
    recent.retain(|r| r.key != key);
}

#[cfg(test)]
mod tests {
    use super::*;
    use posecast_proto::msg::AvatarId;

    #[test]
    fn recent_answers_again_and_forgets_the_oldest() {
        let mut recent = Recent::new();
        let added = CommandResult::AvatarAdded {
            avatar: AvatarId("a1".into()),
        };
        remember(&mut recent, "k1", "add_avatar".into(), &added);
        assert_eq!(answered(&recent, "k1", "add_avatar"), Some(Ok(added)));
        assert!(matches!(
            answered(&recent, "k1", "remove_avatar"),
            Some(Err(Error::Conflict(_)))
        ));
        assert_eq!(answered(&recent, "k2", "add_avatar"), None);
        for i in 0..RECENT {
            remember(
                &mut recent,
                &format!("n{i}"),
                "stop".into(),
                &CommandResult::Done,
            );
        }
        assert_eq!(recent.len(), RECENT);
        assert_eq!(answered(&recent, "k1", "add_avatar"), None);
        assert!(answered(&recent, "n0", "stop").is_some());
        forget(&mut recent, "n0");
        assert_eq!(answered(&recent, "n0", "stop"), None);
    }

    /// Answers are stored tagged with their kind, so an empty list stays the list it was; a
    /// snapshot of before tagged results (bare values) still reads.
    #[test]
    fn stored_answers_keep_their_kind_and_old_snapshots_read() {
        let assets = RecentCommand {
            key: "k".into(),
            op: "configure_asset".into(),
            result: CommandResult::Assets(Vec::new()),
        };
        let stored = serde_json::to_value(&assets).unwrap();
        assert_eq!(stored["result"]["kind"], "assets", "{stored}");
        let back: RecentCommand = serde_json::from_value(stored).unwrap();
        assert_eq!(back, assets);
        let old: RecentCommand = serde_json::from_value(serde_json::json!({
            "key": "k", "op": "add_avatar", "result": { "avatar": "a1" }
        }))
        .unwrap();
        assert_eq!(
            old.result,
            CommandResult::AvatarAdded {
                avatar: AvatarId("a1".into())
            }
        );
        let done: RecentCommand = serde_json::from_value(serde_json::json!({
            "key": "k", "op": "stop", "result": null
        }))
        .unwrap();
        assert_eq!(done.result, CommandResult::Done);
    }
}
