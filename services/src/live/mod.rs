//! Live avatars (issue 16): a websocket connection drives an avatar with a stream of poses.
//!
//! - `posecast_sim::avatar::live`: the per-avatar driver state (`LivePose`) the avatar
//!   evaluates between its clip and its joint overrides.
//! - `posecast_sim::avatar::recording`: a `Recorder` turns the poses an avatar streams, tick by
//!   tick, into a clip on its rig.
//! - this module: the connection's side — `drive` / `release_drive`, validating pose messages
//!   (JSON and binary), and releasing what it drives when it leaves.
//! - `remote`: an avatar of a scene another server of the cluster ticks, driven through that
//!   server: poses checked here (morph weights' names and trackers' names resolved here too)
//!   and passed on.
//!
//! A pose passes, in order: the sender drives the avatar (`not_allowed_now`), the driver's rate
//! budget ([`posecast_proto::live::MAX_RATE_HZ`], `rate_limited`), the pose's kind matches the
//! drive's — rotations (and a root position) for a drive by rotations, trackers for a tracker
//! drive (`drive … trackers`; `invalid_value`) — every joint or tracker known
//! (`unknown_joint`), every rotation a finite non-zero quaternion and the root and tracker
//! positions finite and within [`MAX_ROOT_METRES`] (`invalid_value`). A pose failing any check
//! changes nothing.

use crate::changes;
use crate::scene::Scene;
use posecast_core::error::{Error, Owner};

use crate::state::Services;
use glam::{Quat, Vec3};
use posecast_core::quota::{CommandRate, TokenBucket};
use posecast_proto::command::{Command, CommandResult, DriveInfo, DriveVia, Driver, OnRelease};
use posecast_proto::live::{BinaryPose, MAX_RATE_HZ, VMC_SOURCE};
use posecast_proto::msg::{AvatarId, SceneId};
use posecast_proto::trackers::{Legs, LocomotionClip, TrackerTransform};
use posecast_sim::avatar::Avatar;
use posecast_sim::avatar::live::{LivePose, ValidPose};
use posecast_sim::avatar::trackers::{TrackerSample, Trackers};
use remote::RemoteDrive;
use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::Instant;

mod remote;

pub use posecast_proto::live::MAX_ROOT_METRES;

/// The avatars one connection drives.
#[derive(Debug)]
pub struct Drives {
    conn: u64,
    driven: Vec<(AvatarId, u32, Arc<Scene>)>,
    /// Avatars of scenes ticked on other servers of a cluster, driven there for this
    /// connection: poses are checked here and passed on.
    remote: Vec<RemoteDrive>,
    /// Who drives through this connection.
    who: Driver,
}

fn pose_rate() -> TokenBucket {
    TokenBucket::new(CommandRate {
        per_second: f64::from(MAX_RATE_HZ),
        burst: posecast_sim::avatar::live::RATE_BURST,
    })
}

fn rate_limited(wait: std::time::Duration) -> Error {
    let ms = u64::try_from(wait.as_millis().max(1)).unwrap_or(u64::MAX);
    Error::RateLimited {
        message: format!(
            "poses are limited to {MAX_RATE_HZ} per second per driver: try again in {ms} ms"
        ),
        retry_after_ms: ms,
    }
}

fn not_driving(avatar: impl std::fmt::Display) -> Error {
    Error::NotAllowedNow(format!(
        "this connection does not drive avatar {avatar}; send drive first"
    ))
}

impl Drives {
    /// Nothing driven yet by connection `conn`.
    #[must_use]
    pub fn new(conn: u64) -> Self {
        Self {
            conn,
            driven: Vec::new(),
            remote: Vec::new(),
            who: Driver {
                name: "anonymous".into(),
                via: DriveVia::Websocket,
            },
        }
    }

    /// Says who drives through this connection (presence: `AvatarState::driver`).
    pub fn identify(&mut self, who: Driver) {
        self.who = who;
    }

    /// Whether it drives an avatar of this server still.
    #[must_use]
    pub fn is_driving(&self) -> bool {
        self.driven.iter().any(|(avatar, _, scene)| {
            scene
                .lock()
                .avatar_mut(avatar)
                .and_then(|a| a.live.as_ref())
                .is_some_and(|l| l.driver == Some(self.conn))
        })
    }

