//! A [`Clip`] as glTF animation channels: one channel per animated component (translation,
//! rotation, scale) of each joint, with the clip's channel maps (rig normalisation) applied.
//!
//! Time: glTF animations run from 0 and forbid negative key times, so a key at clip time `t`
//! is written at `t − start`; the exported animation covers exactly `[0, duration]`. Every
//! channel is written over that whole range, so the re-imported clip has the same range.
//!
//! Keys, per channel kind — exact where glTF can say the same thing, resampled where not:
//! - **Step and linear key tracks** keep their interpolation and their own keys inside
//!   `(start, end)`, plus one key at `start` and one at `end` holding the clip's value there.
//!   Values are the mapped samples (`rot_pre · q · rot_post`, …) at those times: slerp and
//!   lerp commute with the maps (left/right multiplication by unit quaternions and affine maps
//!   preserve geodesics and lines), so this is exact, and so is trimming keys outside the range.
//! - **Cubic-spline key tracks** whose keys lie within `[start, end]` are written as cubic
//!   splines with mapped values and tangents (the maps are linear in the Hermite terms; glTF
//!   normalises a cubic rotation after evaluation, as the clip does). Range ends beyond the
//!   keys get a key holding the end value, with the tangents facing it zeroed (they were
//!   unused: the clip clamps past its keys). Cubic tracks with keys outside the range are
//!   resampled, as splitting a segment would need unnormalised rotation keys.
//! - **CSE169 curves** (Euler-angle and per-axis Hermite curves with extrapolation) have no glTF
//!   form: they are sampled as linear keys at [`RESAMPLE_RATE`] plus every curve key inside the
//!   range. The export then equals the clip at every written key, and between keys differs by
//!   the linear-interpolation error of a 60 Hz sampling — the rate a subscriber receives at the
//!   server's default tick rate.
//!
//! Step and linear rotation keys are sign-aligned with the key before (`q` and `−q` are one
//! rotation), so readers that do not take the shortest path still play the same motion.

use super::ExportError;
use super::glb::{Animation, Channel, Output, Weights};
use crate::clip::{
    Clip, Interpolation, JointChannels, RotationChannel, Track, VectorChannel, sample_joint,
};
use glam::{Quat, Vec3};
use posecast_proto::Transform;

/// Keys per second for channels glTF cannot carry key for key (CSE169 curves).
pub const RESAMPLE_RATE: f64 = 60.0;

/// Resampled keys closer than this to the key before (seconds) are dropped.
const MIN_KEY_GAP: f32 = 1e-5;

/// `clip` as one glTF animation of a skeleton with `joints` joints (channel `j` targets node
/// `j`), named after the clip; its morph tracks as a `weights` channel over the mesh's
/// `targets` (morph channel names, the mesh's target order) — see [`weights`].
///
/// # Errors
/// The clip has more joint slots than `joints` ([`ExportError::JointCount`]) or no channel at
/// all ([`ExportError::NothingAnimated`]).
pub fn animation(clip: &Clip, joints: usize, targets: &[String]) -> Result<Animation, ExportError> {
    if clip.joint_count() > joints {
        return Err(ExportError::JointCount {
            clip: clip.name().to_owned(),
            clip_joints: clip.joint_count(),
            rig_joints: joints,
        });
    }
    let mut channels = Vec::new();
    for (joint, ch) in clip.channels().iter().enumerate() {
        if let Some(t) = &ch.translation {
            channels.push(vector_channel(clip, joint, ch, t, Component::Translation));
        }
        if let Some(r) = &ch.rotation {
            channels.push(rotation_channel(clip, joint, ch, r));
        }
        if let Some(s) = &ch.scale {
            channels.push(vector_channel(clip, joint, ch, s, Component::Scale));
        }
    }
    let weights = weights(clip, targets);
    if channels.is_empty() && weights.is_none() {
        return Err(ExportError::NothingAnimated {
            clip: clip.name().to_owned(),
        });
    }
    Ok(Animation {
        name: clip.name().to_owned(),
        channels,
        weights,
    })
}

