//! A clip on its skeleton as Biovision hierarchy (`.bvh`) text, readable by Blender,
//! MotionBuilder and the server's own importer ([`crate::import::bvh`]).
//!
//! Conventions chosen, since BVH fixes none of them:
//! - **Units: centimetres.** BVH has no unit field; MotionBuilder, Maya and most motion-capture
//!   libraries (the CMU conversions among them) write centimetres, and the server's importer
//!   guesses centimetres for a 30–300-unit-tall rig. Offsets and positions are the rig's metres
//!   × [`CENTIMETRES_PER_METRE`] (in Blender, import with scale 0.01 for metres).
//! - **Rotations: `Zrotation Yrotation Xrotation`, degrees**, applied in the order listed:
//!   `R = R_z(z) · R_y(y) · R_x(x)` — the order of the CMU files. Its gimbal lock is at a 90°
//!   turn about Y, the axis limbs twist about in a Y-up rig, rarely reached; ZXY (lock at 90°
//!   about X) would lock at every right-angled knee or elbow flexion. Angles are decomposed in
//!   f64 and chosen continuous from frame to frame (no ±180° flips), and written with six
//!   decimals (a micro-degree).
//! - **Rest rotations are baked in.** BVH joints have no rest rotation: a joint's rest pose is
//!   its `OFFSET` with no turn. Each frame's channels therefore carry the joint's full local
//!   rotation — the clip's value, which already includes the rest rotation, or the rest
//!   rotation itself for joints the clip does not animate — so `T(offset) · R_frame` is the
//!   local transform the clip gives, whatever the rig's rest rotations.
//! - **Channels**: six (`Xposition Yposition Zposition` then the rotations) for roots and for
//!   every joint whose translation the clip animates, whose positions replace the `OFFSET`
//!   (the common reading, and the importer's); three rotations for the others.
//! - **Hierarchy**: one `ROOT` block per root (several roots give several blocks), joints
//!   depth-first with children in skeleton order — the skeleton's own order when it is stored
//!   depth-first, as importers store it. A leaf gets an `End Site` continuing its bone by its
//!   own offset (zero for a leaf on its parent), so tools that draw bones to the end site show
//!   it. Names keep everything but whitespace, control characters and braces, which become `_`
//!   (BVH names end at whitespace for most readers).
//! - **Frames**: one per key when the clip's step and linear keys all lie on one uniform grid
//!   (BVH imports, recordings at a tick rate), else sampled at [`RESAMPLE_RATE`] or a little
//!   faster so frames land on the clip's first and last pose. Frame `i` is the clip at
//!   `start + i · frame_time`; the file's time starts at 0.
//! - **Not written**: scale (BVH has no scale channels).

use super::ExportError;
use crate::clip::{Clip, Interpolation, RotationChannel, Track, TrackValue, VectorChannel};
use glam::{DMat3, DQuat, Quat};
use posecast_proto::{Skeleton, Transform};
use std::f64::consts::{PI, TAU};
use std::fmt::Write as _;

/// BVH units per metre (the file is in centimetres).
pub const CENTIMETRES_PER_METRE: f32 = 100.0;

/// Frames per second when the clip's keys are not on one uniform grid.
pub const RESAMPLE_RATE: f64 = 60.0;

/// Most channel values (frames × channels) one file may hold: ~16.8 M, about 200 MB of text.
/// A longer clip is refused rather than building the text in memory.
pub const MAX_VALUES: usize = 1 << 24;

/// A key grid finer than this (seconds) is not taken as the frame time: it would not be a
/// frame rate but a few close keys.
const MIN_FRAME_TIME: f64 = 1e-3;

/// Nesting deeper than this is not indented further (whitespace means nothing in BVH, and a
/// long chain would otherwise make the text quadratic in its length).
const MAX_INDENT: usize = 32;