    /// `drive` of an avatar whose scene another server of the cluster ticks: sent to that
    /// server, which drives the avatar for this connection; from then on this connection's
    /// poses for it are checked here (driver, rate, joints, values) and passed on. `None` when
    /// the command is not a `drive` of such an avatar. Authorisation is the caller's.
    pub async fn command_remote(
        &mut self,
        state: &Services,
        command: &Command,
    ) -> Option<Result<CommandResult, Error>> {
        let Command::Drive { avatar, .. } = command else {
            return None;
        };
        let cluster = state.cluster()?;
        let scene = state
            .world
            .find_avatar(avatar)
            .ok()
            .filter(|s| s.is_relay())?;
        let result = cluster.drive(&scene.id, self.conn, command).await;
        state.metrics.command(result.is_ok());
        if let Ok(CommandResult::Drive(info)) = &result {
            self.driven.retain(|(id, _, _)| id != avatar);
            self.remote.retain(|r| &r.avatar != avatar);
            self.remote.push(RemoteDrive::new(info, &scene));
        }
        Some(result)
    }

    /// Runs `drive` (this connection becomes the driver) — the one command that needs the
    /// connection — counted and announced like the others ([`crate::control::execute`]), and
    /// returns `None` for every other command. Authorisation is the caller's.
    pub fn command(
        &mut self,
        state: &Services,
        command: &Command,
    ) -> Option<Result<CommandResult, Error>> {
        let Command::Drive {
            avatar,
            source,
            on_release,
            joints,
            trackers,
            legs,
            locomotion,
        } = command
        else {
            return None;
        };
        let before = changes::before(state, command);
        let result = if legs.is_some() && trackers.is_none() {
            Err(Error::invalid(
                "legs is for a tracker drive: name its trackers too",
            ))
        } else if locomotion.is_some() != (*legs == Some(Legs::Locomotion)) {
            Err(Error::invalid(
                "locomotion (the clips the legs play) goes with legs \"locomotion\", and that needs it",
            ))
        } else {
            self.drive(
                state,
                avatar,
                source.as_deref(),
                on_release.unwrap_or_default(),
                joints.as_ref(),
                trackers.as_deref().map(|names| {
                    (
                        names,
                        legs.unwrap_or_default(),
                        locomotion.as_deref().unwrap_or_default(),
                    )
                }),
            )
        }
        .map(|info| CommandResult::Drive(Box::new(info)));
        state.metrics.command(result.is_ok());
        if let Ok(r) = &result {
            changes::after(state, command, before, r);
        }
        Some(result)
    }

    fn drive(
        &mut self,
        state: &Services,
        avatar: &AvatarId,
        source: Option<&str>,
        on_release: OnRelease,
        joints: Option<&posecast_proto::command::JointMask>,
        trackers: Option<(&[String], Legs, &[LocomotionClip])>,
    ) -> Result<DriveInfo, Error> {
        if trackers.is_some() && source.is_some() {
            return Err(Error::invalid(
                "a tracker drive solves the avatar's own rig: give trackers or source, not both",
            ));
        }
        let vmc = match source {
            Some(VMC_SOURCE) => Some(
                crate::vmc::performer_rig()
                    .map_err(|e| Error::Internal(format!("the VMC performer rig: {e}")))?,
            ),
            _ => None,
        };
        let source_rig = source
            .filter(|_| vmc.is_none())
            .map(|name| state.world.library.require(name))
            .transpose()?;
        let scene = state.world.find_avatar(avatar)?;
        let mut s = scene.lock();
        let a = s
            .avatar_mut(avatar)
            .ok_or_else(|| Error::UnknownAvatar(avatar.clone()))?;
        // The VMC performer rig fitted to this avatar's torso, as a `--vmc-in` input drives.
        let source_rig = source_rig.or_else(|| vmc.map(|v| v.for_target(&a.rig)));
        if let Some(driver) = a.live.as_ref().and_then(|l| l.driver)
            && driver != self.conn
        {
            return Err(Error::Conflict(format!(
                "avatar {avatar} already has a live driver"
            )));
        }
        let source = source_rig.unwrap_or_else(|| a.rig.clone());
        let owned = joints
            .map(|mask| posecast_sim::avatar::layers::owned_joints(&a.rig, Some(mask)))
            .transpose()
            .map_err(|e| Error::invalid(format!("joints: {e}")))?;
        let mut live = LivePose::new(
            self.conn,
            on_release,
            source.clone(),
            &a.rig,
            &a.locals,
            state.config.drive_timeout,
        )
        .map_err(|e| {
            e.to_error(&format!(
                "cannot retarget {} onto {}",
                source.name, a.rig.name
            ))
        })?;
        live.owned = owned;
        live.trackers = trackers
            .map(|(names, legs, clips)| {
                let mut t = Trackers::new(&a.rig, names, legs)?;
                if legs == Legs::Locomotion {
                    t.set_locomotion(&a.rig, clips)?;
                }
                Ok::<_, posecast_sim::avatar::trackers::TrackerError>(t)
            })
            .transpose()
            .map_err(|e| {
                Error::invalid(format!("cannot drive avatar {avatar} by trackers: {e}"))
            })?;
        let tracker_names = live
            .trackers
            .as_ref()
            .map(|t| t.names().to_vec())
            .unwrap_or_default();
        a.live = Some(live);
        if let Some(l) = a.live.as_mut() {
            l.by = Some(self.who.clone());
        }
        a.evaluate();
        let num = a.num();
        let morph_targets = a.description.morph_targets.clone();
        let expressions = a.description.expressions.clone();
        drop(s);
        self.driven.retain(|(id, _, _)| id != avatar);
        self.driven.push((avatar.clone(), num, scene.clone()));
        let skeleton = source.skeleton();
        Ok(DriveInfo {
            avatar: avatar.clone(),
            avatar_num: num,
            source: source.name.clone(),
            joints: skeleton.names().to_vec(),
            root: skeleton
                .roots()
                .next()
                .map(|r| skeleton.names()[r].clone())
                .unwrap_or_default(),
            timeout: state.config.drive_timeout.as_secs_f32(),
            max_rate_hz: MAX_RATE_HZ,
            morph_targets,
            expressions,
            trackers: tracker_names,
        })
    }

