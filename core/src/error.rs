//! The server's error: what went wrong, typed, in every layer below the transport; turned into
//! the wire's [`ProtocolError`] (a stable code and a message) in one place, [`From`].
//!
//! The transport (`service`) also builds a few wire errors of its own — a message that is not
//! JSON, a missing hello — that have no meaning below it.

use posecast_proto::msg::{AvatarId, ErrorCode, ErrorDetails, ProtocolError, SceneId};

/// Whose joint (or tracker) or expression an error names: the avatar or rig a client can act
/// on travels in the wire error's `details` (`avatar`, `asset`), and the message reads as
/// before ("avatar a has no joint x").
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Owner {
    /// An avatar's rig: "avatar a".
    Avatar(AvatarId),
    /// A rig by name (a live driver's source): "rig r".
    Rig(String),
    /// A rig by name, addressed by joint index: "rig r (of n joints)".
    RigOfJoints {
        /// The rig.
        rig: String,
        /// How many joints it has.
        joints: usize,
    },
    /// The rig whose poses drive an avatar, as a server relaying them knows it: "the rig
    /// driving a".
    DriverOf(AvatarId),
    /// The same, addressed by joint index: "the driven rig (of n joints)".
    DriverOfJoints {
        /// The avatar driven.
        avatar: AvatarId,
        /// How many joints the driving rig has.
        joints: usize,
    },
    /// An avatar's weight channels, addressed by index: "avatar a (of c morph channels and e
    /// expressions)".
    Channels {
        /// The avatar.
        avatar: AvatarId,
        /// Its morph targets.
        channels: usize,
        /// Its expressions addressable after them (0: none).
        expressions: usize,
    },
    /// A tracker drive of an avatar: "the tracker drive of avatar a (trackers t1, t2)".
    Trackers {
        /// The avatar driven.
        avatar: AvatarId,
        /// Its trackers, in the drive's order.
        trackers: Vec<String>,
    },
}

impl Owner {
    /// The avatar it belongs to, if any.
    #[must_use]
    pub fn avatar(&self) -> Option<&AvatarId> {
        match self {
            Self::Avatar(a) | Self::DriverOf(a) => Some(a),
            Self::DriverOfJoints { avatar, .. }
            | Self::Channels { avatar, .. }
            | Self::Trackers { avatar, .. } => Some(avatar),
            Self::Rig(_) | Self::RigOfJoints { .. } => None,
        }
    }

    /// The rig (asset) it is, if named.
    #[must_use]
    pub fn rig(&self) -> Option<&str> {
        match self {
            Self::Rig(r) | Self::RigOfJoints { rig: r, .. } => Some(r),
            _ => None,
        }
    }
}

impl std::fmt::Display for Owner {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Avatar(a) => write!(f, "avatar {a}"),
            Self::Rig(r) => write!(f, "rig {r}"),
            Self::RigOfJoints { rig, joints } => write!(f, "rig {rig} (of {joints} joints)"),
            Self::DriverOf(a) => write!(f, "the rig driving {a}"),
            Self::DriverOfJoints { joints, .. } => write!(f, "the driven rig (of {joints} joints)"),
            Self::Channels {
                avatar,
                channels,
                expressions,
            } => {
                write!(f, "avatar {avatar} (of {channels} morph channels")?;
                if *expressions > 0 {
                    write!(f, " and {expressions} expressions")?;
                }
                write!(f, ")")
            }
            Self::Trackers { avatar, trackers } => write!(
                f,
                "the tracker drive of avatar {avatar} (trackers {})",
                trackers.join(", ")
            ),
        }
    }
}

