//! Animation clips: one in-memory representation for every source format.
//!
//! A [`Clip`] holds, per skeleton joint, optional rotation, translation and scale channels.
//! A channel is either a key [`Track`] (glTF channels, BVH frames) or CSE169 Hermite
//! [`Curve`]s, one per DOF (`.anim`). Sampling returns local transforms `D_j = T(t)·R·S`;
//! components without a channel come from the caller's rest pose.
//!
//! Rig normalisation changes a clip without touching its keys: [`Clip::map_joint`] stores a
//! per-joint [`ChannelMap`] applied at sampling time, so it is exact for every channel kind.

mod curve;
mod sampler;
mod track;

pub use curve::{Curve, Extrapolation, Key, Tangent};
pub use sampler::Sampler;
pub use track::{Interpolation, Track, TrackValue, slerp_shortest};

use glam::{EulerRot, Quat, Vec3};
use posecast_proto::Transform;

/// Why a clip, track or curve was refused.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum ClipError {
    /// A track or curve was given no keys.
    #[error("a track or curve has no keys")]
    NoKeys,
    /// A track's value count does not match its key times.
    #[error("{times} key times but {values} values ({per_key} per key expected)")]
    KeyCount {
        /// How many key times it has.
        times: usize,
        /// How many values it has.
        values: usize,
        /// Values each key needs: 3 for cubic spline (in-tangent, value, out-tangent), else 1.
        per_key: usize,
    },
    /// Key times do not strictly increase.
    #[error("key {key} has a time that is not after the previous key's")]
    Unordered {
        /// Index of the first key whose time is not after its predecessor's.
        key: usize,
    },
    /// A key's time, value or tangent is NaN or infinite.
    #[error("key {key} has a non-finite time, value or tangent")]
    NotFinite {
        /// Index of the key.
        key: usize,
    },
    /// The clip's playback range has `start > end` or a bound that is not finite.
    #[error("clip range [{start}, {end}] is empty or not finite")]
    BadRange {
        /// The range's start, seconds.
        start: f32,
        /// The range's end, seconds.
        end: f32,
    },
}

/// A rotation channel.
#[derive(Clone, Debug, PartialEq)]
pub enum RotationChannel {
    /// Unit quaternion keys.
    Keys(Track<Quat>),
    /// CSE169 ball joint: Euler angles (radians) applied X, then Y, then Z:
    /// `R = R_z(z) · R_y(y) · R_x(x)`, as `posecast_proto::JointType::BallEuler`.
    Euler(Box<[Curve; 3]>),
}

impl RotationChannel {
    fn sample(&self, time: f32, cursors: &mut [usize; 3]) -> Quat {
        match self {
            Self::Keys(track) => track.sample_from(time, &mut cursors[0]),
            Self::Euler(c) => {
                let x = c[0].evaluate_from(time, &mut cursors[0]);
                let y = c[1].evaluate_from(time, &mut cursors[1]);
                let z = c[2].evaluate_from(time, &mut cursors[2]);
                Quat::from_euler(EulerRot::ZYX, z, y, x)
            }
        }
    }

    fn is_constant(&self) -> bool {
        match self {
            Self::Keys(t) => t.is_constant(),
            Self::Euler(c) => c.iter().all(Curve::is_constant),
        }
    }

    fn time_range(&self) -> (f32, f32) {
        match self {
            Self::Keys(t) => t.time_range(),
            Self::Euler(c) => curves_range(c),
        }
    }
}

/// A translation or scale channel.
#[derive(Clone, Debug, PartialEq)]
pub enum VectorChannel {
    /// Vector keys (glTF channels, BVH frames).
    Keys(Track<Vec3>),
    /// One CSE169 curve per axis (x, y, z).
    Curves(Box<[Curve; 3]>),
}

impl VectorChannel {
    fn sample(&self, time: f32, cursors: &mut [usize; 3]) -> Vec3 {
        match self {
            Self::Keys(track) => track.sample_from(time, &mut cursors[0]),
            Self::Curves(c) => Vec3::new(
                c[0].evaluate_from(time, &mut cursors[0]),
                c[1].evaluate_from(time, &mut cursors[1]),
                c[2].evaluate_from(time, &mut cursors[2]),
            ),
        }
    }

    fn is_constant(&self) -> bool {
        match self {
            Self::Keys(t) => t.is_constant(),
            Self::Curves(c) => c.iter().all(Curve::is_constant),
        }
    }

    fn time_range(&self) -> (f32, f32) {
        match self {
            Self::Keys(t) => t.time_range(),
            Self::Curves(c) => curves_range(c),
        }
    }
}