/// The clip's morph tracks as one linear `weights` channel over `targets`: keys at the
/// clip's start and end and at every morph key between, each target's weight sampled there
/// (0 for a target the clip does not animate). Exact for step-free linear tracks (a recorded
/// take's); step and cubic tracks are read at their keys and joined linearly. `None` when no
/// track drives one of `targets`.
#[must_use]
pub fn weights(clip: &Clip, targets: &[String]) -> Option<Weights> {
    let tracks: Vec<Option<&crate::clip::MorphTrack>> = targets
        .iter()
        .map(|t| clip.morphs().iter().find(|m| m.channel == *t))
        .collect();
    if tracks.iter().all(Option::is_none) {
        return None;
    }
    let (start, end) = (clip.start(), clip.end());
    let mut times = vec![start, end];
    for m in tracks.iter().flatten() {
        times.extend(
            m.track
                .times()
                .iter()
                .copied()
                .filter(|&t| t > start && t < end),
        );
    }
    times.sort_by(f32::total_cmp);
    times.dedup_by(|a, b| (*a - *b).abs() < MIN_KEY_GAP);
    let values = times
        .iter()
        .flat_map(|&t| tracks.iter().map(move |m| m.map_or(0.0, |m| m.sample(t))))
        .collect();
    Some(Weights {
        times: times.iter().map(|&t| t - start).collect(),
        values,
    })
}

#[derive(Clone, Copy, PartialEq, Eq)]
enum Component {
    Translation,
    Scale,
}

/// How one channel's keys are written.
enum Keys<'a, T> {
    /// At these clip times, sampled, with this interpolation (step or linear).
    Sampled(Interpolation, Vec<f32>),
    /// The track's own cubic keys, within the clip's range.
    Cubic(&'a Track<T>),
}

fn plan<'a, T: crate::clip::TrackValue>(clip: &Clip, track: &'a Track<T>) -> Keys<'a, T> {
    let (first, last) = track.time_range();
    match track.interpolation() {
        Interpolation::CubicSpline if first >= clip.start() && last <= clip.end() => {
            Keys::Cubic(track)
        }
        Interpolation::CubicSpline => {
            Keys::Sampled(Interpolation::Linear, resample_times(clip, track.times()))
        }
        i => Keys::Sampled(i, range_times(clip, track.times())),
    }
}

fn rotation_channel(clip: &Clip, joint: usize, ch: &JointChannels, r: &RotationChannel) -> Channel {
    let keys = match r {
        RotationChannel::Keys(track) => plan(clip, track),
        RotationChannel::Euler(curves) => {
            let times: Vec<f32> = curves.iter().flat_map(|c| c.times()).copied().collect();
            Keys::Sampled(Interpolation::Linear, resample_times(clip, &times))
        }
    };
    let (interpolation, times, mut values): (_, _, Vec<Quat>) = match keys {
        Keys::Sampled(interpolation, times) => {
            let values = times
                .iter()
                .map(|&t| sample(ch, t).rotation)
                .collect::<Vec<_>>();
            (interpolation, times, values)
        }
        Keys::Cubic(track) => {
            let map = &ch.map;
            cubic(
                clip,
                track,
                |q| map.rotation(q),
                |m| map.rot_pre * m * map.rot_post,
                Quat::from_xyzw(0.0, 0.0, 0.0, 0.0),
            )
        }
    };
    align_hemispheres(&mut values, interpolation);
    let (times, values) = shift(clip, times, values, stride(interpolation));
    Channel {
        joint,
        interpolation,
        times,
        output: Output::Rotation(values),
    }
}

