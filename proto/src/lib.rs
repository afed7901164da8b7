//! `posecast-proto`: what the posecast server and its clients agree on.
//!
//! - [`transform`]: translation · rotation · scale, and polar decomposition of affine matrices.
//! - [`skeleton`]: a validated joint tree with rest transforms and inverse bind matrices.
//! - [`fk`]: forward kinematics `W_j = W_parent(j) · D_j` and skinning matrices `M_j = W_j · B_j⁻¹`.
//! - [`expressions`]: the standard expression names (ARKit, VRM presets, visemes) and finding them on a rig.
//! - [`morph`]: morph targets (blend shapes) and the CPU morphing reference.
//! - [`skinning`]: the CPU linear-blend-skinning reference every GPU path is tested against.
//! - [`bind`]: seed 001's world-space increment of a joint, `D'_j = W_parent(j)⁻¹ · U · W_j`.
//! - [`dof`]: joint types, degrees of freedom and their limits (seed 002).
//! - [`quant`]: smallest-three quaternion quantisation for the wire.
//! - [`msg`]: the websocket protocol's messages (versioned hello, subscribe, errors, …).
//! - [`description`]: an avatar's rig as sent to clients, with its hash.
//! - [`frame`]: binary pose frames (keyframes and deltas).
//! - [`frame2`]: wire v2 frames (deltas against the previous frame, Rice-coded residuals).
//! - [`command`]: control commands shared by REST and websocket.
//! - [`placement`]: an avatar's world placement (position, rotation).
//! - [`live`]: the pose messages of a live driver (binary encoding).
//! - [`subset`]: joint subsets a subscription may ask for (by depth or by name).
//! - [`precision`]: how finely a subscription's frames code each joint (angle, world-space or translation bounds).
//! - [`rig_options`]: how the server normalises an imported rig (per-asset pipeline options).
//!
//! Conventions: column vectors, right-handed, Y up, metres, seconds (see DESIGN.md).
//!
//! # Example
//!
//! A two-joint arm posed by forward kinematics, and its shoulder's rotation sent through the
//! wire's 48-bit quantisation:
//!
//! ```rust
//! use glam::{Mat4, Quat, Vec3};
//! use posecast_proto::fk::forward_kinematics;
//! use posecast_proto::{Skeleton, Transform, quant};
//!
//! // A shoulder at the origin and an elbow 0.3 m along its x axis (bind = rest).
//! let elbow = Vec3::new(0.3, 0.0, 0.0);
//! let skeleton = Skeleton::new(
//!     vec!["shoulder".into(), "elbow".into()],
//!     vec![None, Some(0)],
//!     vec![Transform::IDENTITY, Transform::from_translation(elbow)],
//!     vec![Mat4::IDENTITY, Mat4::from_translation(-elbow)],
//! )?;
//!
//! // Raise the arm: the shoulder turns 90° about +Z, so W_elbow = W_shoulder · D_elbow puts the
//! // elbow 0.3 m up.
//! let turn = Quat::from_rotation_z(std::f32::consts::FRAC_PI_2);
//! let locals = [Transform::from_translation_rotation(Vec3::ZERO, turn), skeleton.rest()[1]];
//! let mut world = [Mat4::IDENTITY; 2];
//! forward_kinematics(&skeleton, &locals, &mut world);
//! assert!(world[1].w_axis.truncate().abs_diff_eq(Vec3::new(0.0, 0.3, 0.0), 1e-6));
//!
//! // On the wire the rotation takes 6 bytes and comes back within MAX_ERROR_DEGREES.
//! let mut bytes = Vec::new();
//! quant::write(turn, &mut bytes);
//! assert_eq!(bytes.len(), quant::BYTES);
//! let decoded = quant::read(bytes[..].try_into()?);
//! assert!(quant::angle_between_degrees(turn, decoded) <= quant::MAX_ERROR_DEGREES);
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

#![warn(missing_docs)]
pub mod bind;
pub mod command;
pub mod description;
pub mod dof;
pub mod expressions;
pub mod fk;
pub mod frame;
pub mod frame2;
pub mod ids;
pub mod live;
pub mod morph;
pub mod msg;
pub mod placement;
pub mod precision;
pub mod quant;
pub mod quic;
pub mod rig_options;
pub mod skeleton;
pub mod skinning;
pub mod subset;
#[cfg(any(test, feature = "testing"))]
#[allow(clippy::expect_used)]
pub mod testing;
pub mod tokens;
pub mod trackers;
pub mod transform;
#[cfg(feature = "ts")]
pub mod ts;

pub use dof::{Dof, JointDofs, JointType};
pub use placement::Placement;
pub use skeleton::{Skeleton, SkeletonError};
pub use skinning::{MeshError, SkinnedMesh};
pub use transform::{DecomposeError, Transform, unit_quat};
