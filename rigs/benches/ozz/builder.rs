//! ozz's offline `AnimationBuilder` (`src/animation/offline/animation_builder.cc`), and the
//! `RawAnimation` it reads made from a posecast [`Clip`].
//!
//! No key reduction (ozz's `AnimationOptimizer` is not run): every key of the clip's linear
//! tracks becomes an ozz key at the same time; a constant track, or a joint component the clip
//! does not animate, is one key (the builder then stores it twice, at 0 and at the duration).

use std::collections::BTreeMap;

use glam::{Quat, Vec3, Vec4};
use posecast_proto::Transform;
use posecast_rigs::clip::{Clip, Interpolation, RotationChannel, VectorChannel};

use super::animation::{Animation, Component, Float3Key, QuaternionKey, pack};
use super::simd::float_to_half;

/// `RawAnimation::JointTrack`: keys of one joint, times in seconds from 0.
#[derive(Clone, Debug, Default)]
pub struct RawTrack {
    pub translations: Vec<(f32, Vec3)>,
    pub rotations: Vec<(f32, Quat)>,
    pub scales: Vec<(f32, Vec3)>,
}

/// `RawAnimation`: a duration and one track per joint.
#[derive(Clone, Debug, Default)]
pub struct RawAnimation {
    pub duration: f32,
    pub tracks: Vec<RawTrack>,
}

/// Why a clip cannot be given to the builder.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum BuildError {
    /// ozz keys are linearly interpolated; CSE169 curves, step and cubic tracks are not.
    #[error("joint {joint}: only linear key tracks can be ported to ozz keys")]
    NotLinear { joint: usize },
    /// ozz keys live in `[0, duration]`.
    #[error("joint {joint}: a key lies outside the clip's range")]
    OutsideRange { joint: usize },
    /// `RawAnimation::Validate`: a positive duration, at most `kMaxTracks` tracks.
    #[error("the animation has a zero duration or too many tracks")]
    Invalid,
}

/// Key times of a channel, or `None` for a constant one.
fn rotation_times(c: &RotationChannel, joint: usize) -> Result<Option<&[f32]>, BuildError> {
    match c {
        RotationChannel::Keys(t) if t.is_constant() => Ok(None),
        RotationChannel::Keys(t) if t.interpolation() == Interpolation::Linear => {
            Ok(Some(t.times()))
        }
        _ => Err(BuildError::NotLinear { joint }),
    }
}

fn vector_times(c: &VectorChannel, joint: usize) -> Result<Option<&[f32]>, BuildError> {
    match c {
        VectorChannel::Keys(t) if t.is_constant() => Ok(None),
        VectorChannel::Keys(t) if t.interpolation() == Interpolation::Linear => Ok(Some(t.times())),
        _ => Err(BuildError::NotLinear { joint }),
    }
}

/// The raw animation of `clip` over a skeleton whose rest pose is `rest`: key values are what
/// [`Clip::sample`] gives at the key times (so channel maps are baked in), times are shifted
/// so the clip starts at 0.
pub fn raw_from_clip(clip: &Clip, rest: &[Transform]) -> Result<RawAnimation, BuildError> {
    let (start, end) = (clip.start(), clip.end());
    // Per joint and component: the key times, None when constant.
    let mut times: Vec<[Option<&[f32]>; 3]> = Vec::with_capacity(rest.len());
    for j in 0..rest.len() {
        let ch = clip.channels().get(j);
        let r = match ch.and_then(|c| c.rotation.as_ref()) {
            Some(c) => rotation_times(c, j)?,
            None => None,
        };
        let t = match ch.and_then(|c| c.translation.as_ref()) {
            Some(c) => vector_times(c, j)?,
            None => None,
        };
        let s = match ch.and_then(|c| c.scale.as_ref()) {
            Some(c) => vector_times(c, j)?,
            None => None,
        };
        for k in [r, t, s].into_iter().flatten() {
            if k.iter().any(|&x| x < start || x > end) {
                return Err(BuildError::OutsideRange { joint: j });
            }
        }
        times.push([r, t, s]);
    }
    // One pose per distinct key time (times are ≥ 0 here or the range check refused them, so
    // the bit patterns order like the values).
    let mut poses: BTreeMap<u32, Vec<Transform>> = BTreeMap::new();
    let mut pose_at = |t: f32| -> Vec<Transform> {
        poses
            .entry(t.to_bits())
            .or_insert_with(|| {
                let mut out = rest.to_vec();
                clip.sample(t, rest, &mut out);
                out
            })
            .clone()
    };
    let first = pose_at(start);
    let mut tracks = Vec::with_capacity(rest.len());
    for (j, [r, t, s]) in times.iter().enumerate() {
        let mut track = RawTrack::default();
        match r {
            Some(ts) => {
                for &x in *ts {
                    track.rotations.push((x - start, pose_at(x)[j].rotation));
                }
            }
            None => track.rotations.push((0.0, first[j].rotation)),
        }
        match t {
            Some(ts) => {
                for &x in *ts {
                    track
                        .translations
                        .push((x - start, pose_at(x)[j].translation));
                }
            }
            None => track.translations.push((0.0, first[j].translation)),
        }
        match s {
            Some(ts) => {
                for &x in *ts {
                    track.scales.push((x - start, pose_at(x)[j].scale));
                }
            }
            None => track.scales.push((0.0, first[j].scale)),
        }
        tracks.push(track);
    }
    Ok(RawAnimation {
        duration: end - start,
        tracks,
    })
}

