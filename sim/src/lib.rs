//! posecast's simulation: one avatar's pose at a clock.
//!
//! - [`avatar`]: an avatar plays clip layers with cross-fades (a fade stack, so a `play`
//!   during any fade is continuous), follows a live driver's pose retargeted from the
//!   driver's rig, applies joint overrides, places itself and moves its root, and records a
//!   live drive into a clip.
//! - [`bake`]: clips retargeted from one rig onto another, baked off the tick (a blocking
//!   task, bounded) and cached by size.
//! - [`ik`]: inverse kinematics — limbs in closed form, any chain by FABRIK, a gaze — which an
//!   avatar's goals ([`avatar::goals`]) run every evaluation.
//!
//! It knows nothing of sockets or scenes: the server's scenes tick avatars under their lock
//! and publish the poses. It uses `posecast-rigs`, `posecast-core` and `posecast-proto`.
//!
//! # Example
//!
//! The built-in avatar waving, with a joint override on top of the clip:
//!
//! ```rust
//! use glam::Quat;
//! use posecast_proto::msg::AvatarId;
//! use posecast_sim::avatar::Avatar;
//! use posecast_sim::avatar::playback::Layer;
//! use std::sync::Arc;
//!
//! let rig = Arc::new(posecast_rigs::builtin::rig()?);
//! let mut avatar = Avatar::new(AvatarId("ada".into()), 1, rig.clone());
//! // A new avatar holds its rig's rest pose.
//! assert_eq!(avatar.locals, rig.skeleton().rest());
//!
//! // Play `wave` from its start, at normal speed, looping, without a fade; tick at 0.5 s.
//! let wave = rig.clip("wave").ok_or("no wave clip")?.clone();
//! avatar.play(Layer::new(wave, None, 0.0, 1.0, true), 0.0);
//! avatar.tick(0.5);
//! assert_eq!(avatar.pose().rotations.len(), rig.skeleton().len());
//! let mut joints = avatar.locals.iter().zip(rig.skeleton().rest());
//! assert!(joints.any(|(now, rest)| now.rotation.angle_between(rest.rotation) > 0.01));
//!
//! // An override replaces the clip's local rotation of that joint, tick after tick.
//! let elbow = rig.skeleton().find("l_elbow").ok_or("no l_elbow")?;
//! let set = avatar.set_rotation(elbow, Quat::from_rotation_y(0.5))?;
//! avatar.tick(1.0);
//! assert!(avatar.locals[elbow].rotation.angle_between(set) < 1e-6);
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

#![warn(missing_docs)]
pub mod avatar;
pub mod bake;
pub mod ik;