fn curves_range(c: &[Curve; 3]) -> (f32, f32) {
    c.iter()
        .fold((f32::INFINITY, f32::NEG_INFINITY), |(a, b), c| {
            let t = c.times();
            (a.min(t[0]), b.max(t[t.len() - 1]))
        })
}

/// An exact change of a joint's channels, applied at sampling time:
/// `rotation' = rot_pre · rotation(t) · rot_post`,
/// `translation' = trans_offset + trans_scale · (trans_rot · translation(t))`.
/// Scale channels are not changed.
///
/// Rig normalisation (DESIGN.md step 1) is `rot_pre = V_parent(i)`, `rot_post = V_i⁻¹`,
/// `trans_rot = V_parent(i)`; units are `trans_scale`; `trans_offset` folds a static parent
/// transform (e.g. glTF's `Z_UP` node) into a root joint.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ChannelMap {
    /// Rotation multiplied before the sampled rotation (`V_parent(i)` in normalisation).
    pub rot_pre: Quat,
    /// Rotation multiplied after the sampled rotation (`V_i⁻¹` in normalisation).
    pub rot_post: Quat,
    /// Rotation applied to the sampled translation (`V_parent(i)` in normalisation).
    pub trans_rot: Quat,
    /// Factor on the rotated translation: metres per file unit in normalisation.
    pub trans_scale: f32,
    /// Added to the mapped translation, in the parent's space after the map (metres once
    /// normalised).
    pub trans_offset: Vec3,
}

impl Default for ChannelMap {
    fn default() -> Self {
        Self::IDENTITY
    }
}

impl ChannelMap {
    /// The map that changes nothing.
    pub const IDENTITY: Self = Self {
        rot_pre: Quat::IDENTITY,
        rot_post: Quat::IDENTITY,
        trans_rot: Quat::IDENTITY,
        trans_scale: 1.0,
        trans_offset: Vec3::ZERO,
    };

    /// The map that applies `self` first, then `next`.
    #[must_use]
    pub fn then(&self, next: &ChannelMap) -> ChannelMap {
        ChannelMap {
            rot_pre: (next.rot_pre * self.rot_pre).normalize(),
            rot_post: (self.rot_post * next.rot_post).normalize(),
            trans_rot: (next.trans_rot * self.trans_rot).normalize(),
            trans_scale: next.trans_scale * self.trans_scale,
            trans_offset: next.trans_offset
                + next.trans_scale * (next.trans_rot * self.trans_offset),
        }
    }

    /// `rot_pre · q · rot_post`.
    #[must_use]
    pub fn rotation(&self, q: Quat) -> Quat {
        (self.rot_pre * q * self.rot_post).normalize()
    }

    /// `trans_offset + trans_scale · (trans_rot · t)`.
    #[must_use]
    pub fn translation(&self, t: Vec3) -> Vec3 {
        self.trans_offset + self.trans_scale * (self.trans_rot * t)
    }

    fn is_identity(&self) -> bool {
        *self == Self::IDENTITY
    }
}

/// One joint's channels and the map applied to them.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct JointChannels {
    /// The local rotation `R` of `D_j`, if animated.
    pub rotation: Option<RotationChannel>,
    /// The local translation `t` of `D_j`, in the parent's space (file units until the map
    /// scales them), if animated.
    pub translation: Option<VectorChannel>,
    /// The local per-axis scale `S` of `D_j`, if animated.
    pub scale: Option<VectorChannel>,
    /// The map applied to the sampled rotation and translation.
    pub map: ChannelMap,
}

impl JointChannels {
    /// Whether the joint has any channel.
    #[must_use]
    pub fn is_animated(&self) -> bool {
        self.rotation.is_some() || self.translation.is_some() || self.scale.is_some()
    }
}

/// How a playback time outside the clip is brought back into it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum Wrap {
    /// Hold the first / last pose.
    #[default]
    Clamp,
    /// Repeat from `start` every `duration`.
    Loop,
}

/// One morph channel's weight over time: a glTF `weights` animation split per target, named
/// by the target (the rig's morph channel of that name follows it, on every mesh that has it).
#[derive(Clone, Debug, PartialEq)]
pub struct MorphTrack {
    /// The morph channel (target name) it drives.
    pub channel: String,
    /// The weight over clip time (kept in `[0, 1]` when sampled).
    pub track: Track<f32>,
}

impl MorphTrack {
    /// The weight at clip time `time`, clamped to `[0, 1]` (a cubic spline may overshoot).
    #[must_use]
    pub fn sample(&self, time: f32) -> f32 {
        let w = self.track.sample(time);
        if w.is_finite() {
            w.clamp(0.0, 1.0)
        } else {
            0.0
        }
    }
}

