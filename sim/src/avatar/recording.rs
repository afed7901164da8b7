//! Recording what an avatar streams into a clip on its rig (issue 16, "Recording").
//!
//! A [`Recorder`] is fed, once per tick, the avatar's streamed pose ([`AvatarPose`]: every
//! joint's local rotation, the translations of the description's `translated_joints` — the
//! roots always — the scales of its `scaled_joints`, and the avatar's placement) with the
//! scene clock. Whatever drove the avatar (clips, joint overrides, a live driver, DOF clamping)
//! is in that pose, so the recording is what subscribers were sent, before quantisation.
//!
//! **Placement** is folded into the root joints relative to the placement at the first tick:
//! `D'_root = (P_0⁻¹ · P_t) · D_root`. An avatar that stood still records its joints exactly
//! as streamed; one moved by `place_avatar` or by accumulated root motion records that
//! movement, so the clip played on an avatar placed where the recording started retraces it.
//!
//! **Bounds**: a recording stops growing at [`RecordLimits::max_seconds`] of scene time or
//! [`RecordLimits::max_bytes`] of samples, whichever comes first. Later ticks are counted
//! ([`Recorder::dropped`]) and not kept, so a forgotten recording holds a fixed amount of
//! memory; the caller sees [`Pushed::Full`] and can stop it and tell whoever started it.
//! The defaults (10 minutes, 64 MiB) hold a 10-minute take at 60 Hz of a rig of up to ~110
//! joints; the built-in avatar's 23 joints need 380 bytes a tick, 13.7 MB for the 10 minutes.
//!
//! [`Recorder::finish`] gives a [`Clip`] over the avatar's joints (its description's order
//! and names): a linear rotation track per joint (slerp between ticks, as the tick stream is
//! best read), linear translation and scale tracks for the streamed ones, time from 0 at
//! the first tick to the last; tracks that never changed are stored once; a linear weight
//! track per morph channel that was ever away from 0 (the weights streamed, quantised).

use glam::{Quat, Vec3};
use posecast_proto::description::AvatarDescription;
use posecast_proto::frame::AvatarPose;
use posecast_proto::placement::Placement;
use posecast_rigs::clip::{
    Clip, ClipError, Interpolation, JointChannels, MorphTrack, RotationChannel, Track,
};
use posecast_rigs::clip::{TrackValue, VectorChannel};

/// How much one recording may hold.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RecordLimits {
    /// Longest recording, seconds of scene time from the first tick. Clip times are f32:
    /// at 600 s they resolve 61 µs, at 4.5 hours 2 ms — keep it to hours, not days.
    pub max_seconds: f64,
    /// Most bytes of samples: per tick 4 (time) + 16 per joint + 12 per streamed translation
    /// or scale. Vectors grow to at most this, never by doubling past it.
    pub max_bytes: usize,
}

impl RecordLimits {
    /// 10 minutes, 64 MiB.
    pub const DEFAULT: Self = Self {
        max_seconds: 600.0,
        max_bytes: 64 << 20,
    };
}

impl Default for RecordLimits {
    fn default() -> Self {
        Self::DEFAULT
    }
}

/// Why a tick was not recorded, or a recording gave no clip.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum RecordError {
    /// The pose's description hash is not the recording's: the avatar's rig changed.
    #[error(
        "the pose is of another rig (description hash {got:016x}; the recording's is {expected:016x})"
    )]
    RigChanged {
        /// The description hash the recording started with.
        expected: u64,
        /// The hash the pose carries.
        got: u64,
    },
    /// The pose's counts do not match the description the recording started with.
    #[error(
        "the pose has {rotations} rotations, {translations} translations and {scales} scales; the description streams {joints}, {translated} and {scaled}"
    )]
    Shape {
        /// Rotations in the pose.
        rotations: usize,
        /// Translations in the pose.
        translations: usize,
        /// Scales in the pose.
        scales: usize,
        /// Joints in the description (one rotation each).
        joints: usize,
        /// How many joints the description streams translations of (`translated_joints`).
        translated: usize,
        /// How many joints the description streams scales of (`scaled_joints`).
        scaled: usize,
    },
    /// The tick's time is not finite or goes back before the last recorded tick.
    #[error("tick time {time} s is not finite, or before the last recorded tick ({last} s)")]
    Time {
        /// The tick's scene time, seconds.
        time: f64,
        /// The last recorded tick's scene time, seconds.
        last: f64,
    },
    /// [`Recorder::finish`] was called before any tick was recorded.
    #[error("nothing was recorded")]
    Empty,
    /// The recorded tracks were refused as a clip.
    #[error("the recorded samples do not make a clip: {0}")]
    Clip(#[from] ClipError),
}