/// A failed request, command or import step. Nothing was changed by whatever returned it.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum Error {
    /// No such scene.
    #[error("no scene {0}")]
    UnknownScene(SceneId),
    /// No such avatar.
    #[error("no avatar {0}")]
    UnknownAvatar(AvatarId),
    /// A subscription's filter names an avatar the scene does not have.
    #[error("scene {scene} has no avatar {avatar}")]
    NotInScene {
        /// The scene.
        scene: SceneId,
        /// The avatar named.
        avatar: AvatarId,
    },
    /// A rig (an avatar's, or a live driver's source) has no such joint.
    #[error("{owner} has no joint {joint}")]
    UnknownJoint {
        /// Whose joint.
        owner: Owner,
        /// The joint asked for (a name, or an index).
        joint: String,
    },
    /// An avatar has no morph target or standard expression of that name, or no morph
    /// targets at all.
    #[error("{owner} has no morph target or expression {name}{}", if *.has_targets { "" } else { " (it has no morph targets)" })]
    UnknownExpression {
        /// Whose.
        owner: Owner,
        /// The name asked for.
        name: String,
        /// Whether the avatar has any morph targets.
        has_targets: bool,
    },
    /// A rig has no such clip.
    #[error("rig {rig} has no clip {clip}")]
    UnknownClip {
        /// The rig.
        rig: String,
        /// The clip asked for.
        clip: String,
    },
    /// No take (`record_scene`) of that name, or none that can be read.
    #[error("{}", match unreadable { Some(why) => format!("take {take} cannot be read: {why}"), None => format!("no take {take}") })]
    UnknownTake {
        /// The take asked for.
        take: String,
        /// Why a take of that name cannot be read, if it exists.
        unreadable: Option<String>,
    },
    /// No rig (asset) of that name is loaded.
    #[error("no rig (asset) named {asset}{}", needed_by.as_ref().map(|n| format!(" ({n} was made of it)")).unwrap_or_default())]
    UnknownAsset {
        /// The rig asked for.
        asset: String,
        /// What needed it, when that is not the request itself (a take's avatar).
        needed_by: Option<String>,
    },
    /// A value out of range, not finite, or not allowed here.
    #[error("{message}")]
    Invalid {
        /// The request's field whose value is refused (`speed`, `weight`, `scene`), when one
        /// is: the wire error's `details.field`.
        field: Option<&'static str>,
        /// What is wrong with it.
        message: String,
    },
    /// The thing exists already, or another client holds it.
    #[error("{0}")]
    Conflict(String),
    /// Not in this state (e.g. a pose from a connection that does not drive the avatar).
    #[error("{0}")]
    NotAllowedNow(String),
    /// An uploaded asset could not be imported or normalised.
    #[error("{0}")]
    ImportFailed(String),
    /// A server-side failure (storage, a task that died); the request may be retried.
    #[error("{0}")]
    Internal(String),
    /// A deployment limit ([`crate::quota::Quotas`]).
    #[error("quota {quota}: {detail} (the limit is {limit})")]
    Quota {
        /// Which limit (its name in `/metrics` and the message).
        quota: &'static str,
        /// What was asked.
        detail: String,
        /// The limit, as people read it.
        limit: String,
    },
    /// Too many commands or poses: try again after the hint.
    #[error("{message}")]
    RateLimited {
        /// What is limited, and when to try again.
        message: String,
        /// Milliseconds until one would be accepted.
        retry_after_ms: u64,
    },
    /// No token, or an unknown one.
    #[error("{0}")]
    Unauthorized(String),
    /// The token does not allow this.
    #[error("{0}")]
    Forbidden(String),
    /// A binary message that is not a pose.
    #[error("{0}")]
    UnexpectedBinary(String),
    /// The request is too large.
    #[error("{0}")]
    TooLarge(String),
    /// The server is not ready (starting) or is stopping.
    #[error("{0}")]
    Unavailable(String),
    /// Retargeting between a humanoid and a rig that is not one.
    #[error("{0}")]
    NotHumanoid(String),
    /// A rig without a mesh asked for its mesh.
    #[error("rig {0} has no mesh")]
    NoMesh(String),
    /// The command may or may not have been applied: another server of the cluster did not
    /// answer in time, or a write to the cluster's store was not answered (it may have
    /// landed). Unlike [`Error::Unavailable`] (not applied), a retry must carry the same
    /// idempotency key to apply at most once.
    #[error("{0}")]
    OutcomeUnknown(String),
    /// The disk is full (`ENOSPC`, `EDQUOT`): nothing was changed or stored.
    #[error("{0}")]
    StorageFull(String),
    /// The error another server of the cluster answered with (a forwarded command), as it
    /// was on the wire.
    #[error("{}", .0.message)]
    Remote(ProtocolError),
}

