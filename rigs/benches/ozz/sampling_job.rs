//! ozz's `SamplingJob` and its `Context` (`src/animation/runtime/sampling_job.cc`,
//! `include/ozz/animation/runtime/sampling_job.h`).
//!
//! The context caches, per track, the indices of the two keys around the last sampled time
//! (the "penultimate" and "last" entries) and their decompressed SoA values. A cursor walks the
//! time-sorted key array forwards (or back, when rewinding); each key it passes replaces the
//! cache entry of its track and flags that track's SoA group outdated, and only outdated groups
//! are decompressed again. Interpolation is then SoA: four tracks per lane set.

use super::simd::sse::{
    __m128, __m128i, _mm_add_ps, _mm_and_ps, _mm_andnot_ps, _mm_castsi128_ps, _mm_cvtepi32_ps,
    _mm_mul_ps, _mm_or_ps, _mm_set_ps1, _mm_setr_epi32, _mm_slli_epi32, _mm_sub_ps,
};

use glam::Vec4;

use super::animation::{Animation, Component, Float3Key, QuaternionKey, unpack};
use super::builder::{SQRT2, SQRT2_2};
use super::simd::{
    SoaFloat3, SoaQuaternion, SoaTransform, half_to_float, lerp3, nlerp_est, rcp_est, rsqrt_est,
};

/// `internal::InterpSoaFloat3`: the two keys around the sampled time, SoA.
#[derive(Clone, Copy, Debug)]
struct InterpSoaFloat3 {
    ratio: [Vec4; 2],
    value: [SoaFloat3; 2],
}

/// `internal::InterpSoaQuaternion`.
#[derive(Clone, Copy, Debug)]
struct InterpSoaQuaternion {
    ratio: [Vec4; 2],
    value: [SoaQuaternion; 2],
}

const ZERO3: SoaFloat3 = SoaFloat3 {
    x: Vec4::ZERO,
    y: Vec4::ZERO,
    z: Vec4::ZERO,
};
const ZEROQ: SoaQuaternion = SoaQuaternion {
    x: Vec4::ZERO,
    y: Vec4::ZERO,
    z: Vec4::ZERO,
    w: Vec4::ZERO,
};

/// `SamplingJob::Context`: the sampling cache of one animation instance.
#[derive(Clone, Debug)]
pub struct Context {
    max_soa_tracks: usize,
    soa_translations: Vec<InterpSoaFloat3>,
    soa_rotations: Vec<InterpSoaQuaternion>,
    soa_scales: Vec<InterpSoaFloat3>,
    translation_cache: Vec<i32>,
    rotation_cache: Vec<i32>,
    scale_cache: Vec<i32>,
    outdated_translations: Vec<u8>,
    outdated_rotations: Vec<u8>,
    outdated_scales: Vec<u8>,
    /// The animation last sampled (its address; 0 for none).
    animation: usize,
    ratio: f32,
    translation_cursor: usize,
    rotation_cursor: usize,
    scale_cursor: usize,
}

impl Context {
    /// `Context(int _max_tracks)` / `Resize`.
    #[must_use]
    pub fn new(max_tracks: usize) -> Self {
        let max_soa_tracks = max_tracks.div_ceil(4);
        let tracks = max_soa_tracks * 4;
        let num_outdated = max_soa_tracks.div_ceil(8);
        let f3 = InterpSoaFloat3 {
            ratio: [Vec4::ZERO; 2],
            value: [ZERO3; 2],
        };
        Self {
            max_soa_tracks,
            soa_translations: vec![f3; max_soa_tracks],
            soa_rotations: vec![
                InterpSoaQuaternion {
                    ratio: [Vec4::ZERO; 2],
                    value: [ZEROQ; 2],
                };
                max_soa_tracks
            ],
            soa_scales: vec![f3; max_soa_tracks],
            translation_cache: vec![0; tracks * 2],
            rotation_cache: vec![0; tracks * 2],
            scale_cache: vec![0; tracks * 2],
            outdated_translations: vec![0; num_outdated],
            outdated_rotations: vec![0; num_outdated],
            outdated_scales: vec![0; num_outdated],
            animation: 0,
            ratio: 0.0,
            translation_cursor: 0,
            rotation_cursor: 0,
            scale_cursor: 0,
        }
    }