/// What [`Recorder::push`] did with a tick.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Pushed {
    /// Appended.
    Recorded,
    /// Same time as the last tick (the pose was re-evaluated): the newer pose replaced it.
    Replaced,
    /// The recording is at its limits: not kept (counted in [`Recorder::dropped`]).
    Full,
}

/// One avatar's recording in progress.
#[derive(Clone, Debug)]
pub struct Recorder {
    name: String,
    hash: u64,
    joints: usize,
    translated: Vec<usize>,
    scaled: Vec<usize>,
    /// Per root joint: its index in `translated`, if streamed.
    roots: Vec<(usize, Option<usize>)>,
    limits: RecordLimits,
    max_frames: usize,
    /// Scene time and placement of the first tick.
    origin: Option<(f64, Placement)>,
    /// Root motion in scene space ([`Recorder::in_scene_space`]): the origin's placement is
    /// the identity rather than the first tick's.
    scene_space: bool,
    /// Scene time of the last tick kept.
    last: f64,
    times: Vec<f32>,
    /// `joints` per tick.
    rotations: Vec<Quat>,
    /// `translated.len()` per tick.
    translations: Vec<Vec3>,
    /// `scaled.len()` per tick.
    scales: Vec<Vec3>,
    /// The description's morph channels.
    channels: Vec<String>,
    /// `channels.len()` morph weights per tick.
    weights: Vec<f32>,
    full: bool,
    dropped: u64,
}

impl Recorder {
    /// A recording, to become clip `name`, of the avatar `description` describes.
    #[must_use]
    pub fn new(
        name: impl Into<String>,
        description: &AvatarDescription,
        limits: RecordLimits,
    ) -> Self {
        let joints = description.joint_names.len();
        let translated: Vec<usize> = description
            .translated_joints
            .iter()
            .map(|&j| usize::from(j))
            .collect();
        let scaled: Vec<usize> = description
            .scaled_joints
            .iter()
            .map(|&j| usize::from(j))
            .collect();
        let roots = (0..joints)
            .filter(|&j| description.parents.get(j).is_none_or(|&p| p < 0))
            .map(|j| (j, translated.iter().position(|&t| t == j)))
            .collect();
        let channels = description.morph_targets.clone();
        let per_frame =
            4 + 16 * joints + 12 * (translated.len() + scaled.len()) + 4 * channels.len();
        Self {
            name: name.into(),
            hash: description.hash_u64(),
            joints,
            roots,
            max_frames: (limits.max_bytes / per_frame).max(1),
            limits,
            translated,
            scaled,
            origin: None,
            scene_space: false,
            last: f64::NEG_INFINITY,
            times: Vec::new(),
            rotations: Vec::new(),
            translations: Vec::new(),
            scales: Vec::new(),
            weights: Vec::new(),
            channels,
            full: false,
            dropped: 0,
        }
    }

    /// Records the roots in scene space: every placement, the first one included, moves
    /// them (by default the clip starts where the avatar stood at its first tick, so it plays
    /// from wherever the avatar playing it stands). For exports of a whole scene, where every
    /// avatar keeps its place.
    #[must_use]
    pub fn in_scene_space(mut self) -> Self {
        self.scene_space = true;
        self
    }

    /// The clip's name.
    #[must_use]
    pub fn name(&self) -> &str {
        &self.name
    }