    /// A JSON pose message.
    ///
    /// # Errors
    /// See the module documentation; nothing changes on error.
    pub fn json_pose(
        &mut self,
        state: &Services,
        avatar: &AvatarId,
        pose: &JsonPose<'_>,
    ) -> Result<(), Error> {
        if let Some(r) = self.remote.iter_mut().find(|r| &r.avatar == avatar) {
            return r.json_pose(state, self.conn, pose);
        }
        let JsonPose {
            rotations,
            root_position,
            time_us,
            weights,
            trackers,
        } = *pose;
        let (_, _, scene) = self
            .driven
            .iter()
            .find(|(id, _, _)| id == avatar)
            .ok_or_else(|| not_driving(avatar))?;
        let named = |a: &Avatar| {
            crate::world::command::face::resolve_weights(
                a,
                weights.iter().map(|(n, w)| (n.as_str(), *w)),
            )
        };
        self.with_live(scene, avatar, named, |live| {
            if let Some(names) = live.trackers.as_ref().map(Trackers::names) {
                if !rotations.is_empty() || root_position.is_some() {
                    return Err(rotations_to_trackers(avatar));
                }
                let mut samples = Vec::with_capacity(trackers.len());
                for (name, t) in trackers {
                    let i = names
                        .iter()
                        .position(|n| n == name)
                        .ok_or_else(|| unknown_tracker(avatar, names, name))?;
                    samples.push((i, tracker_sample(name, t.position, t.rotation)?));
                }
                return Ok(Valid::Trackers { samples, time_us });
            }
            if !trackers.is_empty() {
                return Err(trackers_to_rotations(avatar));
            }
            let skeleton = live.source.skeleton();
            let mut pose = ValidPose {
                rotations: Vec::with_capacity(rotations.len()),
                root_position: root(root_position.map(Vec3::from_array))?,
                time_us,
            };
            for (name, q) in rotations {
                let j = skeleton.find(name).ok_or_else(|| Error::UnknownJoint {
                    owner: Owner::Rig(live.source.name.clone()),
                    joint: name.clone(),
                })?;
                pose.rotations.push((j, rotation(name, *q)?));
            }
            Ok(Valid::Rotations(pose))
        })
    }

    /// A binary pose message ([`BinaryPose`]).
    ///
    /// # Errors
    /// `unexpected_binary` when the bytes are not a pose; otherwise as [`Drives::json_pose`].
    pub fn binary_pose(&mut self, state: &Services, bytes: &[u8]) -> Result<(), Error> {
        let msg = BinaryPose::decode(bytes).map_err(|e| Error::UnexpectedBinary(e.to_string()))?;
        if let Some(r) = self.remote.iter_mut().find(|r| r.num == msg.avatar_num) {
            return r.binary_pose(state, self.conn, msg);
        }
        self.apply_binary(&msg, false)
    }