    /// `Step`: invalidates the cache for another animation, or when rewinding further back
    /// than restarting would cost ("restart is worth 5% of seek time").
    fn step(&mut self, animation: &Animation, ratio: f32) {
        let id = std::ptr::from_ref(animation) as usize;
        let changed = self.animation != id;
        const RESTART_OVERHEAD: f32 = 0.05;
        let restart = self.ratio > RESTART_OVERHEAD && self.ratio - ratio > ratio;
        if changed || restart {
            self.animation = id;
            self.translation_cursor = 0;
            self.rotation_cursor = 0;
            self.scale_cursor = 0;
        }
        self.ratio = ratio;
    }
}

/// `TrackForward`: the track of key `key`, found as the cache entry holding its previous key,
/// searching from the last track found.
#[inline(always)]
fn track_forward(
    cache: &[i32],
    previouses: &[u16],
    key: usize,
    last_track: usize,
    num_tracks: usize,
) -> usize {
    let target = (key - usize::from(previouses[key])) as i32;
    for entry in last_track + num_tracks..num_tracks * 2 {
        if cache[entry] == target {
            return entry - num_tracks;
        }
    }
    for entry in num_tracks..num_tracks * 2 {
        if cache[entry] == target {
            return entry - num_tracks;
        }
    }
    unreachable!("previous track should be in cache")
}

/// `TrackBackward`.
#[inline(always)]
fn track_backward(cache: &[i32], target: i32, last_track: usize, num_tracks: usize) -> usize {
    for entry in (num_tracks..=last_track + num_tracks).rev() {
        if cache[entry] == target {
            return entry - num_tracks;
        }
    }
    for entry in (last_track + num_tracks + 1..num_tracks * 2).rev() {
        if cache[entry] == target {
            return entry - num_tracks;
        }
    }
    unreachable!("previous track should be in cache")
}

/// `TimePoint`: the ratio of key `at`.
#[inline(always)]
fn time_point(timepoints: &[f32], ratios: &[u8], at: usize) -> f32 {
    if timepoints.len() <= usize::from(u8::MAX) {
        timepoints[usize::from(ratios[at])]
    } else {
        timepoints[usize::from(u16::from_le_bytes([ratios[2 * at], ratios[2 * at + 1]]))]
    }
}

/// `TimePoints`: the ratios of four keys.
#[inline(always)]
fn time_points(timepoints: &[f32], ratios: &[u8], ats: &[i32]) -> Vec4 {
    let at = |k: usize| time_point(timepoints, ratios, ats[k] as usize);
    Vec4::new(at(0), at(1), at(2), at(3))
}