    /// Records the pose streamed at scene time `time` (seconds).
    ///
    /// # Errors
    /// The pose is of another rig or shape than the description the recording started with
    /// (the avatar's rig changed), or `time` is not finite or before the last tick. Nothing
    /// is recorded then.
    pub fn push(&mut self, time: f64, pose: &AvatarPose) -> Result<Pushed, RecordError> {
        if pose.hash != self.hash {
            return Err(RecordError::RigChanged {
                expected: self.hash,
                got: pose.hash,
            });
        }
        if pose.rotations.len() != self.joints
            || pose.translations.len() != self.translated.len()
            || pose.scales.len() != self.scaled.len()
        {
            return Err(RecordError::Shape {
                rotations: pose.rotations.len(),
                translations: pose.translations.len(),
                scales: pose.scales.len(),
                joints: self.joints,
                translated: self.translated.len(),
                scaled: self.scaled.len(),
            });
        }
        if !time.is_finite() || time < self.last {
            return Err(RecordError::Time {
                time,
                last: self.last,
            });
        }
        let start = if self.scene_space {
            Placement::IDENTITY
        } else {
            pose.placement
        };
        let (t0, _) = *self.origin.get_or_insert((time, start));
        let since = time - t0;
        let key = since as f32;
        let replace = self.times.last() == Some(&key);
        if replace {
            let n = self.times.len() - 1;
            self.rotations.truncate(n * self.joints);
            self.translations.truncate(n * self.translated.len());
            self.scales.truncate(n * self.scaled.len());
            self.weights.truncate(n * self.channels.len());
            if n == 0 {
                // The first tick again: its placement is the origin.
                self.origin = Some((t0, start));
            }
        } else if self.full || since > self.limits.max_seconds || self.frames() >= self.max_frames {
            self.full = true;
            self.dropped += 1;
            return Ok(Pushed::Full);
        } else {
            self.times.push(key);
        }
        self.last = time;
        let first_rotation = self.rotations.len();
        let first_translation = self.translations.len();
        let max = self.max_frames;
        append_bounded(&mut self.rotations, &pose.rotations, max);
        append_bounded(&mut self.translations, &pose.translations, max);
        append_bounded(&mut self.scales, &pose.scales, max);
        // One weight per channel (a pose without weights: all 0).
        if pose.weights.len() == self.channels.len() {
            append_bounded(&mut self.weights, &pose.weights, max);
        } else {
            append_bounded(&mut self.weights, &vec![0.0; self.channels.len()], max);
        }
        let p0 = self.origin.map_or(pose.placement, |(_, p)| p);
        // P_0⁻¹ · P_t, applied to every root: D' = (r, p) · D.
        if pose.placement != p0 {
            let back = p0.rotation.inverse();
            let r = (back * pose.placement.rotation).normalize();
            let p = back * (pose.placement.position - p0.position);
            for &(root, streamed) in &self.roots {
                if let Some(q) = self.rotations.get_mut(first_rotation + root) {
                    *q = (r * *q).normalize();
                }
                let t = streamed.and_then(|k| self.translations.get_mut(first_translation + k));
                if let Some(t) = t {
                    *t = p + r * *t;
                }
            }
        }
        Ok(if replace {
            Pushed::Replaced
        } else {
            Pushed::Recorded
        })
    }

    /// Ticks recorded.
    #[must_use]
    pub fn frames(&self) -> usize {
        self.times.len()
    }

    /// Seconds from the first tick to the last recorded.
    #[must_use]
    pub fn duration(&self) -> f32 {
        self.times.last().copied().unwrap_or(0.0)
    }

    /// Whether the limits were reached (later ticks are dropped).
    #[must_use]
    pub fn is_full(&self) -> bool {
        self.full
    }

    /// Ticks not kept because the recording was full.
    #[must_use]
    pub fn dropped(&self) -> u64 {
        self.dropped
    }

    /// The limits this recording runs under.
    #[must_use]
    pub fn limits(&self) -> RecordLimits {
        self.limits
    }