/// `clip` on `skeleton` as BVH text (see the module documentation for every convention).
/// `frame_time` (seconds) overrides the frame time chosen from the clip.
///
/// # Errors
/// The clip has more joint slots than the skeleton has joints ([`ExportError::JointCount`]),
/// `frame_time` is not a positive finite number ([`ExportError::FrameTime`]), or the file would
/// hold more than [`MAX_VALUES`] values ([`ExportError::TooManyFrames`]).
pub fn write(
    skeleton: &Skeleton,
    clip: &Clip,
    frame_time: Option<f64>,
) -> Result<String, ExportError> {
    if clip.joint_count() > skeleton.len() {
        return Err(ExportError::JointCount {
            clip: clip.name().to_owned(),
            clip_joints: clip.joint_count(),
            rig_joints: skeleton.len(),
        });
    }
    if let Some(dt) = frame_time
        && !(dt.is_finite() && dt > 0.0)
    {
        return Err(ExportError::FrameTime { frame_time: dt });
    }
    let duration = f64::from(clip.duration());
    let grid = if frame_time.is_some() {
        None
    } else {
        key_grid(clip)
    };
    let dt = frame_time
        .or(grid.as_ref().map(|g| g.frame_time))
        .unwrap_or_else(|| resampled_frame_time(duration));
    // Frames up to the first at or past the end (which holds the end pose).
    let frames = if duration > 0.0 {
        // A float-to-int `as` saturates: an absurd count is refused below, not wrapped.
        ((duration / dt - 1e-6).ceil().max(0.0) as usize).saturating_add(1)
    } else {
        1
    };
    let order = depth_first(skeleton);
    let translated: Vec<bool> = (0..skeleton.len())
        .map(|j| skeleton.parents()[j].is_none() || clip.animates_translation(j))
        .collect();
    let channels: usize = translated.iter().map(|&t| if t { 6 } else { 3 }).sum();
    if frames.saturating_mul(channels) > MAX_VALUES {
        return Err(ExportError::TooManyFrames {
            frames,
            channels,
            max_values: MAX_VALUES,
        });
    }

    let mut out = String::with_capacity(64 * skeleton.len() + frames * channels * 12);
    out.push_str("HIERARCHY\n");
    hierarchy(&mut out, skeleton, &translated);
    // `write!` into a String cannot fail.
    let _ = writeln!(out, "MOTION\nFrames: {frames}\nFrame Time: {dt:.9}");
    let rest = skeleton.rest();
    let mut locals = rest.to_vec();
    let mut sampler = clip.sampler();
    let mut angles: Vec<Option<[f64; 3]>> = vec![None; skeleton.len()];
    let times = frame_times(clip, dt, frames, grid.as_ref());
    for t in times {
        sampler.sample(clip, t, rest, &mut locals);
        let mut first = true;
        let mut value = |out: &mut String, v: f64| {
            if !first {
                out.push(' ');
            }
            first = false;
            number(out, v);
        };
        for &j in &order {
            let local: &Transform = &locals[j];
            if translated[j] {
                for c in (local.translation * CENTIMETRES_PER_METRE).to_array() {
                    value(&mut out, f64::from(c));
                }
            }
            let zyx = euler_zyx(local.rotation, angles[j]);
            angles[j] = Some(zyx);
            for a in zyx {
                value(&mut out, a.to_degrees());
            }
        }
        out.push('\n');
    }
    Ok(out)
}

/// Joints in the order BVH nests them: depth-first, children in skeleton order.
fn depth_first(skeleton: &Skeleton) -> Vec<usize> {
    let children = children(skeleton);
    let mut order = Vec::with_capacity(skeleton.len());
    let mut stack: Vec<usize> = skeleton.roots().collect();
    stack.reverse();
    while let Some(j) = stack.pop() {
        order.push(j);
        stack.extend(children[j].iter().rev());
    }
    order
}

fn children(skeleton: &Skeleton) -> Vec<Vec<usize>> {
    let mut children = vec![Vec::new(); skeleton.len()];
    for (j, p) in skeleton.parents().iter().enumerate() {
        if let Some(p) = *p {
            children[p].push(j);
        }
    }
    children
}