fn vector_channel(
    clip: &Clip,
    joint: usize,
    ch: &JointChannels,
    v: &VectorChannel,
    component: Component,
) -> Channel {
    let keys = match v {
        VectorChannel::Keys(track) => plan(clip, track),
        VectorChannel::Curves(curves) => {
            let times: Vec<f32> = curves.iter().flat_map(|c| c.times()).copied().collect();
            Keys::Sampled(Interpolation::Linear, resample_times(clip, &times))
        }
    };
    let pick = |x: Transform| match component {
        Component::Translation => x.translation,
        Component::Scale => x.scale,
    };
    let (interpolation, times, values): (_, _, Vec<Vec3>) = match keys {
        Keys::Sampled(interpolation, times) => {
            let values = times.iter().map(|&t| pick(sample(ch, t))).collect();
            (interpolation, times, values)
        }
        Keys::Cubic(track) => {
            let map = ch.map;
            // Scale channels are not mapped (see `ChannelMap`).
            let translation = component == Component::Translation;
            cubic(
                clip,
                track,
                |v| if translation { map.translation(v) } else { v },
                |m| {
                    if translation {
                        map.trans_scale * (map.trans_rot * m)
                    } else {
                        m
                    }
                },
                Vec3::ZERO,
            )
        }
    };
    let (times, values) = shift(clip, times, values, stride(interpolation));
    Channel {
        joint,
        interpolation,
        times,
        output: match component {
            Component::Translation => Output::Translation(values),
            Component::Scale => Output::Scale(values),
        },
    }
}

/// Values per key: three (in-tangent, value, out-tangent) for cubic splines, else one.
fn stride(interpolation: Interpolation) -> usize {
    if interpolation == Interpolation::CubicSpline {
        3
    } else {
        1
    }
}

/// The joint's local transform at clip time `t`, channel maps applied.
fn sample(ch: &JointChannels, t: f32) -> Transform {
    sample_joint(ch, t, &Transform::IDENTITY, &mut [0; 9])
}

/// A cubic track's keys as glTF stores them — `(in-tangent, value, out-tangent)` per key —
/// with values mapped by `value` and tangents by its linear part `tangent`, and a constant
/// key added at a range end the keys do not reach.
fn cubic<T: crate::clip::TrackValue>(
    clip: &Clip,
    track: &Track<T>,
    value: impl Fn(T) -> T,
    tangent: impl Fn(T) -> T,
    zero: T,
) -> (Interpolation, Vec<f32>, Vec<T>) {
    let (first, last) = track.time_range();
    let n = track.times().len();
    let mut times = Vec::with_capacity(n + 2);
    let mut out = Vec::with_capacity(3 * (n + 2));
    let pad_start = first > clip.start();
    let pad_end = last < clip.end();
    if pad_start {
        times.push(clip.start());
        out.extend([zero, value(track.values()[0]), zero]);
    }
    for (k, (&t, (&v, &(m_in, m_out)))) in track
        .times()
        .iter()
        .zip(track.values().iter().zip(track.tangents()))
        .enumerate()
    {
        let m_in = if k == 0 && pad_start {
            zero
        } else {
            tangent(m_in)
        };
        let m_out = if k + 1 == n && pad_end {
            zero
        } else {
            tangent(m_out)
        };
        times.push(t);
        out.extend([m_in, value(v), m_out]);
    }
    if pad_end {
        times.push(clip.end());
        out.extend([zero, value(track.values()[n - 1]), zero]);
    }
    (Interpolation::CubicSpline, times, out)
}

/// `start`, the keys strictly inside the range, `end` (just `start` for a zero-length clip).
fn range_times(clip: &Clip, keys: &[f32]) -> Vec<f32> {
    let (start, end) = (clip.start(), clip.end());
    let mut times = Vec::with_capacity(keys.len() + 2);
    times.push(start);
    times.extend(keys.iter().copied().filter(|&t| t > start && t < end));
    if end > start {
        times.push(end);
    }
    times
}