    /// The recording as a clip named as given to [`Recorder::new`] (see the module
    /// documentation).
    ///
    /// # Errors
    /// [`RecordError::Empty`] when no tick was recorded.
    pub fn finish(self) -> Result<Clip, RecordError> {
        if self.times.is_empty() {
            return Err(RecordError::Empty);
        }
        let mut channels = vec![JointChannels::default(); self.joints];
        for (j, ch) in channels.iter_mut().enumerate() {
            let keys = column(&self.rotations, self.joints, j);
            ch.rotation = Some(RotationChannel::Keys(self.track(keys)?));
        }
        for (k, &j) in self.translated.iter().enumerate() {
            let keys = column(&self.translations, self.translated.len(), k);
            if let Some(ch) = channels.get_mut(j) {
                ch.translation = Some(VectorChannel::Keys(self.track(keys)?));
            }
        }
        for (k, &j) in self.scaled.iter().enumerate() {
            let keys = column(&self.scales, self.scaled.len(), k);
            if let Some(ch) = channels.get_mut(j) {
                ch.scale = Some(VectorChannel::Keys(self.track(keys)?));
            }
        }
        // A morph channel that moved during the take (one never away from 0 is left out).
        let mut morphs = Vec::new();
        for (c, channel) in self.channels.iter().enumerate() {
            let keys = column(&self.weights, self.channels.len(), c);
            if keys.iter().any(|&w| w != 0.0) {
                morphs.push(MorphTrack {
                    channel: channel.clone(),
                    track: self.track(keys)?,
                });
            }
        }
        let end = self.duration();
        Ok(Clip::new(self.name, channels, Some((0.0, end)))?.with_morphs(morphs))
    }

    fn track<T: TrackValue>(&self, keys: Vec<T>) -> Result<Track<T>, ClipError> {
        Track::new(Interpolation::Linear, self.times.clone(), keys)
    }
}

/// Entry `k` of every `stride`-long row.
fn column<T: Copy>(values: &[T], stride: usize, k: usize) -> Vec<T> {
    values
        .iter()
        .skip(k)
        .step_by(stride.max(1))
        .copied()
        .collect()
}

/// Appends one tick's `row`, growing `v` by doubling but never past `max_frames` rows, so the
/// bound is on memory, not only on length.
fn append_bounded<T: Copy>(v: &mut Vec<T>, row: &[T], max_frames: usize) {
    let needed = v.len() + row.len();
    if needed > v.capacity() {
        let limit = max_frames.saturating_mul(row.len()).max(needed);
        let target = v.capacity().saturating_mul(2).clamp(needed, limit);
        v.reserve_exact(target - v.len());
    }
    v.extend_from_slice(row);
}

#[cfg(test)]
mod tests {
    use super::*;
    use posecast_proto::Transform;
    use posecast_proto::msg::AvatarId;
    use posecast_rigs::asset::Asset;

    /// The built-in avatar as imported: turned rest frames, `walk` moves the root.
    fn avatar() -> Asset {
        posecast_rigs::import::gltf::from_slice("avatar.glb", posecast_rigs::builtin::AVATAR_GLB)
            .unwrap()
            .remove(0)
    }

    fn describe(asset: &Asset, clip: &Clip) -> AvatarDescription {
        let n = asset.skeleton.len();
        let translated: Vec<bool> = (0..n).map(|j| clip.animates_translation(j)).collect();
        let scaled = vec![false; n];
        AvatarDescription::new(
            AvatarId("a".into()),
            1,
            asset.name.clone(),
            &asset.skeleton,
            &translated,
            &scaled,
            None,
        )
    }

    /// What the avatar streams when it shows `locals`: `Avatar::evaluate`'s selection.
    fn streamed(d: &AvatarDescription, locals: &[Transform], placement: Placement) -> AvatarPose {
        AvatarPose {
            avatar_num: d.num,
            hash: d.hash_u64(),
            rotations: locals.iter().map(|t| t.rotation).collect(),
            translations: d
                .translated_joints
                .iter()
                .map(|&j| locals[usize::from(j)].translation)
                .collect(),
            scales: d
                .scaled_joints
                .iter()
                .map(|&j| locals[usize::from(j)].scale)
                .collect(),
            placement,
            weights: Vec::new(),
        }
    }

    fn same_rotation(a: Quat, b: Quat, tol: f32) -> bool {
        let (a, b) = (glam::Vec4::from(a), glam::Vec4::from(b));
        (a - b).abs().max_element() <= tol || (a + b).abs().max_element() <= tol
    }