impl Error {
    /// The stable wire code.
    #[must_use]
    pub fn code(&self) -> ErrorCode {
        match self {
            Self::UnknownScene(_) => ErrorCode::UnknownScene,
            Self::UnknownAvatar(_) | Self::NotInScene { .. } => ErrorCode::UnknownAvatar,
            Self::UnknownJoint { .. } => ErrorCode::UnknownJoint,
            Self::UnknownExpression { .. } => ErrorCode::UnknownExpression,
            Self::UnknownClip { .. } => ErrorCode::UnknownClip,
            Self::UnknownAsset { .. } => ErrorCode::UnknownAsset,
            Self::UnknownTake { .. } => ErrorCode::UnknownTake,
            Self::Invalid { .. } => ErrorCode::InvalidValue,
            Self::Conflict(_) => ErrorCode::Conflict,
            Self::NotAllowedNow(_) => ErrorCode::NotAllowedNow,
            Self::ImportFailed(_) => ErrorCode::ImportFailed,
            Self::Internal(_) => ErrorCode::Internal,
            Self::Quota { .. } => ErrorCode::QuotaExceeded,
            Self::RateLimited { .. } => ErrorCode::RateLimited,
            Self::Unauthorized(_) => ErrorCode::Unauthorized,
            Self::Forbidden(_) => ErrorCode::Forbidden,
            Self::UnexpectedBinary(_) => ErrorCode::UnexpectedBinary,
            Self::TooLarge(_) => ErrorCode::TooLarge,
            Self::Unavailable(_) => ErrorCode::Unavailable,
            Self::NotHumanoid(_) => ErrorCode::NotHumanoid,
            Self::NoMesh(_) => ErrorCode::NoMesh,
            Self::StorageFull(_) => ErrorCode::StorageFull,
            Self::OutcomeUnknown(_) => ErrorCode::OutcomeUnknown,
            Self::Remote(wire) => wire.code,
        }
    }

    /// An [`Error::UnknownAsset`] asked for by the request itself.
    pub fn unknown_asset(asset: impl Into<String>) -> Self {
        Self::UnknownAsset {
            asset: asset.into(),
            needed_by: None,
        }
    }

    /// An [`Error::Invalid`] that names no field.
    pub fn invalid(message: impl Into<String>) -> Self {
        Self::Invalid {
            field: None,
            message: message.into(),
        }
    }

    /// An [`Error::Invalid`] about the request's field `field`.
    pub fn invalid_field(field: &'static str, message: impl Into<String>) -> Self {
        Self::Invalid {
            field: Some(field),
            message: message.into(),
        }
    }

    /// The wire error answering command `id`.
    #[must_use]
    pub fn for_command(self, id: u64) -> ProtocolError {
        ProtocolError::from(self).for_command(id)
    }

    /// The error for an I/O failure while storing `what`: [`Error::StorageFull`] when the disk
    /// or a file-system quota is full (so a client can tell "free room" from "try again"),
    /// else [`Error::Internal`].
    #[must_use]
    pub fn storing(what: &str, e: &std::io::Error) -> Self {
        if is_storage_full(e) {
            Self::StorageFull(format!("{what}: the server's disk is full ({e})"))
        } else {
            Self::internal(what, e)
        }
    }

    /// An [`Error::Internal`]: `what` failed because of `e`.
    pub fn internal(what: &str, e: &dyn std::fmt::Display) -> Self {
        Self::Internal(format!("{what}: {e}"))
    }
}

/// Whether an I/O error means "no room": `ENOSPC` (disk full) or `EDQUOT` (a file-system
/// quota), as `io::ErrorKind` names them.
#[must_use]
pub fn is_storage_full(e: &std::io::Error) -> bool {
    matches!(
        e.kind(),
        std::io::ErrorKind::StorageFull | std::io::ErrorKind::QuotaExceeded
    )
}