    /// A pose another server of the cluster relays for the connection this driver stands for
    /// (`cluster::drive`), checked again here as a [`Drives::binary_pose`] (the avatar or its
    /// driver may have changed since the relaying server checked it), except that its weights
    /// may also set the expressions the avatar's file defines: slots past the channels, as
    /// `Avatar::morph_channel` numbers them, to which the relaying server resolved a JSON
    /// pose's names (`live::remote`).
    ///
    /// # Errors
    /// As [`Drives::binary_pose`].
    pub fn relayed_pose(&self, bytes: &[u8]) -> Result<(), Error> {
        let msg = BinaryPose::decode(bytes).map_err(|e| Error::UnexpectedBinary(e.to_string()))?;
        self.apply_binary(&msg, true)
    }

    /// Applies a binary pose to an avatar this connection drives here; `expressions`: its
    /// weights may set file-defined expressions' slots too.
    fn apply_binary(&self, msg: &BinaryPose, expressions: bool) -> Result<(), Error> {
        let (avatar, _, scene) = self
            .driven
            .iter()
            .find(|(_, num, _)| *num == msg.avatar_num)
            .ok_or_else(|| not_driving(format!("number {}", msg.avatar_num)))?;
        let by_slot = |a: &Avatar| {
            let channels = a.description.morph_targets.len();
            let defined = if expressions {
                a.description.expression_binds.len()
            } else {
                0
            };
            msg.weights
                .iter()
                .map(|&(c, level)| {
                    if usize::from(c) < channels + defined {
                        Ok((usize::from(c), posecast_proto::morph::weight_value(level)))
                    } else {
                        Err(Error::UnknownExpression {
                            owner: Owner::Channels {
                                avatar: a.id.clone(),
                                channels,
                                expressions: defined,
                            },
                            name: format!("channel {c}"),
                            has_targets: channels > 0,
                        })
                    }
                })
                .collect::<Result<Vec<_>, Error>>()
        };
        self.with_live(scene, avatar, by_slot, |live| {
            if let Some(names) = live.trackers.as_ref().map(Trackers::names) {
                if !msg.rotations.is_empty() || msg.root_position.is_some() {
                    return Err(rotations_to_trackers(avatar));
                }
                let mut samples = Vec::with_capacity(msg.trackers.len());
                for &(i, p, q) in &msg.trackers {
                    let label = format!("index {i}");
                    let i = usize::from(i);
                    if i >= names.len() {
                        return Err(unknown_tracker(avatar, names, &label));
                    }
                    samples.push((i, tracker_sample(&names[i], p.to_array(), q.to_array())?));
                }
                return Ok(Valid::Trackers {
                    samples,
                    time_us: msg.time_us,
                });
            }
            if !msg.trackers.is_empty() {
                return Err(trackers_to_rotations(avatar));
            }
            let n = live.source.skeleton().len();
            let mut pose = ValidPose {
                rotations: Vec::with_capacity(msg.rotations.len()),
                root_position: root(msg.root_position)?,
                time_us: msg.time_us,
            };
            for &(j, q) in &msg.rotations {
                let j = usize::from(j);
                if j >= n {
                    return Err(Error::UnknownJoint {
                        owner: Owner::RigOfJoints {
                            rig: live.source.name.clone(),
                            joints: n,
                        },
                        joint: format!("index {j}"),
                    });
                }
                pose.rotations.push((j, q));
            }
            Ok(Valid::Rotations(pose))
        })
    }

    /// Checks the driver and its rate, validates with `validate`, stores the pose.
    fn with_live(
        &self,
        scene: &Scene,
        avatar: &AvatarId,
        weights: impl FnOnce(&Avatar) -> Result<Vec<(usize, f32)>, Error>,
        validate: impl FnOnce(&LivePose) -> Result<Valid, Error>,
    ) -> Result<(), Error> {
        let now = Instant::now();
        let mut s = scene.lock();
        let a = s
            .avatar_mut(avatar)
            .filter(|a| a.live.as_ref().is_some_and(|l| l.driver == Some(self.conn)))
            .ok_or_else(|| not_driving(avatar))?;
        let Some(live) = a.live.as_mut() else {
            return Err(not_driving(avatar));
        };
        live.take_rate(now).map_err(rate_limited)?;
        let pose = validate(live)?;
        // Weights resolved and checked before anything is stored: a bad one changes nothing.
        let morph = weights(a)?;
        // A pose older than the last applied is dropped, and its weights with it; a stored
        // one's weights apply with it at the next tick's evaluation.
        let stored = a.live.as_mut().is_some_and(|live| match pose {
            Valid::Rotations(pose) => live.store(pose, now),
            Valid::Trackers { samples, time_us } => live.store_trackers(&samples, time_us, now),
        });
        if stored {
            a.store_morph(&morph);
        }
        Ok(())
    }

