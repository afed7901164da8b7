//! Poses a test looks at: [`StreamedPose`] (what a client decoded, with the joint names), the
//! expected pose of a clip ([`sample_clip`], the server's own sampling), and how far one is
//! from the other ([`PoseDiff`], the worst joint's rotation angle in degrees).

use crate::KitError;
use glam::Quat;
use posecast_client::net::PoseSample;
use posecast_proto::msg::AvatarId;
use posecast_proto::quant::angle_between_degrees;
use posecast_proto::{Skeleton, Transform};
use posecast_server::rig::Rig;
use std::fmt::Write as _;
use std::sync::Arc;

/// One avatar's pose as a client decoded it, with the skeleton (joint names) it belongs to.
#[derive(Debug, Clone)]
pub struct StreamedPose {
    /// The avatar.
    pub avatar: AvatarId,
    /// The decoded pose: tick, times, local transforms (avatar frame), placement.
    pub sample: PoseSample,
    /// The avatar's skeleton, rebuilt from its description.
    pub skeleton: Arc<Skeleton>,
}

impl StreamedPose {
    /// The scene's tick this pose is from.
    ///
    /// ```
    /// # let pose = posecast_testkit::pose::example_pose();
    /// assert_eq!(pose.seq(), 7);
    /// ```
    #[must_use]
    pub fn seq(&self) -> u64 {
        self.sample.seq
    }

    /// Every joint's local transform, in skeleton order.
    ///
    /// ```
    /// # let pose = posecast_testkit::pose::example_pose();
    /// assert_eq!(pose.locals().len(), pose.skeleton.len());
    /// ```
    #[must_use]
    pub fn locals(&self) -> &[Transform] {
        &self.sample.locals
    }

    /// The local transform of the joint called `name`.
    ///
    /// ```
    /// # let pose = posecast_testkit::pose::example_pose();
    /// assert!(pose.joint("l_elbow").is_some());
    /// assert!(pose.joint("no_such_joint").is_none());
    /// ```
    #[must_use]
    pub fn joint(&self, name: &str) -> Option<&Transform> {
        self.skeleton
            .find(name)
            .and_then(|j| self.sample.locals.get(j))
    }

    /// The local rotation of the joint called `name`.
    ///
    /// ```
    /// # let pose = posecast_testkit::pose::example_pose();
    /// let q = pose.rotation("l_elbow").unwrap();
    /// assert!((q.length() - 1.0).abs() < 1e-5);
    /// ```
    #[must_use]
    pub fn rotation(&self, name: &str) -> Option<Quat> {
        self.joint(name).map(|t| t.rotation)
    }

    /// The joint whose rotation is furthest from `expected`'s (same skeleton order), and by
    /// how many degrees (`q` and `−q` are the same rotation).
    ///
    /// # Errors
    /// [`KitError::JointCount`] when `expected` has another number of joints.
    ///
    /// ```
    /// # let pose = posecast_testkit::pose::example_pose();
    /// let mut expected = pose.locals().to_vec();
    /// let elbow = pose.skeleton.find("l_elbow").unwrap();
    /// expected[elbow].rotation = expected[elbow].rotation * glam::Quat::from_rotation_x(0.1);
    /// let diff = pose.compare(&expected).unwrap();
    /// assert_eq!(diff.joint_name, "l_elbow");
    /// assert!((diff.degrees - 0.1f64.to_degrees()).abs() < 1e-3);
    /// ```
    pub fn compare(&self, expected: &[Transform]) -> Result<PoseDiff, KitError> {
        if expected.len() != self.sample.locals.len() {
            return Err(KitError::JointCount {
                avatar: self.avatar.to_string(),
                streamed: self.sample.locals.len(),
                expected: expected.len(),
            });
        }
        let (joint, degrees) = self
            .sample
            .locals
            .iter()
            .zip(expected)
            .map(|(a, b)| angle_between_degrees(a.rotation, b.rotation))
            .enumerate()
            .fold(
                (0, 0.0f64),
                |best, (j, d)| {
                    if d > best.1 { (j, d) } else { best }
                },
            );
        Ok(PoseDiff {
            joint,
            joint_name: self
                .skeleton
                .names()
                .get(joint)
                .cloned()
                .unwrap_or_default(),
            degrees,
        })
    }