/// The `HIERARCHY` blocks, iteratively (a skeleton may be a chain of 65,535 joints).
fn hierarchy(out: &mut String, skeleton: &Skeleton, translated: &[bool]) {
    let children = children(skeleton);
    for root in skeleton.roots() {
        // (joint, next child to open)
        let mut stack: Vec<(usize, usize)> = Vec::new();
        open(out, skeleton, root, 0, translated[root]);
        stack.push((root, 0));
        while let Some(&mut (j, ref mut next)) = stack.last_mut() {
            if let Some(&child) = children[j].get(*next) {
                *next += 1;
                open(out, skeleton, child, stack.len(), translated[child]);
                stack.push((child, 0));
                continue;
            }
            let depth = stack.len() - 1;
            if children[j].is_empty() {
                indent(out, depth + 1);
                out.push_str("End Site\n");
                indent(out, depth + 1);
                out.push_str("{\n");
                indent(out, depth + 2);
                offset(out, skeleton.rest()[j].translation * CENTIMETRES_PER_METRE);
                indent(out, depth + 1);
                out.push_str("}\n");
            }
            indent(out, depth);
            out.push_str("}\n");
            stack.pop();
        }
    }
}

/// A joint's `ROOT`/`JOINT` line, its brace, `OFFSET` and `CHANNELS`.
fn open(out: &mut String, skeleton: &Skeleton, j: usize, depth: usize, translated: bool) {
    indent(out, depth);
    out.push_str(if depth == 0 { "ROOT " } else { "JOINT " });
    out.push_str(&bvh_name(&skeleton.names()[j]));
    out.push('\n');
    indent(out, depth);
    out.push_str("{\n");
    indent(out, depth + 1);
    offset(out, skeleton.rest()[j].translation * CENTIMETRES_PER_METRE);
    indent(out, depth + 1);
    out.push_str(if translated {
        "CHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation\n"
    } else {
        "CHANNELS 3 Zrotation Yrotation Xrotation\n"
    });
}

fn indent(out: &mut String, depth: usize) {
    out.extend(std::iter::repeat_n('\t', depth.min(MAX_INDENT)));
}

/// `v` with six decimals, without the sign of a value that rounds to zero.
fn number(out: &mut String, v: f64) {
    let v = if v.abs() < 5e-7 { 0.0 } else { v };
    // `write!` into a String cannot fail.
    let _ = write!(out, "{v:.6}");
}

/// An `OFFSET` line (centimetres).
fn offset(out: &mut String, v: glam::Vec3) {
    out.push_str("OFFSET");
    for c in v.to_array() {
        out.push(' ');
        number(out, f64::from(c));
    }
    out.push('\n');
}

/// A joint name as one BVH token.
fn bvh_name(name: &str) -> String {
    name.chars()
        .map(|c| {
            if c.is_whitespace() || c.is_control() || c == '{' || c == '}' {
                '_'
            } else {
                c
            }
        })
        .collect()
}

/// Angles `[z, y, x]` (radians) with `R = R_z(z) · R_y(y) · R_x(x)` equal to `q`, from its
/// f64 rotation matrix; of the two solutions (and their 2π turns), the one nearest
/// `previous`.
///
/// With `R = R_z R_y R_x`: `r20 = −sin y`, `(r21, r22) = cos y (sin x, cos x)`,
/// `(r10, r00) = cos y (sin z, cos z)`; at `cos y = 0` only `z ± x` is defined: `x = 0`,
/// `z = atan2(−r01, r11)`.
fn euler_zyx(q: Quat, previous: Option<[f64; 3]>) -> [f64; 3] {
    let m = DMat3::from_quat(
        DQuat::from_xyzw(
            f64::from(q.x),
            f64::from(q.y),
            f64::from(q.z),
            f64::from(q.w),
        )
        .normalize(),
    );
    // glam is column-major: r_ij = col(j)[i].
    let r = |i: usize, j: usize| m.col(j)[i];
    let y = (-r(2, 0)).clamp(-1.0, 1.0).asin();
    let cy = (r(2, 1).powi(2) + r(2, 2).powi(2)).sqrt();
    let (z, x) = if cy > 1e-9 {
        (r(1, 0).atan2(r(0, 0)), r(2, 1).atan2(r(2, 2)))
    } else {
        ((-r(0, 1)).atan2(r(1, 1)), 0.0)
    };
    let Some(p) = previous else {
        return [z, y, x];
    };
    let near = |a: f64, to: f64| a - TAU * ((a - to) / TAU).round();
    let candidates = [[z, y, x], [z + PI, PI - y, x + PI]].map(|c| {
        let c = [near(c[0], p[0]), near(c[1], p[1]), near(c[2], p[2])];
        let d = (c[0] - p[0]).abs() + (c[1] - p[1]).abs() + (c[2] - p[2]).abs();
        (c, d)
    });
    if candidates[1].1 < candidates[0].1 {
        candidates[1].0
    } else {
        candidates[0].0
    }
}