/// `UpdateCacheCursor`: moves the cursor to `ratio`, updating the cache entries of every key
/// passed and flagging their SoA groups outdated.
fn update_cache_cursor(
    ratio: f32,
    num_soa_tracks: usize,
    timepoints: &[f32],
    ratios: &[u8],
    previouses: &[u16],
    cursor_io: &mut usize,
    cache: &mut [i32],
    outdated: &mut [u8],
) {
    let num_tracks = num_soa_tracks * 4;
    let num_keys = previouses.len();
    let mut cursor = *cursor_io;
    if cursor == 0 {
        // The first two keys of every track are the first `2 · num_tracks` keys, in track order.
        while cursor < num_tracks * 2 {
            cache[cursor] = cursor as i32;
            cursor += 1;
        }
        let num_outdated_flags = num_soa_tracks.div_ceil(8);
        for o in &mut outdated[..num_outdated_flags - 1] {
            *o = 0xff;
        }
        outdated[num_outdated_flags - 1] = 0xff >> (num_outdated_flags * 8 - num_soa_tracks);
    }

    // Forwards: until a key is first needed after `ratio`; the sorting makes every key before
    // it already processed.
    let mut track = 0;
    while cursor < num_keys
        && time_point(timepoints, ratios, cursor - usize::from(previouses[cursor])) <= ratio
    {
        track = track_forward(cache, previouses, cursor, track, num_tracks);
        outdated[track / 32] |= 1 << ((track & 0x1f) / 4);
        let penultimate = track;
        let last = track + num_tracks;
        cache[penultimate] = cache[last];
        cache[last] = cursor as i32;
        cursor += 1;
    }

    // Rewinds while the penultimate key is after `ratio`.
    while time_point(
        timepoints,
        ratios,
        (cursor - 1) - usize::from(previouses[cursor - 1]),
    ) > ratio
    {
        track = track_backward(cache, (cursor - 1) as i32, track, num_tracks);
        outdated[track / 32] |= 1 << ((track & 0x1f) / 4);
        let penultimate = track;
        let last = track + num_tracks;
        cache[last] = cache[penultimate];
        let previous = i32::from(previouses[cache[penultimate] as usize]);
        cache[penultimate] -= previous;
        cursor -= 1;
    }
    *cursor_io = cursor;
}

/// The left (penultimate) and right (last) interpolation keys of one SoA group.
trait Interp: Copy {
    type Key: Copy;
    type Soa;
    fn set(&mut self, side: usize, ratio: Vec4, value: Self::Soa);
    fn decompress(k: [&Self::Key; 4]) -> Self::Soa;
}

impl Interp for InterpSoaFloat3 {
    type Key = Float3Key;
    type Soa = SoaFloat3;
    #[inline(always)]
    fn set(&mut self, side: usize, ratio: Vec4, value: SoaFloat3) {
        self.ratio[side] = ratio;
        self.value[side] = value;
    }
    #[inline(always)]
    fn decompress(k: [&Float3Key; 4]) -> SoaFloat3 {
        decompress_float3(k)
    }
}

impl Interp for InterpSoaQuaternion {
    type Key = QuaternionKey;
    type Soa = SoaQuaternion;
    #[inline(always)]
    fn set(&mut self, side: usize, ratio: Vec4, value: SoaQuaternion) {
        self.ratio[side] = ratio;
        self.value[side] = value;
    }
    #[inline(always)]
    fn decompress(k: [&QuaternionKey; 4]) -> SoaQuaternion {
        decompress_quaternion(k)
    }
}

/// `UpdateInterpKeyframes`: decompresses both keys of every outdated SoA group.
fn update_interp_keyframes<I: Interp>(
    num_soa_tracks: usize,
    timepoints: &[f32],
    keys: &Component<I::Key>,
    cache: &[i32],
    outdated: &mut [u8],
    interp: &mut [I],
) {
    let num_outdated_flags = num_soa_tracks.div_ceil(8);
    for j in 0..num_outdated_flags {
        let mut flags = outdated[j];
        outdated[j] = 0;
        let mut i = j * 8;
        while flags != 0 {
            if flags & 1 != 0 {
                let cached_p = &cache[i * 4..i * 4 + 4];
                let v = |k: usize| &keys.values[cached_p[k] as usize];
                interp[i].set(
                    0,
                    time_points(timepoints, &keys.ratios, cached_p),
                    I::decompress([v(0), v(1), v(2), v(3)]),
                );
                let lasts = (i + num_soa_tracks) * 4;
                let cached_l = &cache[lasts..lasts + 4];
                let v = |k: usize| &keys.values[cached_l[k] as usize];
                interp[i].set(
                    1,
                    time_points(timepoints, &keys.ratios, cached_l),
                    I::decompress([v(0), v(1), v(2), v(3)]),
                );
            }
            i += 1;
            flags >>= 1;
        }
    }
}