    /// [`StreamedPose::compare`], failing when the worst joint is more than
    /// `tolerance_degrees` off. The error names the avatar, the tick, the joint and its angle.
    /// [`posecast_proto::quant::MAX_ERROR_DEGREES`] is the binary encoding's bound (JSON is
    /// closer still).
    ///
    /// # Errors
    /// [`KitError::PoseMismatch`], or [`KitError::JointCount`].
    ///
    /// ```
    /// # let pose = posecast_testkit::pose::example_pose();
    /// let mut expected = pose.locals().to_vec();
    /// assert!(pose.assert_near(&expected, 0.01).is_ok());
    /// let knee = pose.skeleton.find("r_knee").unwrap();
    /// expected[knee].rotation = glam::Quat::from_rotation_x(1.0) * expected[knee].rotation;
    /// let err = pose.assert_near(&expected, 0.01).unwrap_err();
    /// assert!(err.to_string().contains("joint `r_knee` is 57.29"), "{err}");
    /// ```
    pub fn assert_near(
        &self,
        expected: &[Transform],
        tolerance_degrees: f64,
    ) -> Result<PoseDiff, KitError> {
        let diff = self.compare(expected)?;
        // `!(a <= b)` so a NaN angle fails too.
        if diff.degrees.is_nan() || diff.degrees > tolerance_degrees {
            return Err(KitError::PoseMismatch {
                avatar: self.avatar.to_string(),
                seq: self.sample.seq,
                joint: diff.joint_name,
                degrees: diff.degrees,
                tolerance: tolerance_degrees,
            });
        }
        Ok(diff)
    }

    /// The pose written out for people: the tick, then every joint's name and local rotation
    /// `[x, y, z, w]` (what timeouts report as the last pose seen).
    ///
    /// ```
    /// # let pose = posecast_testkit::pose::example_pose();
    /// let text = pose.describe();
    /// assert!(text.starts_with("tick 7:"), "{text}");
    /// assert!(text.contains("l_elbow ["), "{text}");
    /// ```
    #[must_use]
    pub fn describe(&self) -> String {
        let mut out = format!("tick {}:", self.sample.seq);
        for (name, t) in self.skeleton.names().iter().zip(&self.sample.locals) {
            let [x, y, z, w] = t.rotation.to_array();
            // Writing to a String cannot fail.
            write!(out, " {name} [{x:.3}, {y:.3}, {z:.3}, {w:.3}]").ok();
        }
        out
    }
}

/// How far a streamed pose is from an expected one: the worst joint.
#[derive(Debug, Clone, PartialEq)]
pub struct PoseDiff {
    /// The worst joint's index.
    pub joint: usize,
    /// Its name.
    pub joint_name: String,
    /// The angle between its streamed and expected local rotations, degrees.
    pub degrees: f64,
}

/// The local pose `rig`'s clip `clip` gives at `time` seconds from the clip's start, exactly as
/// an avatar playing it evaluates it: the clip's own sampling (`Clip::sample`, the rig's rest
/// where the clip has no channel), then every joint with DOF limits clamped to them. Not
/// wrapped: for a looping clip past its end, pass `time % duration`. Root translation is as
/// authored (a looping clip played in place holds its roots; compare rotations).
///
/// # Errors
/// [`KitError::UnknownClip`], naming the clips the rig has.
///
/// ```
/// let rig = posecast_server::builtin::rig().unwrap();
/// let pose = posecast_testkit::sample_clip(&rig, "walk", 0.25).unwrap();
/// assert_eq!(pose.len(), rig.skeleton().len());
/// let err = posecast_testkit::sample_clip(&rig, "fly", 0.0).unwrap_err();
/// assert!(err.to_string().contains("walk"), "{err}");
/// ```
pub fn sample_clip(rig: &Rig, clip: &str, time: f32) -> Result<Vec<Transform>, KitError> {
    let c = rig.clip(clip).ok_or_else(|| KitError::UnknownClip {
        asset: rig.name.clone(),
        clip: clip.to_owned(),
        available: rig
            .clips
            .iter()
            .map(|c| c.name().to_owned())
            .collect::<Vec<_>>()
            .join(", "),
    })?;
    let rest = rig.skeleton().rest();
    let mut out = rest.to_vec();
    c.sample(c.start() + time, rest, &mut out);
    for (local, limits) in out.iter_mut().zip(&rig.limits) {
        if let Some(limits) = limits {
            local.rotation = limits.clamp(local.rotation);
        }
    }
    Ok(out)
}

/// A pose of the built-in avatar at rest with its left elbow bent, for the examples in these
/// docs (tick 7).
///
/// # Panics
/// Never for the built-in avatar (it has `l_elbow` and loads).
#[doc(hidden)]
#[must_use]
#[allow(clippy::expect_used)]
pub fn example_pose() -> StreamedPose {
    let rig = posecast_server::builtin::rig().expect("the built-in avatar loads");
    let skeleton = rig.skeleton().clone();
    let mut locals = skeleton.rest().to_vec();
    let elbow = skeleton
        .find("l_elbow")
        .expect("the built-in avatar has l_elbow");
    locals[elbow].rotation = Quat::from_rotation_z(0.8);
    StreamedPose {
        avatar: AvatarId("avatar".into()),
        sample: PoseSample {
            seq: 7,
            server_time_us: 0,
            received_us: 0,
            locals,
            placement: Default::default(),
            weights: Vec::new(),
        },
        skeleton: Arc::new(skeleton),
    }
}