    /// The connection left: each avatar it still drives returns to its clip or holds its last
    /// pose, as its `drive` asked.
    pub fn leave(&mut self, state: &Services) {
        if let Some(cluster) = state.cluster() {
            let mut scenes: Vec<&SceneId> = self.remote.iter().map(|r| &r.scene).collect();
            scenes.dedup();
            for scene in scenes {
                cluster.release(scene, self.conn);
            }
        }
        self.remote.clear();
        for (avatar, _, scene) in self.driven.drain(..) {
            let mut s = scene.lock();
            if let Some(a) = s.avatar_mut(&avatar)
                && a.live.as_ref().is_some_and(|l| l.driver == Some(self.conn))
            {
                a.driver_gone();
                drop(s);
                changes::avatar_changed(state, &scene, &avatar);
            }
        }
    }
}

/// A pose checked against its drive, ready to store.
enum Valid {
    /// Local rotations of the source rig (a drive by rotations).
    Rotations(ValidPose),
    /// Tracker transforms (a tracker drive): `(tracker index, sample)`.
    Trackers {
        samples: Vec<(usize, TrackerSample)>,
        time_us: Option<u64>,
    },
}

/// The fields of a JSON `pose` message ([`posecast_proto::msg::ClientMsg::Pose`]).
#[derive(Clone, Copy, Debug)]
pub struct JsonPose<'a> {
    /// Local rotations of the source rig's joints by name.
    pub rotations: &'a BTreeMap<String, [f32; 4]>,
    /// The source root's local translation.
    pub root_position: Option<[f32; 3]>,
    /// The driver's clock, µs.
    pub time_us: Option<u64>,
    /// Morph weights by name.
    pub weights: &'a BTreeMap<String, f32>,
    /// Tracker transforms by tracker name (a tracker drive).
    pub trackers: &'a BTreeMap<String, TrackerTransform>,
}

/// A tracker's transform, checked: the position finite and within [`MAX_ROOT_METRES`], the
/// rotation a finite non-zero quaternion (normalised).
fn tracker_sample(name: &str, position: [f32; 3], q: [f32; 4]) -> Result<TrackerSample, Error> {
    let p = Vec3::from_array(position);
    if !(p.is_finite() && p.length() <= MAX_ROOT_METRES) {
        return Err(Error::invalid(format!(
            "tracker {name}: position {position:?} must be finite and within {MAX_ROOT_METRES} m"
        )));
    }
    let rotation = posecast_proto::unit_quat(q).ok_or_else(|| {
        Error::invalid(format!(
            "tracker {name}: rotation {q:?} is not a finite non-zero quaternion"
        ))
    })?;
    Ok(TrackerSample {
        position: p,
        rotation,
    })
}

/// A tracker (a name, or `index N`) the drive of `avatar` (trackers `names`) does not have.
fn unknown_tracker(avatar: &AvatarId, names: &[String], tracker: &str) -> Error {
    Error::UnknownJoint {
        owner: Owner::Trackers {
            avatar: avatar.clone(),
            trackers: names.to_vec(),
        },
        joint: format!("for tracker {tracker}"),
    }
}

/// Rotations or a root position sent to a tracker drive.
fn rotations_to_trackers(avatar: impl std::fmt::Display) -> Error {
    Error::invalid(format!(
        "avatar {avatar} is driven by trackers: its poses carry trackers, not rotations or \
         root_position (drive it again without trackers to send rotations)"
    ))
}

/// Trackers sent to a drive by rotations.
fn trackers_to_rotations(avatar: impl std::fmt::Display) -> Error {
    Error::invalid(format!(
        "avatar {avatar} is driven by rotations: its drive named no trackers (drive it with \
         trackers to send them)"
    ))
}

fn rotation(joint: &str, q: [f32; 4]) -> Result<Quat, Error> {
    posecast_proto::unit_quat(q).ok_or_else(|| {
        Error::invalid(format!(
            "joint {joint}: rotation {q:?} is not a finite non-zero quaternion"
        ))
    })
}

fn root(p: Option<Vec3>) -> Result<Option<Vec3>, Error> {
    match p {
        Some(p) if !(p.is_finite() && p.length() <= MAX_ROOT_METRES) => {
            Err(Error::invalid(format!(
                "root_position {:?} must be finite and within {MAX_ROOT_METRES} m",
                p.to_array()
            )))
        }
        _ => Ok(p),
    }
}