/// `kMaxPreviousOffset`: offsets to the previous key are stored on 16 bits.
const MAX_PREVIOUS_OFFSET: usize = (1 << 16) - 1;

/// `SortingKey`: a key, its track, and the time of the previous key of its track (−1 for the
/// first), which is when sampling first needs it.
#[derive(Clone, Copy, Debug)]
struct SortingKey<V> {
    track: u16,
    prev_key_time: f32,
    time: f32,
    value: V,
}

/// `SortingKeyLess`: by previous key time, then track.
fn sorting_key_less<V>(l: &SortingKey<V>, r: &SortingKey<V>) -> bool {
    let time_diff = l.prev_key_time - r.prev_key_time;
    time_diff < 0.0 || (time_diff == 0.0 && l.track < r.track)
}

fn ordering<V>(l: &SortingKey<V>, r: &SortingKey<V>) -> std::cmp::Ordering {
    if sorting_key_less(l, r) {
        std::cmp::Ordering::Less
    } else if sorting_key_less(r, l) {
        std::cmp::Ordering::Greater
    } else {
        std::cmp::Ordering::Equal
    }
}

/// `PushBackIdentityKey`.
fn push_back_identity_key<V: Copy>(
    track: u16,
    time: f32,
    identity: V,
    dest: &mut Vec<SortingKey<V>>,
) {
    let prev_key_time = match dest.last() {
        Some(k) if k.track == track => k.time,
        _ => -1.0,
    };
    dest.push(SortingKey {
        track,
        prev_key_time,
        time,
        value: identity,
    });
}

/// `CopyRaw`: copies a track, adding keys at 0 and at `duration` where missing.
fn copy_raw<V: Copy>(
    src: &[(f32, V)],
    track: u16,
    duration: f32,
    identity: V,
    dest: &mut Vec<SortingKey<V>>,
) {
    let key = |prev_key_time, time, value| SortingKey {
        track,
        prev_key_time,
        time,
        value,
    };
    match src {
        [] => {
            push_back_identity_key(track, 0.0, identity, dest);
            push_back_identity_key(track, duration, identity, dest);
        }
        [(_, v)] => {
            dest.push(key(-1.0, 0.0, *v));
            dest.push(key(0.0, duration, *v));
        }
        [(t0, v0), .., (tn, vn)] => {
            let mut prev_time = -1.0;
            if *t0 != 0.0 {
                dest.push(key(prev_time, 0.0, *v0));
                prev_time = 0.0;
            }
            for &(t, v) in src {
                dest.push(key(prev_time, t, v));
                prev_time = t;
            }
            if *tn - duration != 0.0 {
                dest.push(key(prev_time, duration, *vn));
            }
        }
    }
}