/// A clip's keys on one uniform grid from its start.
struct KeyGrid<'a> {
    /// The grid's spacing, seconds.
    frame_time: f64,
    /// Every step and linear track's key times.
    keys: Vec<&'a [f32]>,
}

/// The grid of a clip whose step and linear keys all lie on one uniform grid from its start
/// (the finest key spacing, refined over the farthest key), when the clip's end lies on it
/// too. `None` for clips with curves or cubic splines, or without a moving key track.
fn key_grid(clip: &Clip) -> Option<KeyGrid<'_>> {
    let mut keys: Vec<&[f32]> = Vec::new();
    for ch in clip.channels() {
        match &ch.rotation {
            Some(RotationChannel::Keys(t)) => keys.extend(grid_keys(t)?),
            Some(RotationChannel::Euler(_)) => return None,
            None => {}
        }
        for v in [&ch.translation, &ch.scale].into_iter().flatten() {
            match v {
                VectorChannel::Keys(t) => keys.extend(grid_keys(t)?),
                VectorChannel::Curves(_) => return None,
            }
        }
    }
    let (start, end) = (f64::from(clip.start()), f64::from(clip.end()));
    let finest = keys
        .iter()
        .flat_map(|t| t.windows(2).map(|w| f64::from(w[1]) - f64::from(w[0])))
        .fold(f64::INFINITY, f64::min);
    if !(finest.is_finite() && finest >= MIN_FRAME_TIME) {
        return None;
    }
    let inside = || {
        keys.iter()
            .flat_map(|t| t.iter())
            .map(|&t| f64::from(t))
            .filter(|&t| t >= start && t <= end)
    };
    let far = inside().fold(0.0, |m: f64, t| m.max(t - start));
    let steps = (far / finest).round();
    let dt = if steps >= 1.0 { far / steps } else { finest };
    let on_grid = |t: f64| {
        let k = (t - start) / dt;
        (k - k.round()).abs() < 1e-2
    };
    (inside().all(on_grid) && on_grid(end)).then_some(KeyGrid {
        frame_time: dt,
        keys,
    })
}

/// The clip time of each frame: `start + i · dt`, clamped to the end — or, on a key grid, the
/// key's own time where frame `i` has one, so frames sample the keys exactly rather than a
/// rounding of time away from them.
fn frame_times(clip: &Clip, dt: f64, frames: usize, grid: Option<&KeyGrid<'_>>) -> Vec<f32> {
    let (start, end) = (f64::from(clip.start()), f64::from(clip.end()));
    let mut times: Vec<f32> = (0..frames)
        .map(|i| (start + i as f64 * dt).min(end) as f32)
        .collect();
    for &t in grid
        .iter()
        .flat_map(|g| g.keys.iter())
        .flat_map(|k| k.iter())
    {
        let k = ((f64::from(t) - start) / dt).round();
        if k >= 0.0
            && t <= clip.end()
            && let Some(slot) = times.get_mut(k as usize)
        {
            *slot = t;
        }
    }
    times
}

/// A track's key times when it can be framed: none for a constant track, `None` (no grid)
/// for a cubic spline.
fn grid_keys<T: TrackValue>(track: &Track<T>) -> Option<Option<&[f32]>> {
    match track.interpolation() {
        Interpolation::CubicSpline => None,
        _ if track.is_constant() => Some(None),
        _ => Some(Some(track.times())),
    }
}

