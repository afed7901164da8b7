//! Typed command results: protocol version 3 tags an `ack`'s result with its kind; versions 1
//! and 2 (and a REST client reading `result` alone) have only the bare value, whose shape
//! depends on the command (so an empty list is ambiguous). Knowing the command sent,
//! [`typed_result`] reads a bare value into the one variant that command answers with.

use crate::KitError;
use posecast_client::net::ClientError;
use posecast_proto::command::{
    AssetDetail, AssetInfo, AvatarState, Command, CommandResult, DriveInfo, JointInfo,
    RecordingInfo, SceneInfo,
};
use posecast_proto::msg::{AvatarId, SceneId};
use serde_json::Value;

/// The command's `op`, as on the wire (`"play"`, `"add_avatar"`, …).
///
/// ```
/// use posecast_proto::command::Command;
/// assert_eq!(posecast_testkit::op(&Command::ListScenes), "list_scenes");
/// ```
#[must_use]
pub fn op(command: &Command) -> String {
    serde_json::to_value(command)
        .ok()
        .and_then(|v| v.get("op").and_then(Value::as_str).map(str::to_owned))
        .unwrap_or_default()
}

/// Reads a command's answer (`ack.result`, `null` when absent) as the [`CommandResult`]
/// variant `command` answers with: `list_scenes` → [`CommandResult::Scenes`], `get_avatar` →
/// [`CommandResult::Avatar`], `drive` → [`CommandResult::Drive`], the joint rotations →
/// [`CommandResult::Rotation`], and so on; commands with nothing to say →
/// [`CommandResult::Done`].
///
/// # Errors
/// [`KitError::UnexpectedResult`] when the value does not have that variant's shape.
///
/// ```
/// use posecast_proto::command::{Command, CommandResult};
/// use posecast_testkit::typed_result;
/// let listed = typed_result(&Command::ListScenes, serde_json::json!([])).unwrap();
/// assert_eq!(listed, CommandResult::Scenes(Vec::new()));
/// // The same `[]` is an empty asset list when it answers `list_assets`.
/// let assets = typed_result(&Command::ListAssets, serde_json::json!([])).unwrap();
/// assert_eq!(assets, CommandResult::Assets(Vec::new()));
/// // A shape that does not fit is an error naming the command.
/// let err = typed_result(&Command::ListScenes, serde_json::json!({"x": 1})).unwrap_err();
/// assert!(err.to_string().contains("list_scenes"), "{err}");
/// ```
pub fn typed_result(command: &Command, value: Value) -> Result<CommandResult, KitError> {
    fn read<T: serde::de::DeserializeOwned>(
        command: &Command,
        value: Value,
        expected: &'static str,
    ) -> Result<T, KitError> {
        serde_json::from_value(value.clone()).map_err(|e| KitError::UnexpectedResult {
            op: op(command),
            expected,
            value,
            message: e.to_string(),
        })
    }
    #[derive(serde::Deserialize)]
    struct Scene {
        scene: SceneId,
    }
    #[derive(serde::Deserialize)]
    struct Added {
        avatar: AvatarId,
    }
    #[derive(serde::Deserialize)]
    struct Dofs {
        rotation: [f32; 4],
        values: Vec<f32>,
    }
    #[derive(serde::Deserialize)]
    struct Rotation {
        rotation: [f32; 4],
    }
    Ok(match command {
        Command::ListScenes => {
            CommandResult::Scenes(read::<Vec<SceneInfo>>(command, value, "list of scenes")?)
        }
        Command::ListAssets | Command::ConfigureAsset { .. } => {
            CommandResult::Assets(read::<Vec<AssetInfo>>(command, value, "list of assets")?)
        }
        Command::GetAsset { .. } => {
            CommandResult::Asset(read::<Box<AssetDetail>>(command, value, "asset detail")?)
        }
        Command::GetAvatar { .. } => {
            CommandResult::Avatar(read::<Box<AvatarState>>(command, value, "avatar state")?)
        }
        Command::GetJoint { .. } => {
            CommandResult::Joint(read::<Box<JointInfo>>(command, value, "joint")?)
        }
        Command::Drive { .. } => {
            CommandResult::Drive(read::<Box<DriveInfo>>(command, value, "drive info")?)
        }
        Command::CalibrateTrackers { .. } => {
            CommandResult::Calibration(read::<Box<posecast_proto::trackers::CalibrationInfo>>(
                command,
                value,
                "calibration",
            )?)
        }
        Command::StopRecording { .. } => {
            CommandResult::Recorded(read::<Box<RecordingInfo>>(command, value, "recording")?)
        }
        Command::CreateScene { .. } => CommandResult::SceneCreated {
            scene: read::<Scene>(command, value, "created scene")?.scene,
        },
        Command::AddAvatar { .. } => CommandResult::AvatarAdded {
            avatar: read::<Added>(command, value, "added avatar")?.avatar,
        },
        Command::SetJointDofs { .. } => {
            let d = read::<Dofs>(command, value, "rotation and DOF values")?;
            CommandResult::Dofs {
                rotation: d.rotation,
                values: d.values,
            }
        }
        Command::SetJointRotation { .. }
        | Command::RotateJointLocal { .. }
        | Command::RotateJointWorld { .. } => CommandResult::Rotation {
            rotation: read::<Rotation>(command, value, "rotation")?.rotation,
        },
        _ if value.is_null() => CommandResult::Done,
        _ => {
            return Err(KitError::UnexpectedResult {
                op: op(command),
                expected: "null",
                value,
                message: "this command answers with nothing".into(),
            });
        }
    })
}

/// A command's outcome from a client or driver: the typed result, or the server's typed
/// refusal as [`KitError::Refused`] (other failures as [`KitError::Client`]).
pub(crate) fn outcome(
    command: &Command,
    answer: Result<CommandResult, ClientError>,
) -> Result<CommandResult, KitError> {
    match answer {
        // Tagged (protocol 3) or read by its shape (1 and 2): either way the variant must be
        // the one `command` answers with — an empty list read as `scenes` for `list_assets`
        // is read again as `assets`.
        Ok(result) => typed_result(command, result.to_value()),
        Err(ClientError::Server(error)) => Err(KitError::Refused {
            op: op(command),
            error,
        }),
        Err(e) => Err(KitError::Client(e)),
    }
}