/// A uniform grid at [`RESAMPLE_RATE`] or a little faster, so that it lands on `start` and
/// `end`, merged with `keys` inside the range; keys closer than [`MIN_KEY_GAP`] merged.
fn resample_times(clip: &Clip, keys: &[f32]) -> Vec<f32> {
    let (start, end) = (f64::from(clip.start()), f64::from(clip.end()));
    let duration = end - start;
    let steps = (duration * RESAMPLE_RATE).ceil().max(1.0) as usize;
    let mut times: Vec<f32> = (0..=steps)
        .map(|i| (start + duration * i as f64 / steps as f64) as f32)
        .chain(
            keys.iter()
                .copied()
                .filter(|&t| t > clip.start() && t < clip.end()),
        )
        .collect();
    times.sort_by(f32::total_cmp);
    let mut kept: Vec<f32> = Vec::with_capacity(times.len());
    for t in times {
        match kept.last() {
            Some(&last) if t - last < MIN_KEY_GAP => {
                // Keep the range's end exactly.
                if t == clip.end()
                    && let Some(l) = kept.last_mut()
                {
                    *l = t;
                }
            }
            _ => kept.push(t),
        }
    }
    kept
}

/// Clip times as animation times (`t − start`) with their values (`stride` per key). Where
/// the subtraction rounds two neighbouring keys to one time, the later is dropped, so times
/// stay strictly increasing.
fn shift<T>(clip: &Clip, times: Vec<f32>, values: Vec<T>, stride: usize) -> (Vec<f32>, Vec<T>) {
    let start = clip.start();
    let mut out_times: Vec<f32> = Vec::with_capacity(times.len());
    let mut out_values = Vec::with_capacity(values.len());
    let mut values = values.into_iter();
    for t in times {
        let t = (t - start).max(0.0);
        let key = values.by_ref().take(stride);
        if out_times.last().is_some_and(|&last| t <= last) {
            key.for_each(drop);
            continue;
        }
        out_times.push(t);
        out_values.extend(key);
    }
    (out_times, out_values)
}