/// `1 / RESAMPLE_RATE`, shortened so a whole number of frames spans `duration`.
fn resampled_frame_time(duration: f64) -> f64 {
    if duration > 0.0 {
        duration / (duration * RESAMPLE_RATE).ceil().max(1.0)
    } else {
        1.0 / RESAMPLE_RATE
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::clip::JointChannels;
    use glam::{EulerRot, Vec3};

    /// Radians between two rotations, precise near zero (unlike `acos` of the dot product).
    fn angle_between(a: Quat, b: Quat) -> f32 {
        let d = a.conjugate() * b;
        2.0 * Vec3::new(d.x, d.y, d.z).length().min(1.0).asin()
    }

    #[test]
    fn euler_zyx_reproduces_rotations_and_stays_continuous() {
        // A hand-checked value: 90° about Y is y = 90°, nothing else.
        let [z, y, x] = euler_zyx(Quat::from_rotation_y(0.5 * std::f32::consts::PI), None);
        assert!(z.abs() < 1e-6 && (y - PI / 2.0).abs() < 1e-6 && x.abs() < 1e-6);
        let mut previous = None;
        for i in 0..2000 {
            let f = i as f32 * 0.01;
            // Passing through the gimbal (y = ±90°) and wrapping z and x.
            let q = Quat::from_euler(EulerRot::ZYX, 3.0 * f, 1.7 * f.sin(), -2.0 * f);
            let a = euler_zyx(q, previous);
            let back = Quat::from_rotation_z(a[0] as f32)
                * Quat::from_rotation_y(a[1] as f32)
                * Quat::from_rotation_x(a[2] as f32);
            assert!(angle_between(back, q) < 1e-5, "frame {i}");
            if let Some(p) = previous {
                let jump = (0..3).map(|c| (a[c] - p[c]).abs()).fold(0.0, f64::max);
                // Steps are 0.03 rad per axis at most, except at the gimbal itself.
                assert!(
                    jump < 0.5 || (a[1].abs() - PI / 2.0).abs() < 0.05,
                    "frame {i}"
                );
            }
            previous = Some(a);
        }
    }

    #[test]
    fn names_are_single_tokens() {
        assert_eq!(bvh_name("l hip\t{1}"), "l_hip__1_");
        assert_eq!(bvh_name("Hips"), "Hips");
    }

    #[test]
    fn uniform_keys_give_their_frame_time_and_others_resample() {
        let track = |times: Vec<f32>| {
            let values = times
                .iter()
                .map(|&t| Quat::from_rotation_x(t))
                .collect::<Vec<_>>();
            RotationChannel::Keys(Track::new(Interpolation::Linear, times, values).unwrap())
        };
        let clip = |times: Vec<f32>| {
            let joints = vec![JointChannels {
                rotation: Some(track(times)),
                ..Default::default()
            }];
            Clip::new("c", joints, None).unwrap()
        };
        let grid: Vec<f32> = (0..31).map(|i| i as f32 / 30.0).collect();
        let dt = key_grid(&clip(grid)).unwrap().frame_time;
        assert!((dt - 1.0 / 30.0).abs() < 1e-7);
        // A missing key is still on the grid.
        let gaps: Vec<f32> = [0, 1, 2, 5, 6, 10]
            .iter()
            .map(|&i| i as f32 * 0.1)
            .collect();
        assert!((key_grid(&clip(gaps)).unwrap().frame_time - 0.1).abs() < 1e-7);
        // Off the grid: resampled at 60 Hz or a little faster.
        assert!(key_grid(&clip(vec![0.0, 0.1, 0.25])).is_none());
        let d = resampled_frame_time(0.25);
        // An absurd frame time is refused, not a wrapped count.
        let long = clip((0..31).map(|i| i as f32 / 30.0).collect());
        let skeleton =
            posecast_proto::testing::skeleton_bound_at_rest(vec![None], vec![Transform::IDENTITY]);
        assert!(matches!(
            write(&skeleton, &long, Some(1e-300)),
            Err(ExportError::TooManyFrames { .. })
        ));
        assert!(matches!(
            write(&skeleton, &long, Some(-1.0)),
            Err(ExportError::FrameTime { .. })
        ));
        assert!(d <= 1.0 / 60.0 && ((0.25 / d) - (0.25 / d).round()).abs() < 1e-9);
    }
}