/// An animation clip over a fixed joint list (one channel slot per skeleton joint), and the
/// morph channels it animates.
#[derive(Clone, Debug, PartialEq)]
pub struct Clip {
    name: String,
    start: f32,
    end: f32,
    joints: Vec<JointChannels>,
    morphs: Vec<MorphTrack>,
}

impl Clip {
    /// A clip over `joints`. `range` is the playback range in seconds; `None` takes the first
    /// and last key over all channels (`[0, 0]` when nothing is animated).
    pub fn new(
        name: impl Into<String>,
        joints: Vec<JointChannels>,
        range: Option<(f32, f32)>,
    ) -> Result<Self, ClipError> {
        let (start, end) = match range {
            Some(r) => r,
            None => {
                let mut r = (f32::INFINITY, f32::NEG_INFINITY);
                let mut grow = |(a, b): (f32, f32)| r = (r.0.min(a), r.1.max(b));
                for j in &joints {
                    j.rotation.iter().for_each(|c| grow(c.time_range()));
                    j.translation.iter().for_each(|c| grow(c.time_range()));
                    j.scale.iter().for_each(|c| grow(c.time_range()));
                }
                if r.0.is_finite() { r } else { (0.0, 0.0) }
            }
        };
        if !(start.is_finite() && end.is_finite() && start <= end) {
            return Err(ClipError::BadRange { start, end });
        }
        Ok(Self {
            name: name.into(),
            start,
            end,
            joints,
            morphs: Vec::new(),
        })
    }

    /// The same clip animating these morph channels too (replacing any it had; one track per
    /// channel: a later track of a channel already listed is dropped).
    #[must_use]
    pub fn with_morphs(mut self, morphs: Vec<MorphTrack>) -> Self {
        let mut kept: Vec<MorphTrack> = Vec::with_capacity(morphs.len());
        for m in morphs {
            if !kept.iter().any(|k| k.channel == m.channel) {
                kept.push(m);
            }
        }
        self.morphs = kept;
        self
    }

    /// The morph channels the clip animates.
    #[must_use]
    pub fn morphs(&self) -> &[MorphTrack] {
        &self.morphs
    }

    /// The clip's name (from the file, or given on import).
    #[must_use]
    pub fn name(&self) -> &str {
        &self.name
    }

    /// Renames the clip.
    pub fn set_name(&mut self, name: impl Into<String>) {
        self.name = name.into();
    }

    /// Clip time of the first pose, seconds (glTF clips may start after 0).
    #[must_use]
    pub fn start(&self) -> f32 {
        self.start
    }

    /// Clip time of the last pose, seconds.
    #[must_use]
    pub fn end(&self) -> f32 {
        self.end
    }

    /// `end − start`, seconds.
    #[must_use]
    pub fn duration(&self) -> f32 {
        self.end - self.start
    }

    /// Number of joint slots (the skeleton's joint count).
    #[must_use]
    pub fn joint_count(&self) -> usize {
        self.joints.len()
    }

    /// Every joint's channels.
    #[must_use]
    pub fn channels(&self) -> &[JointChannels] {
        &self.joints
    }

    /// Whether `joint` has a rotation channel (false for a joint past the slots).
    #[must_use]
    pub fn animates_rotation(&self, joint: usize) -> bool {
        self.joints.get(joint).is_some_and(|j| j.rotation.is_some())
    }

    /// Whether `joint` has a translation channel (false for a joint past the slots).
    #[must_use]
    pub fn animates_translation(&self, joint: usize) -> bool {
        self.joints
            .get(joint)
            .is_some_and(|j| j.translation.is_some())
    }

    /// Whether `joint` has a scale channel (false for a joint past the slots).
    #[must_use]
    pub fn animates_scale(&self, joint: usize) -> bool {
        self.joints.get(joint).is_some_and(|j| j.scale.is_some())
    }

    /// Whether a joint's channels all hold one value (constant tracks are stored once).
    #[must_use]
    pub fn is_static(&self, joint: usize) -> bool {
        self.joints.get(joint).is_none_or(|j| {
            j.rotation.as_ref().is_none_or(RotationChannel::is_constant)
                && j.translation
                    .as_ref()
                    .is_none_or(VectorChannel::is_constant)
                && j.scale.as_ref().is_none_or(VectorChannel::is_constant)
        })
    }