/// `simd_int4::Load(a, b, c, d)`.
#[inline(always)]
fn load_i(a: i32, b: i32, c: i32, d: i32) -> __m128i {
    _mm_setr_epi32(a, b, c, d)
}

/// `DecompressFloat3`.
#[inline(always)]
fn decompress_float3(k: [&Float3Key; 4]) -> SoaFloat3 {
    let lane = |c: usize| {
        load_i(
            i32::from(k[0].values[c]),
            i32::from(k[1].values[c]),
            i32::from(k[2].values[c]),
            i32::from(k[3].values[c]),
        )
    };
    SoaFloat3 {
        x: half_to_float(lane(0)),
        y: half_to_float(lane(1)),
        z: half_to_float(lane(2)),
    }
}

/// `kCpntMapping`: for each largest-component index, where each output component is read from
/// the three stored values (the largest's own slot reads a dummy, zeroed below).
const CPNT_MAPPING: [[usize; 4]; 4] = [[0, 0, 1, 2], [0, 0, 1, 2], [0, 1, 0, 2], [0, 1, 2, 0]];

/// `DecompressQuaternion`: rebuilds four quaternions from their three stored components, the
/// largest as `√(1 − a² − b² − c²)` (with `x · RSqrtEst(x)`, as ozz) and its stored sign.
#[inline(always)]
fn decompress_quaternion(k: [&QuaternionKey; 4]) -> SoaQuaternion {
    let (l0, s0, v0) = unpack(k[0]);
    let (l1, s1, v1) = unpack(k[1]);
    let (l2, s2, v2) = unpack(k[2]);
    let (l3, s3, v3) = unpack(k[3]);
    let largests = [l0, l1, l2, l3];
    let (m0, m1, m2, m3) = (
        &CPNT_MAPPING[l0],
        &CPNT_MAPPING[l1],
        &CPNT_MAPPING[l2],
        &CPNT_MAPPING[l3],
    );
    let cmp = |c: usize| load_i(v0[m0[c]], v1[m1[c]], v2[m2[c]], v3[m3[c]]);

    let scale = _mm_set_ps1(SQRT2 / QuaternionKey::F_SCALE);
    let offset = _mm_set_ps1(-SQRT2_2);
    let from = |c: usize| _mm_add_ps(_mm_mul_ps(scale, _mm_cvtepi32_ps(cmp(c))), offset);
    let mut cpnt: [__m128; 4] = [from(0), from(1), from(2), from(3)];

    let mask = |lane: usize| -> __m128 {
        let mut m = [0i32; 4];
        m[lane] = -1;
        _mm_castsi128_ps(load_i(m[0], m[1], m[2], m[3]))
    };
    let masks = [mask(0), mask(1), mask(2), mask(3)];
    // Zeroes the largest components so they are not part of the dot.
    for lane in 0..4 {
        let c = largests[lane];
        cpnt[c] = _mm_andnot_ps(masks[lane], cpnt[c]);
    }
    let dot = _mm_add_ps(
        _mm_add_ps(
            _mm_add_ps(_mm_mul_ps(cpnt[0], cpnt[0]), _mm_mul_ps(cpnt[1], cpnt[1])),
            _mm_mul_ps(cpnt[2], cpnt[2]),
        ),
        _mm_mul_ps(cpnt[3], cpnt[3]),
    );
    let ww0 = _mm_sub_ps(_mm_set_ps1(1.0), dot);
    let w0: __m128 = (Vec4::from(ww0) * rsqrt_est(Vec4::from(ww0))).into();
    let sign = _mm_slli_epi32::<31>(load_i(s0, s1, s2, s3));
    let restored = _mm_or_ps(w0, _mm_castsi128_ps(sign));
    for lane in 0..4 {
        let c = largests[lane];
        cpnt[c] = _mm_or_ps(cpnt[c], _mm_and_ps(restored, masks[lane]));
    }
    SoaQuaternion {
        x: Vec4::from(cpnt[0]),
        y: Vec4::from(cpnt[1]),
        z: Vec4::from(cpnt[2]),
        w: Vec4::from(cpnt[3]),
    }
}