    /// Records `clip` sampled at `rate` Hz from scene time `t0` with a fixed placement.
    fn record(asset: &Asset, clip: &Clip, rate: f64, t0: f64) -> (Clip, Vec<f64>) {
        let d = describe(asset, clip);
        let mut rec = Recorder::new("take", &d, RecordLimits::DEFAULT);
        let rest = asset.skeleton.rest();
        let mut locals = rest.to_vec();
        let ticks = (f64::from(clip.duration()) * rate).round() as usize;
        let mut times = Vec::new();
        let here = Placement {
            position: Vec3::new(2.0, 0.0, -1.0),
            rotation: Quat::from_rotation_y(0.7),
        };
        for k in 0..=ticks {
            let t = k as f64 / rate;
            clip.sample(t as f32, rest, &mut locals);
            assert_eq!(
                rec.push(t0 + t, &streamed(&d, &locals, here)),
                Ok(Pushed::Recorded)
            );
            times.push(t);
        }
        assert_eq!(rec.frames(), ticks + 1);
        (rec.finish().unwrap(), times)
    }

    #[test]
    fn a_recorded_clip_samples_back_as_the_clip_at_every_tick() {
        let asset = avatar();
        for clip in &asset.clips {
            // 60 Hz ticks over a 30 Hz clip, starting at an arbitrary scene time.
            let (take, ticks) = record(&asset, clip, 60.0, 1234.5);
            assert_eq!(take.name(), "take");
            assert_eq!(take.joint_count(), asset.skeleton.len());
            assert_eq!((take.start(), take.end()), (0.0, clip.duration()));
            let rest = asset.skeleton.rest();
            let (mut want, mut got) = (rest.to_vec(), rest.to_vec());
            for &t in &ticks {
                clip.sample(t as f32, rest, &mut want);
                take.sample(t as f32, rest, &mut got);
                for (j, (w, g)) in want.iter().zip(&got).enumerate() {
                    assert!(
                        same_rotation(w.rotation, g.rotation, 1e-6),
                        "{} joint {j} at {t}",
                        clip.name()
                    );
                    assert!(w.translation.abs_diff_eq(g.translation, 1e-6));
                }
            }
        }
    }

    #[test]
    fn ticks_on_the_clip_keys_record_the_same_motion_between_them_too() {
        let asset = avatar();
        let clip = &asset.clips[1]; // walk: 30 Hz keys, root translation
        let (take, _) = record(&asset, clip, 30.0, 0.0);
        let rest = asset.skeleton.rest();
        let (mut want, mut got) = (rest.to_vec(), rest.to_vec());
        for i in 0..=300 {
            let t = i as f32 * clip.duration() / 300.0;
            clip.sample(t, rest, &mut want);
            take.sample(t, rest, &mut got);
            for (w, g) in want.iter().zip(&got) {
                assert!(same_rotation(w.rotation, g.rotation, 1e-6), "at {t}");
                assert!(w.translation.abs_diff_eq(g.translation, 1e-6), "at {t}");
            }
        }
    }

    #[test]
    fn placement_moves_are_folded_into_the_roots_relative_to_the_start() {
        let asset = avatar();
        let clip = &asset.clips[1];
        let d = describe(&asset, clip);
        let mut rec = Recorder::new("moved", &d, RecordLimits::DEFAULT);
        let rest = asset.skeleton.rest();
        let mut locals = rest.to_vec();
        let placement = |k: usize| Placement {
            position: Vec3::new(1.0 + 0.1 * k as f32, 0.0, -0.05 * k as f32),
            // Not only about Y, so that a rotation composed on the wrong side shows.
            rotation: Quat::from_axis_angle(
                Vec3::new(0.3, 1.0, 0.2).normalize(),
                0.3 + 0.02 * k as f32,
            ),
        };
        let mut expected = Vec::new();
        for k in 0..20 {
            let t = k as f32 / 30.0;
            clip.sample(t, rest, &mut locals);
            // A turning root, as an override would make it.
            locals[0].rotation = Quat::from_rotation_x(0.1 * k as f32) * locals[0].rotation;
            rec.push(f64::from(t), &streamed(&d, &locals, placement(k)))
                .unwrap();
            // World of the root: P_t · D_root; relative to the start: P_0⁻¹ · P_t · D_root.
            let root =
                placement(0).to_mat4().inverse() * placement(k).to_mat4() * locals[0].to_mat4();
            expected.push((t, root, locals[1]));
        }
        let take = rec.finish().unwrap();
        let mut got = rest.to_vec();
        for (t, root, child) in expected {
            take.sample(t, rest, &mut got);
            assert!(
                got[0].to_mat4().abs_diff_eq(root, 1e-5),
                "root at {t}: {:?} vs {root:?}",
                got[0].to_mat4()
            );
            // Only the roots move with the placement.
            assert!(same_rotation(got[1].rotation, child.rotation, 1e-6));
            assert_eq!(got[1].translation, child.translation);
        }
    }