impl Error {
    /// What the error is about, for the wire ([`ErrorDetails`]); `None` when its message is
    /// all there is.
    #[must_use]
    pub fn details(&self) -> Option<ErrorDetails> {
        let d = ErrorDetails::default();
        Some(match self {
            Self::UnknownScene(scene) => ErrorDetails {
                scene: Some(scene.clone()),
                ..d
            },
            Self::UnknownAvatar(avatar) => ErrorDetails {
                avatar: Some(avatar.clone()),
                ..d
            },
            Self::NotInScene { scene, avatar } => ErrorDetails {
                scene: Some(scene.clone()),
                avatar: Some(avatar.clone()),
                ..d
            },
            Self::UnknownJoint { owner, joint } => ErrorDetails {
                joint: Some(joint.clone()),
                avatar: owner.avatar().cloned(),
                asset: owner.rig().map(str::to_owned),
                ..d
            },
            Self::UnknownExpression { owner, name, .. } => ErrorDetails {
                expression: Some(name.clone()),
                avatar: owner.avatar().cloned(),
                asset: owner.rig().map(str::to_owned),
                ..d
            },
            Self::UnknownClip { rig, clip } => ErrorDetails {
                asset: Some(rig.clone()),
                clip: Some(clip.clone()),
                ..d
            },
            Self::UnknownAsset { asset, .. } | Self::NoMesh(asset) => ErrorDetails {
                asset: Some(asset.clone()),
                ..d
            },
            Self::UnknownTake { take, .. } => ErrorDetails {
                take: Some(take.clone()),
                ..d
            },
            Self::Quota { quota, limit, .. } => ErrorDetails {
                quota: Some((*quota).to_owned()),
                limit: Some(limit.clone()),
                ..d
            },
            Self::Invalid {
                field: Some(field), ..
            } => ErrorDetails {
                field: Some((*field).to_owned()),
                ..d
            },
            Self::Remote(wire) => return wire.details.as_deref().cloned(),
            _ => return None,
        })
    }
}

impl From<Error> for ProtocolError {
    fn from(e: Error) -> Self {
        if let Error::Remote(wire) = e {
            return wire;
        }
        let mut wire = Self::new(e.code(), e.to_string());
        wire.details = e.details().map(Box::new);
        if let Error::RateLimited { retry_after_ms, .. } = e {
            wire.retry_after_ms = Some(retry_after_ms);
        }
        wire
    }
}

/// A result of this crate.
pub type Result<T, E = Error> = std::result::Result<T, E>;

#[cfg(test)]
mod tests {
    use super::*;

    /// The wire error names its subject in `details` where the error has one, and the
    /// take errors keep their messages.
    #[test]
    fn the_wire_error_names_its_subject() {
        let take = |unreadable: Option<&str>| Error::UnknownTake {
            take: "t1".into(),
            unreadable: unreadable.map(str::to_owned),
        };
        assert_eq!(take(None).to_string(), "no take t1");
        assert_eq!(
            take(Some("not a take")).to_string(),
            "take t1 cannot be read: not a take"
        );
        let wire = ProtocolError::from(take(None));
        assert_eq!(
            (wire.code, wire.details.and_then(|d| d.take)),
            (ErrorCode::UnknownTake, Some("t1".to_owned()))
        );
        let wire = ProtocolError::from(Error::NotInScene {
            scene: SceneId("s".into()),
            avatar: AvatarId("a".into()),
        });
        let d = wire.details.unwrap();
        assert_eq!(
            (d.scene, d.avatar),
            (Some(SceneId("s".into())), Some(AvatarId("a".into())))
        );
        let wire = ProtocolError::from(Error::Quota {
            quota: "scenes",
            detail: "scene s would be scene 3".into(),
            limit: "2".into(),
        });
        let d = wire.details.unwrap();
        assert_eq!(
            (d.quota.as_deref(), d.limit.as_deref()),
            (Some("scenes"), Some("2"))
        );
        // Whose joint or expression: the avatar, or the rig.
        let d = ProtocolError::from(Error::UnknownExpression {
            owner: Owner::Channels {
                avatar: AvatarId("a".into()),
                channels: 1,
                expressions: 0,
            },
            name: "channel 4".into(),
            has_targets: true,
        })
        .details
        .unwrap();
        assert_eq!(
            (d.avatar, d.asset, d.expression.as_deref()),
            (Some(AvatarId("a".into())), None, Some("channel 4"))
        );
        let d = ProtocolError::from(Error::UnknownJoint {
            owner: Owner::Rig("src".into()),
            joint: "tail".into(),
        })
        .details
        .unwrap();
        assert_eq!(
            (d.avatar, d.asset.as_deref(), d.joint.as_deref()),
            (None, Some("src"), Some("tail"))
        );
        // A rig a take's avatar was made of: the name, and the message says who needed it.
        let e = Error::UnknownAsset {
            asset: "robot".into(),
            needed_by: Some("avatar a of take t".into()),
        };
        assert_eq!(
            e.to_string(),
            "no rig (asset) named robot (avatar a of take t was made of it)"
        );
        assert_eq!(
            ProtocolError::from(e).details.unwrap().asset.as_deref(),
            Some("robot")
        );
        // An invalid value names its field when it has one.
        let wire = ProtocolError::from(Error::invalid_field("speed", "speed must be finite"));
        assert_eq!(
            (
                wire.code,
                wire.message.as_str(),
                wire.details.unwrap().field
            ),
            (
                ErrorCode::InvalidValue,
                "speed must be finite",
                Some("speed".to_owned())
            )
        );
        assert_eq!(ProtocolError::from(Error::invalid("x")).details, None);
        // A forwarded error keeps what its server said.
        let remote = ProtocolError::from(Error::unknown_asset("r"));
        assert_eq!(ProtocolError::from(Error::Remote(remote.clone())), remote);
        assert_eq!(remote.details.unwrap().asset.as_deref(), Some("r"));
    }