    /// Brings a playback time into the clip: clamped to `[start, end]`, or looped with period
    /// `duration` (a zero-length clip always gives `start`). NaN gives `start`.
    #[must_use]
    pub fn wrap_time(&self, t: f32, mode: Wrap) -> f32 {
        if t.is_nan() {
            return self.start;
        }
        match mode {
            Wrap::Clamp => t.clamp(self.start, self.end),
            Wrap::Loop => {
                let d = self.duration();
                if d <= 0.0 || !t.is_finite() {
                    self.start
                } else {
                    (self.start + (t - self.start).rem_euclid(d)).min(self.end)
                }
            }
        }
    }

    /// Exact random access at clip time `time` (seconds). Beyond the keys, tracks clamp and
    /// CSE169 curves extrapolate as their file says.
    ///
    /// Writes `out[j]` for `j < min(rest.len(), out.len())`: `rest[j]` with each animated
    /// component replaced by its (mapped) channel value. Joints the clip has no slot for keep
    /// `rest[j]`; entries of `out` past `rest.len()` are left untouched. Never panics.
    pub fn sample(&self, time: f32, rest: &[Transform], out: &mut [Transform]) {
        let mut cursors = [0usize; 9];
        for (j, (o, r)) in out.iter_mut().zip(rest).enumerate() {
            cursors.fill(0);
            *o = match self.joints.get(j) {
                Some(ch) => sample_joint(ch, time, r, &mut cursors),
                None => *r,
            };
        }
    }

    /// A sampler for this clip that caches each track's key position.
    #[must_use]
    pub fn sampler(&self) -> Sampler {
        Sampler::new(self)
    }

    /// Composes `map` after any map already on `joint` (see [`ChannelMap`]). Out-of-range
    /// joints are ignored.
    pub fn map_joint(&mut self, joint: usize, map: ChannelMap) {
        if let Some(j) = self.joints.get_mut(joint) {
            j.map = j.map.then(&map);
        }
    }

    /// The same clip over another joint list: new joint `i` takes old joint `source[i]`'s
    /// channels (none when `None` or out of range).
    #[must_use]
    pub fn remap_joints(&self, source: &[Option<usize>]) -> Clip {
        let joints = source
            .iter()
            .map(|s| {
                s.and_then(|old| self.joints.get(old))
                    .cloned()
                    .unwrap_or_default()
            })
            .collect();
        Clip {
            name: self.name.clone(),
            start: self.start,
            end: self.end,
            joints,
            morphs: self.morphs.clone(),
        }
    }

    /// Replaces joint `joint`'s channels (ignored when out of range).
    pub fn set_channels(&mut self, joint: usize, channels: JointChannels) {
        if let Some(j) = self.joints.get_mut(joint) {
            *j = channels;
        }
    }
}

/// One joint's local transform at `time`.
#[inline]
pub(crate) fn sample_joint(
    ch: &JointChannels,
    time: f32,
    rest: &Transform,
    cursors: &mut [usize; 9],
) -> Transform {
    let mut x = *rest;
    let (rc, rest_c) = cursors.split_at_mut(3);
    let (tc, sc) = rest_c.split_at_mut(3);
    let identity = ch.map.is_identity();
    if let Some(r) = &ch.rotation {
        let mut c = [rc[0], rc[1], rc[2]];
        let q = r.sample(time, &mut c);
        rc.copy_from_slice(&c);
        x.rotation = if identity { q } else { ch.map.rotation(q) };
    }
    if let Some(t) = &ch.translation {
        let mut c = [tc[0], tc[1], tc[2]];
        let v = t.sample(time, &mut c);
        tc.copy_from_slice(&c);
        x.translation = if identity { v } else { ch.map.translation(v) };
    }
    if let Some(s) = &ch.scale {
        let mut c = [sc[0], sc[1], sc[2]];
        x.scale = s.sample(time, &mut c);
        sc.copy_from_slice(&c);
    }
    x
}

#[cfg(test)]
mod tests {
    use super::*;

    fn two_joint_clip() -> Clip {
        let rot = Track::new(
            Interpolation::Linear,
            vec![1.0, 3.0],
            vec![Quat::IDENTITY, Quat::from_rotation_z(1.0)],
        )
        .unwrap();
        let trans = Track::new(
            Interpolation::Linear,
            vec![1.0, 3.0],
            vec![Vec3::ZERO, Vec3::new(2.0, 0.0, 0.0)],
        )
        .unwrap();
        let joints = vec![
            JointChannels {
                translation: Some(VectorChannel::Keys(trans)),
                ..Default::default()
            },
            JointChannels {
                rotation: Some(RotationChannel::Keys(rot)),
                ..Default::default()
            },
        ];
        Clip::new("walk", joints, None).unwrap()
    }