    #[test]
    fn limits_stop_the_recording_and_count_what_is_dropped() {
        let asset = avatar();
        let clip = &asset.clips[0];
        let d = describe(&asset, clip);
        let per_frame = 4 + 16 * d.joint_names.len() + 12 * d.translated_joints.len();
        let limits = RecordLimits {
            max_seconds: 100.0,
            max_bytes: 10 * per_frame + per_frame / 2,
        };
        let mut rec = Recorder::new("short", &d, limits);
        let pose = streamed(&d, asset.skeleton.rest(), Placement::IDENTITY);
        let results: Vec<Pushed> = (0..15)
            .map(|k| rec.push(f64::from(k) * 0.1, &pose).unwrap())
            .collect();
        assert_eq!(results[9], Pushed::Recorded);
        assert_eq!(results[10], Pushed::Full);
        assert!(rec.is_full() && rec.frames() == 10 && rec.dropped() == 5);
        assert!(rec.rotations.capacity() <= 10 * d.joint_names.len());
        let take = rec.finish().unwrap();
        assert!((take.duration() - 0.9).abs() < 1e-6);

        let mut timed = Recorder::new(
            "timed",
            &d,
            RecordLimits {
                max_seconds: 1.0,
                ..RecordLimits::DEFAULT
            },
        );
        for k in 0..=10 {
            assert_eq!(
                timed.push(5.0 + f64::from(k) * 0.1, &pose).unwrap(),
                Pushed::Recorded
            );
        }
        assert_eq!(timed.push(6.2, &pose).unwrap(), Pushed::Full);
    }

    #[test]
    fn bad_ticks_change_nothing() {
        let asset = avatar();
        let clip = &asset.clips[1];
        let d = describe(&asset, clip);
        let mut rec = Recorder::new("bad", &d, RecordLimits::DEFAULT);
        assert_eq!(rec.clone().finish(), Err(RecordError::Empty));
        let pose = streamed(&d, asset.skeleton.rest(), Placement::IDENTITY);
        rec.push(1.0, &pose).unwrap();
        // Re-evaluated at the same tick: the newer pose wins.
        let mut turned = pose.clone();
        turned.rotations[3] = Quat::from_rotation_x(0.5);
        assert_eq!(rec.push(1.0, &turned), Ok(Pushed::Replaced));
        assert!(matches!(
            rec.push(0.5, &pose),
            Err(RecordError::Time { .. })
        ));
        assert!(matches!(
            rec.push(f64::NAN, &pose),
            Err(RecordError::Time { .. })
        ));
        let mut short = pose.clone();
        short.rotations.pop();
        assert!(matches!(
            rec.push(2.0, &short),
            Err(RecordError::Shape { .. })
        ));
        let mut other = pose.clone();
        other.hash ^= 1;
        assert!(matches!(
            rec.push(2.0, &other),
            Err(RecordError::RigChanged { .. })
        ));
        assert_eq!(rec.frames(), 1);
        let take = rec.finish().unwrap();
        let mut got = asset.skeleton.rest().to_vec();
        take.sample(0.0, asset.skeleton.rest(), &mut got);
        assert!(same_rotation(
            got[3].rotation,
            Quat::from_rotation_x(0.5),
            1e-6
        ));
    }
}