/// `Interpolates`: SoA lerp of translations and scales, `NLerpEst` of rotations, with the
/// interpolation coefficient `(r − r₀) · RcpEst(r₁ − r₀)`.
fn interpolates(
    anim_ratio: f32,
    num_soa_tracks: usize,
    translations: &[InterpSoaFloat3],
    rotations: &[InterpSoaQuaternion],
    scales: &[InterpSoaFloat3],
    output: &mut [SoaTransform],
) {
    let anim_ratio = Vec4::splat(anim_ratio);
    for ((((t, r), s), o), _) in translations
        .iter()
        .zip(rotations)
        .zip(scales)
        .zip(output.iter_mut())
        .zip(0..num_soa_tracks)
    {
        let interp_t = (anim_ratio - t.ratio[0]) * rcp_est(t.ratio[1] - t.ratio[0]);
        let interp_r = (anim_ratio - r.ratio[0]) * rcp_est(r.ratio[1] - r.ratio[0]);
        let interp_s = (anim_ratio - s.ratio[0]) * rcp_est(s.ratio[1] - s.ratio[0]);
        o.translation = lerp3(&t.value[0], &t.value[1], interp_t);
        o.rotation = nlerp_est(&r.value[0], &r.value[1], interp_r);
        o.scale = lerp3(&s.value[0], &s.value[1], interp_s);
    }
}

/// `SamplingJob::Run`: samples `animation` at `ratio` (of its duration, clamped to `[0, 1]`)
/// into `output` (one [`SoaTransform`] per four tracks). False when a buffer is too small
/// (`Validate`).
pub fn run(
    animation: &Animation,
    ratio: f32,
    context: &mut Context,
    output: &mut [SoaTransform],
) -> bool {
    let num_soa_tracks = animation.num_soa_tracks();
    if output.is_empty() || output.len() < num_soa_tracks || context.max_soa_tracks < num_soa_tracks
    {
        return false;
    }
    if num_soa_tracks == 0 {
        return true;
    }
    // `math::Clamp(0, ratio, 1)`, which maps NaN to 1 (`f32::clamp` would keep it).
    #[allow(clippy::manual_clamp)]
    let anim_ratio = ratio.min(1.0).max(0.0);
    context.step(animation, anim_ratio);

    let tp = &animation.timepoints;
    let t = &animation.translations;
    update_cache_cursor(
        anim_ratio,
        num_soa_tracks,
        tp,
        &t.ratios,
        &t.previouses,
        &mut context.translation_cursor,
        &mut context.translation_cache,
        &mut context.outdated_translations,
    );
    update_interp_keyframes(
        num_soa_tracks,
        tp,
        t,
        &context.translation_cache,
        &mut context.outdated_translations,
        &mut context.soa_translations,
    );
    let r = &animation.rotations;
    update_cache_cursor(
        anim_ratio,
        num_soa_tracks,
        tp,
        &r.ratios,
        &r.previouses,
        &mut context.rotation_cursor,
        &mut context.rotation_cache,
        &mut context.outdated_rotations,
    );
    update_interp_keyframes(
        num_soa_tracks,
        tp,
        r,
        &context.rotation_cache,
        &mut context.outdated_rotations,
        &mut context.soa_rotations,
    );
    let s = &animation.scales;
    update_cache_cursor(
        anim_ratio,
        num_soa_tracks,
        tp,
        &s.ratios,
        &s.previouses,
        &mut context.scale_cursor,
        &mut context.scale_cache,
        &mut context.outdated_scales,
    );
    update_interp_keyframes(
        num_soa_tracks,
        tp,
        s,
        &context.scale_cache,
        &mut context.outdated_scales,
        &mut context.soa_scales,
    );

    interpolates(
        anim_ratio,
        num_soa_tracks,
        &context.soa_translations,
        &context.soa_rotations,
        &context.soa_scales,
        output,
    );
    true
}