/// `Sort`: sorts keys, then inserts a key wherever a track's previous key would be more than
/// `kMaxPreviousOffset` keys back.
fn sort<V: Copy>(src: &mut Vec<SortingKey<V>>, num_tracks: usize, lerp: fn(V, V, f32) -> V) {
    src.sort_by(ordering);
    let mut previouses: Vec<(isize, isize)> = vec![(-1, -1); num_tracks];
    let mut again = true;
    while again {
        again = false;
        previouses.fill((-1, -1));
        for i in 0..src.len() {
            let track = src[i].track;
            let previous = &mut previouses[usize::from(track)];
            if previous.0 != -1 && i - previous.0 as usize > MAX_PREVIOUS_OFFSET {
                let (first, second) = (previous.0 as usize, previous.1 as usize);
                let mut last = src[first];
                let penultimate = src[second];
                let insert = SortingKey {
                    track,
                    prev_key_time: penultimate.time,
                    time: (penultimate.time + last.time) * 0.5,
                    value: lerp(penultimate.value, last.value, 0.5),
                };
                src.remove(first);
                src.push(insert);
                last.prev_key_time = insert.time;
                src.push(last);
                // `std::inplace_merge` of the two pushed keys into the sorted run.
                src[second..].sort_by(ordering);
                again = true;
                break;
            }
            previous.1 = previous.0;
            previous.0 = i as isize;
        }
    }
}

/// `NormalizeSafe(Quaternion)`.
fn normalize_safe(q: Quat, safe: Quat) -> Quat {
    let sq_len = q.length_squared();
    if sq_len == 0.0 {
        safe
    } else {
        q * (1.0 / sq_len.sqrt())
    }
}

/// `FixupQuaternions`: normalises, puts a track's first key in the `w ≥ 0` hemisphere and each
/// next key in the hemisphere of the one before, so `NLerp` takes the short path.
fn fixup_quaternions(src: &mut [SortingKey<Quat>]) {
    let mut track = usize::MAX;
    for i in 0..src.len() {
        let mut normalized = normalize_safe(src[i].value, Quat::IDENTITY);
        if track != usize::from(src[i].track) {
            if normalized.w < 0.0 {
                normalized = -normalized;
            }
        } else {
            let prev = Vec4::from(src[i - 1].value);
            if prev.dot(Vec4::from(normalized)) < 0.0 {
                normalized = -normalized;
            }
        }
        src[i].value = normalized;
        track = usize::from(src[i].track);
    }
}

/// `BuildTimePoints`: every distinct key time, sorted.
fn build_time_points(
    t: &[SortingKey<Vec3>],
    r: &[SortingKey<Quat>],
    s: &[SortingKey<Vec3>],
) -> Vec<f32> {
    let mut points: Vec<f32> = t.iter().map(|k| k.time).collect();
    points.extend(r.iter().map(|k| k.time));
    points.extend(s.iter().map(|k| k.time));
    points.sort_by(f32::total_cmp);
    points.dedup();
    points
}

/// `TimePointToIndex`.
fn time_point_to_index(points: &[f32], time: f32) -> u16 {
    let found = points
        .iter()
        .position(|&p| p == time)
        .unwrap_or(points.len());
    debug_assert!(found < points.len());
    found as u16
}

/// `CopyToAnimation`: time point indices, offsets to the previous key, compressed values.
fn copy_to_animation<V: Copy, K: Copy + Default>(
    points: &[f32],
    src: &[SortingKey<V>],
    num_tracks: usize,
    compress: fn(V) -> K,
) -> Component<K> {
    let wide = points.len() > usize::from(u8::MAX);
    let mut dest = Component {
        ratios: Vec::with_capacity(src.len() * if wide { 2 } else { 1 }),
        previouses: Vec::with_capacity(src.len()),
        values: Vec::with_capacity(src.len()),
    };
    let mut previouses: Vec<Option<usize>> = vec![None; num_tracks];
    for (i, key) in src.iter().enumerate() {
        let ratio = time_point_to_index(points, key.time);
        if wide {
            dest.ratios.extend_from_slice(&ratio.to_le_bytes());
        } else {
            dest.ratios.push(ratio as u8);
        }
        let track = usize::from(key.track);
        let diff = previouses[track].map_or(0, |p| i - p);
        debug_assert!(diff < MAX_PREVIOUS_OFFSET);
        dest.previouses.push(diff as u16);
        dest.values.push(compress(key.value));
        previouses[track] = Some(i);
    }
    dest
}

/// `CompressFloat3`: three half floats.
fn compress_float3(v: Vec3) -> Float3Key {
    Float3Key {
        values: [float_to_half(v.x), float_to_half(v.y), float_to_half(v.z)],
    }
}