    #[test]
    fn range_and_flags() {
        let c = two_joint_clip();
        assert_eq!((c.start(), c.end(), c.duration()), (1.0, 3.0, 2.0));
        assert!(c.animates_translation(0) && !c.animates_rotation(0));
        assert!(c.animates_rotation(1) && !c.animates_scale(1));
        assert!(!c.animates_rotation(7));
        assert_eq!(c.wrap_time(3.5, Wrap::Loop), 1.5);
        assert_eq!(c.wrap_time(0.5, Wrap::Loop), 2.5);
        assert_eq!(c.wrap_time(3.5, Wrap::Clamp), 3.0);
        assert_eq!(c.wrap_time(f32::NAN, Wrap::Loop), 1.0);
    }

    #[test]
    fn rest_fills_unanimated_components_and_lengths_are_safe() {
        let c = two_joint_clip();
        let rest = [
            Transform::from_translation_rotation(Vec3::Y, Quat::from_rotation_x(0.3)),
            Transform::from_translation(Vec3::Z),
            Transform::from_translation(Vec3::X),
        ];
        let mut out = [Transform::IDENTITY; 3];
        c.sample(2.0, &rest, &mut out);
        assert_eq!(out[0].translation, Vec3::X);
        assert_eq!(out[0].rotation, rest[0].rotation);
        assert_eq!(out[1].translation, Vec3::Z);
        assert!(out[1].rotation.dot(Quat::from_rotation_z(0.5)).abs() > 1.0 - 1e-6);
        assert_eq!(out[2], rest[2]);
        // Short buffers: no panic, only the overlap is written.
        let mut short = [Transform::IDENTITY; 1];
        c.sample(2.0, &rest, &mut short);
        assert_eq!(short[0].translation, Vec3::X);
        c.sample(2.0, &rest[..0], &mut out);
    }

    #[test]
    fn channel_maps_compose() {
        let mut c = two_joint_clip();
        let a = ChannelMap {
            rot_pre: Quat::from_rotation_x(0.4),
            rot_post: Quat::from_rotation_y(-0.2),
            trans_rot: Quat::from_rotation_y(1.0),
            trans_scale: 2.0,
            trans_offset: Vec3::new(0.0, 1.0, 0.0),
        };
        let b = ChannelMap {
            rot_pre: Quat::from_rotation_z(0.7),
            rot_post: Quat::from_rotation_x(0.1),
            trans_rot: Quat::from_rotation_x(0.5),
            trans_scale: 0.01,
            trans_offset: Vec3::new(3.0, 0.0, 0.0),
        };
        let rest = [Transform::IDENTITY; 2];
        let mut before = [Transform::IDENTITY; 2];
        c.sample(2.2, &rest, &mut before);
        c.map_joint(0, a);
        c.map_joint(0, b);
        c.map_joint(1, a);
        c.map_joint(1, b);
        let mut after = [Transform::IDENTITY; 2];
        c.sample(2.2, &rest, &mut after);
        let t = before[0].translation;
        let expected_t = b.trans_offset
            + b.trans_scale * (b.trans_rot * (a.trans_offset + a.trans_scale * (a.trans_rot * t)));
        assert!(after[0].translation.abs_diff_eq(expected_t, 1e-5));
        let q = before[1].rotation;
        let expected_q = b.rot_pre * (a.rot_pre * q * a.rot_post) * b.rot_post;
        assert!(after[1].rotation.dot(expected_q).abs() > 1.0 - 1e-5);
    }

    #[test]
    fn remap_moves_channels() {
        let c = two_joint_clip();
        let r = c.remap_joints(&[Some(1), None, Some(0), Some(9)]);
        assert_eq!(r.joint_count(), 4);
        assert!(r.animates_rotation(0) && r.animates_translation(2));
        assert!(!r.animates_rotation(1) && !r.animates_rotation(3));
    }

    #[test]
    fn euler_channel_is_rz_ry_rx() {
        let curves = Box::new([
            Curve::constant(0.3),
            Curve::constant(-0.4),
            Curve::constant(1.1),
        ]);
        let joints = vec![JointChannels {
            rotation: Some(RotationChannel::Euler(curves)),
            ..Default::default()
        }];
        let c = Clip::new("e", joints, Some((0.0, 1.0))).unwrap();
        let mut out = [Transform::IDENTITY];
        c.sample(0.5, &[Transform::IDENTITY], &mut out);
        let expected =
            Quat::from_rotation_z(1.1) * Quat::from_rotation_y(-0.4) * Quat::from_rotation_x(0.3);
        assert!(out[0].rotation.dot(expected).abs() > 1.0 - 1e-6);
        assert!(c.is_static(0));
    }
}