/// Makes step and linear rotation keys continuous in sign: `q_k` is negated when
/// `q_{k−1} · q_k < 0` (the same rotation). Cubic splines are left alone: negating one key
/// would change the spline between it and its neighbours.
fn align_hemispheres(values: &mut [Quat], interpolation: Interpolation) {
    if interpolation == Interpolation::CubicSpline {
        return;
    }
    for k in 1..values.len() {
        if values[k - 1].dot(values[k]) < 0.0 {
            values[k] = -values[k];
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::clip::{ChannelMap, Curve, Extrapolation, Key, Tangent};
    use crate::export::glb::{Model, write};
    use posecast_proto::testing::skeleton_bound_at_rest;

    /// Radians between two rotations, precise near zero.
    fn angle(a: Quat, b: Quat) -> f32 {
        let d = a.conjugate() * b;
        2.0 * Vec3::new(d.x, d.y, d.z).length().min(1.0).asin()
    }

    fn curve(keys: &[(f32, f32)], extrapolation: Extrapolation) -> Curve {
        let keys: Vec<Key> = keys
            .iter()
            .map(|&(time, value)| Key {
                time,
                value,
                tangent_in: Tangent::Smooth,
                tangent_out: Tangent::Smooth,
            })
            .collect();
        Curve::new(&keys, extrapolation, extrapolation).unwrap()
    }

    /// One joint per channel kind, every joint mapped, playing `[0.5, 2.5]` of keys that
    /// reach beyond it on some tracks and fall short of it on others.
    fn mixed_clip() -> Clip {
        let q = |t: f32| Quat::from_euler(glam::EulerRot::YXZ, 1.3 * t, 0.7 * t.sin(), -0.4 * t);
        let times: Vec<f32> = (0..=12).map(|i| i as f32 * 0.25).collect(); // 0 … 3 s
        let linear = Track::new(
            Interpolation::Linear,
            times.clone(),
            times.iter().map(|&t| q(t)).collect(),
        )
        .unwrap();
        let step = Track::new(
            Interpolation::Step,
            times.clone(),
            times.iter().map(|&t| Vec3::new(t, -t * t, 0.5)).collect(),
        )
        .unwrap();
        // Cubic keys inside the range, so the range ends are padded.
        let cubic_times = vec![1.0, 1.5, 2.0];
        let cubic_values = cubic_times
            .iter()
            .flat_map(|&t| {
                let v = q(t);
                [v * 0.3, v, Quat::from_xyzw(0.1, -0.2, 0.05, 0.0) * t]
            })
            .collect();
        let cubic = Track::new(Interpolation::CubicSpline, cubic_times, cubic_values).unwrap();
        // Cubic keys past the range: resampled.
        let wide_times = vec![0.0, 1.2, 3.0];
        let wide_values = wide_times
            .iter()
            .flat_map(|&t| [Vec3::X, Vec3::new(t, 1.0, -t), Vec3::Z * 2.0])
            .collect();
        let wide = Track::new(Interpolation::CubicSpline, wide_times, wide_values).unwrap();
        // Cubic translation keys exactly on the range.
        let moved_times = vec![0.5, 1.4, 2.5];
        let moved_values = moved_times
            .iter()
            .flat_map(|&t| {
                [
                    Vec3::new(1.0, -2.0, t),
                    Vec3::new(t, t * t, 0.3),
                    Vec3::Y * t,
                ]
            })
            .collect();
        let moved = Track::new(Interpolation::CubicSpline, moved_times, moved_values).unwrap();
        let euler = Box::new([
            curve(&[(0.0, 0.1), (1.0, 0.9), (2.0, -0.3)], Extrapolation::Cycle),
            curve(&[(0.2, -0.5), (1.7, 0.4)], Extrapolation::Linear),
            curve(&[(0.0, 0.0), (3.0, 2.5)], Extrapolation::Constant),
        ]);
        let curves = Box::new([
            curve(&[(0.0, 0.0), (2.0, 1.0)], Extrapolation::CycleOffset),
            curve(&[(1.0, 0.3)], Extrapolation::Constant),
            curve(
                &[(0.0, 0.2), (0.6, -0.2), (1.9, 0.5)],
                Extrapolation::Bounce,
            ),
        ]);
        let joints = vec![
            JointChannels {
                rotation: Some(RotationChannel::Keys(linear)),
                translation: Some(VectorChannel::Keys(step)),
                ..Default::default()
            },
            JointChannels {
                rotation: Some(RotationChannel::Keys(cubic)),
                translation: Some(VectorChannel::Keys(moved)),
                scale: Some(VectorChannel::Keys(wide)),
                ..Default::default()
            },
            JointChannels {
                rotation: Some(RotationChannel::Euler(euler)),
                translation: Some(VectorChannel::Curves(curves)),
                ..Default::default()
            },
            JointChannels::default(),
        ];
        let mut clip = Clip::new("mixed", joints, Some((0.5, 2.5))).unwrap();
        for j in 0..3 {
            clip.map_joint(
                j,
                ChannelMap {
                    rot_pre: Quat::from_rotation_x(0.3 + j as f32),
                    rot_post: Quat::from_rotation_z(-0.8),
                    trans_rot: Quat::from_rotation_y(0.6),
                    trans_scale: 0.01,
                    trans_offset: Vec3::new(0.0, 1.0, 0.2),
                },
            );
        }
        clip
    }

    fn skeleton() -> posecast_proto::Skeleton {
        let rest = (0..4)
            .map(|j| {
                Transform::from_translation_rotation(
                    Vec3::new(0.1, 0.3 * j as f32, 0.0),
                    Quat::from_rotation_y(0.2 * j as f32),
                )
            })
            .collect();
        skeleton_bound_at_rest(vec![None, Some(0), Some(1), Some(0)], rest)
    }

    #[test]
    fn channels_keep_their_interpolation_where_gltf_can() {
        let a = animation(&mixed_clip(), 4, &[]).unwrap();
        let kinds: Vec<(usize, Interpolation, &str)> = a
            .channels
            .iter()
            .map(|c| {
                let what = match c.output {
                    Output::Translation(_) => "t",
                    Output::Rotation(_) => "r",
                    Output::Scale(_) => "s",
                };
                (c.joint, c.interpolation, what)
            })
            .collect();
        use Interpolation::*;
        assert_eq!(
            kinds,
            [
                (0, Step, "t"),
                (0, Linear, "r"),
                (1, CubicSpline, "t"),
                (1, CubicSpline, "r"),
                (1, Linear, "s"),
                (2, Linear, "t"),
                (2, Linear, "r"),
            ]
        );
        for c in &a.channels {
            assert_eq!(c.times.first(), Some(&0.0), "joint {}", c.joint);
            assert_eq!(c.times.last(), Some(&2.0), "joint {}", c.joint);
        }
        // The linear track: range ends plus its 7 keys inside (0.5, 2.5).
        assert_eq!(a.channels[1].times.len(), 2 + 7);
        // The cubic on the range: its 3 keys; the padded one: 3 keys and 2 pads.
        assert_eq!(a.channels[2].times.len(), 3);
        assert_eq!(a.channels[3].times.len(), 5);
    }

    #[test]
    fn the_written_animation_imports_back_as_the_clip() {
        let clip = mixed_clip();
        let skeleton = skeleton();
        let a = animation(&clip, skeleton.len(), &[]).unwrap();
        let bytes = write(&Model {
            generator: "test",
            name: Some("t"),
            skeleton: &skeleton,
            mesh: None,
            animations: std::slice::from_ref(&a),
        })
        .unwrap();
        let back = crate::import::gltf::from_slice("t.glb", &bytes)
            .unwrap()
            .remove(0);
        let back = &back.clips[0];
        assert_eq!((back.start(), back.end()), (0.0, clip.duration()));
        let rest = skeleton.rest();
        let compare = |tau: f32, joints: &[usize]| {
            let (mut want, mut got) = (rest.to_vec(), rest.to_vec());
            clip.sample(clip.start() + tau, rest, &mut want);
            back.sample(tau, rest, &mut got);
            for &j in joints {
                let (w, g) = (want[j], got[j]);
                assert!(angle(w.rotation, g.rotation) < 2e-5, "joint {j} at {tau}");
                assert!(
                    w.translation.abs_diff_eq(g.translation, 2e-5),
                    "joint {j} at {tau}"
                );
                assert!(w.scale.abs_diff_eq(g.scale, 2e-5), "joint {j} at {tau}");
            }
        };
        // Exact channels (joints 0, 1 rotation; 3 rest) everywhere, off the step keys.
        for i in 0..=400 {
            compare((i as f32 * 0.005 + 0.0013).min(2.0), &[0, 3]);
        }
        let joint1 = |tau| {
            let (mut want, mut got) = (rest.to_vec(), rest.to_vec());
            clip.sample(clip.start() + tau, rest, &mut want);
            back.sample(tau, rest, &mut got);
            (want[1], got[1])
        };
        for i in 0..=400 {
            let (w, g) = joint1(i as f32 * 0.005);
            assert!(angle(w.rotation, g.rotation) < 2e-5, "cubic at {i}");
            assert!(
                w.translation.abs_diff_eq(g.translation, 2e-5),
                "cubic translation at {i}"
            );
        }
        // Resampled channels (joint 1's scale, joint 2) at their keys.
        for c in a.channels.iter().filter(|c| c.joint == 2) {
            for &tau in &c.times {
                compare(tau, &[2]);
            }
        }
        for &tau in &a.channels[4].times {
            let (w, g) = joint1(tau);
            assert!(w.scale.abs_diff_eq(g.scale, 2e-5), "scale at {tau}");
        }
    }

    #[test]
    fn a_clip_without_channels_or_with_too_many_joints_is_refused() {
        let empty = Clip::new("e", vec![JointChannels::default(); 2], Some((0.0, 1.0))).unwrap();
        assert!(matches!(
            animation(&empty, 2, &[]),
            Err(ExportError::NothingAnimated { .. })
        ));
        assert!(matches!(
            animation(&mixed_clip(), 3, &[]),
            Err(ExportError::JointCount { .. })
        ));
    }
}