    /// Every variant keeps the code and message clients had before the enum existed.
    #[test]
    fn the_wire_error_has_the_code_and_message() {
        let cases = [
            (
                Error::UnknownAvatar(AvatarId("a".into())),
                ErrorCode::UnknownAvatar,
                "no avatar a",
            ),
            (
                Error::UnknownJoint {
                    owner: Owner::Avatar(AvatarId("a".into())),
                    joint: "knee".into(),
                },
                ErrorCode::UnknownJoint,
                "avatar a has no joint knee",
            ),
            (
                Error::UnknownJoint {
                    owner: Owner::RigOfJoints {
                        rig: "r".into(),
                        joints: 23,
                    },
                    joint: "index 40".into(),
                },
                ErrorCode::UnknownJoint,
                "rig r (of 23 joints) has no joint index 40",
            ),
            (
                Error::UnknownJoint {
                    owner: Owner::Trackers {
                        avatar: AvatarId("a".into()),
                        trackers: vec!["head".into(), "left_hand".into()],
                    },
                    joint: "for tracker hip".into(),
                },
                ErrorCode::UnknownJoint,
                "the tracker drive of avatar a (trackers head, left_hand) has no joint for tracker hip",
            ),
            (
                Error::UnknownExpression {
                    owner: Owner::Channels {
                        avatar: AvatarId("a".into()),
                        channels: 3,
                        expressions: 2,
                    },
                    name: "channel 9".into(),
                    has_targets: true,
                },
                ErrorCode::UnknownExpression,
                "avatar a (of 3 morph channels and 2 expressions) has no morph target or expression channel 9",
            ),
            (
                Error::UnknownExpression {
                    owner: Owner::Avatar(AvatarId("a".into())),
                    name: "smile".into(),
                    has_targets: false,
                },
                ErrorCode::UnknownExpression,
                "avatar a has no morph target or expression smile (it has no morph targets)",
            ),
            (
                Error::Quota {
                    quota: "scenes",
                    detail: "scene s would be scene 3".into(),
                    limit: "2".into(),
                },
                ErrorCode::QuotaExceeded,
                "quota scenes: scene s would be scene 3 (the limit is 2)",
            ),
        ];
        for (e, code, message) in cases {
            let wire = ProtocolError::from(e);
            assert_eq!((wire.code, wire.message.as_str()), (code, message));
            assert_eq!(wire.retry_after_ms, None);
        }
        let wire = ProtocolError::from(crate::quota::rate_limited(
            std::time::Duration::from_millis(250),
        ));
        assert_eq!(wire.code, ErrorCode::RateLimited);
        assert_eq!(wire.retry_after_ms, Some(250));
        assert_eq!(wire.message, "too many commands: try again in 250 ms");
    }
}