/// `kSqrt2` and `kSqrt2_2` of `math_constant.h`.
pub const SQRT2: f32 = std::f32::consts::SQRT_2;
pub const SQRT2_2: f32 = std::f32::consts::FRAC_1_SQRT_2;

/// `CompressQuaternion`: the largest component is dropped (its index and sign kept), the three
/// others quantised on 15 bits over `[−√2/2, √2/2]`.
fn compress_quaternion(q: Quat) -> QuaternionKey {
    let quat = [q.x, q.y, q.z, q.w];
    // `std::max_element` with `LessAbs`: the first of the largest magnitudes.
    let mut largest = 0;
    for i in 1..4 {
        if quat[largest].abs() < quat[i].abs() {
            largest = i;
        }
    }
    let scale = QuaternionKey::F_SCALE / SQRT2;
    let offset = -SQRT2_2;
    const MAPPING: [[usize; 3]; 4] = [[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]];
    let map = MAPPING[largest];
    let q = |k: usize| (((quat[map[k]] - offset) * scale + 0.5) as i32).min(QuaternionKey::I_SCALE);
    pack(
        largest as i32,
        i32::from(quat[largest] < 0.0),
        [q(0), q(1), q(2)],
    )
}

fn lerp_vec3(a: Vec3, b: Vec3, f: f32) -> Vec3 {
    a.lerp(b, f)
}

/// `LerpRotation`: normalised lerp.
fn nlerp_quat(a: Quat, b: Quat, f: f32) -> Quat {
    Quat::from_vec4(Vec4::from(a).lerp(Vec4::from(b), f)).normalize()
}

/// `kMaxTracks` of `Skeleton`.
const MAX_TRACKS: usize = 1024;

/// `AnimationBuilder::operator()`.
pub fn build(input: &RawAnimation) -> Result<Animation, BuildError> {
    if input.duration.is_nan() || input.duration <= 0.0 || input.tracks.len() > MAX_TRACKS {
        return Err(BuildError::Invalid);
    }
    let duration = input.duration;
    let inv_duration = 1.0 / duration;
    let num_tracks = input.tracks.len();
    let num_soa_tracks = num_tracks.div_ceil(4) * 4;

    let mut translations = Vec::new();
    let mut rotations = Vec::new();
    let mut scales = Vec::new();
    for (i, raw) in input.tracks.iter().enumerate() {
        let i = i as u16;
        copy_raw(
            &raw.translations,
            i,
            duration,
            Vec3::ZERO,
            &mut translations,
        );
        copy_raw(&raw.rotations, i, duration, Quat::IDENTITY, &mut rotations);
        copy_raw(&raw.scales, i, duration, Vec3::ONE, &mut scales);
    }
    for i in num_tracks..num_soa_tracks {
        let i = i as u16;
        push_back_identity_key(i, 0.0, Vec3::ZERO, &mut translations);
        push_back_identity_key(i, duration, Vec3::ZERO, &mut translations);
        push_back_identity_key(i, 0.0, Quat::IDENTITY, &mut rotations);
        push_back_identity_key(i, duration, Quat::IDENTITY, &mut rotations);
        push_back_identity_key(i, 0.0, Vec3::ONE, &mut scales);
        push_back_identity_key(i, duration, Vec3::ONE, &mut scales);
    }

    fixup_quaternions(&mut rotations);

    sort(&mut translations, num_soa_tracks, lerp_vec3);
    sort(&mut rotations, num_soa_tracks, nlerp_quat);
    sort(&mut scales, num_soa_tracks, lerp_vec3);

    let points = build_time_points(&translations, &rotations, &scales);
    if points.len() >= usize::from(u16::MAX) {
        return Err(BuildError::Invalid);
    }
    let translations = copy_to_animation(&points, &translations, num_soa_tracks, compress_float3);
    let rotations = copy_to_animation(&points, &rotations, num_soa_tracks, compress_quaternion);
    let scales = copy_to_animation(&points, &scales, num_soa_tracks, compress_float3);
    Ok(Animation {
        duration,
        num_tracks,
        timepoints: points.iter().map(|t| t * inv_duration).collect(),
        translations,
        rotations,
        scales,
    })
}
