//! Biovision hierarchy (`.bvh`) motion capture: `HIERARCHY` with `ROOT`/`JOINT`/`End Site`
//! blocks, then `MOTION` with `Frames:`, `Frame Time:` and one line of channel values per
//! frame.
//!
//! - Rotation channels apply in the order listed: `Zrotation Yrotation Xrotation` is
//!   `R = R_z · R_y · R_x` (degrees). Any order per joint is accepted.
//! - Position channels give the joint's translation in its parent's space and replace its
//!   `OFFSET` (the usual reading: a root's position is absolute); a missing axis keeps the
//!   offset's component.
//! - `End Site`s are not joints; their offsets are kept in [`SourceInfo::end_sites`].
//! - Frames become one quaternion track (slerp between frames) per rotated joint and one
//!   vector track per translated joint; constant ones are stored once.
//!
//! Joint names run to the end of their line (names with spaces occur); repeated names get
//! `#2`, `#3` suffixes.

use glam::{Mat4, Quat, Vec3};
use posecast_proto::{Skeleton, Transform};

use super::ImportError;
use super::skel::{renamed_note, unique_names};
use super::text::Tokens;
use crate::asset::{Asset, SourceFormat, SourceInfo};
use crate::clip::{Clip, Interpolation, JointChannels, RotationChannel, Track, VectorChannel};

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Channel {
    Position(usize),
    Rotation(usize),
}

struct Joint {
    name: String,
    parent: Option<usize>,
    offset: Vec3,
    channels: Vec<Channel>,
}

/// Deepest nesting accepted.
const MAX_DEPTH: usize = 4096;

/// Parses BVH text into an asset with one skeleton and one clip (none when the file has no
/// frames). `name` names the file in errors; the asset and clip are named by its stem.
pub fn parse(name: &str, text: &str) -> Result<Asset, ImportError> {
    let mut tokens = Tokens::new(name, text);
    tokens.expect("HIERARCHY")?;
    let mut joints: Vec<Joint> = Vec::new();
    let mut end_sites = Vec::new();
    // Open blocks: Some(joint) or None for an End Site.
    let mut open: Vec<Option<usize>> = Vec::new();
    loop {
        let t = tokens.next_token("`ROOT`, `JOINT`, `End Site` or `MOTION`")?;
        let word = t.text.to_ascii_lowercase();
        match word.as_str() {
            "root" | "joint" => {
                if word == "joint" && open.is_empty() {
                    return Err(tokens.syntax(t, "`ROOT` (a JOINT outside any joint)"));
                }
                if open.last().is_some_and(Option::is_none) {
                    return Err(tokens.syntax(t, "`OFFSET` or `}` inside End Site"));
                }
                let mut parts = Vec::new();
                while let Some(p) = tokens.peek() {
                    if p.line != t.line || p.text == "{" {
                        break;
                    }
                    parts.push(tokens.next_token("joint name")?.text);
                }
                if parts.is_empty() {
                    return Err(tokens.invalid(t.line, "joint without a name"));
                }
                tokens.expect("{")?;
                if open.len() >= MAX_DEPTH {
                    return Err(tokens.invalid(t.line, "joints nested too deeply"));
                }
                joints.push(Joint {
                    name: parts.join(" "),
                    parent: if word == "root" {
                        None
                    } else {
                        open.last().copied().flatten()
                    },
                    offset: Vec3::ZERO,
                    channels: Vec::new(),
                });
                open.push(Some(joints.len() - 1));
            }
            "end" => {
                tokens.expect("Site")?;
                tokens.expect("{")?;
                let Some(Some(parent)) = open.last().copied() else {
                    return Err(tokens.syntax(t, "End Site inside a joint"));
                };
                tokens.expect("OFFSET")?;
                end_sites.push((parent, tokens.vec3("End Site offset")?));
                tokens.expect("}")?;
            }
            "offset" => {
                let Some(Some(j)) = open.last().copied() else {
                    return Err(tokens.syntax(t, "OFFSET inside a joint"));
                };
                joints[j].offset = tokens.vec3("OFFSET x y z")?;
            }
            "channels" => {
                let Some(Some(j)) = open.last().copied() else {
                    return Err(tokens.syntax(t, "CHANNELS inside a joint"));
                };
                let (n, line) = tokens.count("channel count")?;
                if n > 6 {
                    return Err(tokens.invalid(line, format!("{n} channels (at most 6)")));
                }
                let mut ch = Vec::with_capacity(n);
                for _ in 0..n {
                    let c = tokens.next_token("channel name")?;
                    let lower = c.text.to_ascii_lowercase();
                    let axis = match lower.as_bytes().first() {
                        Some(b'x') => 0,
                        Some(b'y') => 1,
                        Some(b'z') => 2,
                        _ => return Err(tokens.syntax(c, "Xposition … Zrotation")),
                    };
                    ch.push(match &lower[1..] {
                        "position" => Channel::Position(axis),
                        "rotation" => Channel::Rotation(axis),
                        _ => return Err(tokens.syntax(c, "Xposition … Zrotation")),
                    });
                }
                joints[j].channels = ch;
            }
            "}" => {
                if open.pop().is_none() {
                    return Err(tokens.syntax(t, "`ROOT` or `MOTION`"));
                }
            }
            "motion" if open.is_empty() => break,
            _ => {
                return Err(tokens.syntax(
                    t,
                    "`ROOT`, `JOINT`, `End Site`, `OFFSET`, `CHANNELS` or `}`",
                ));
            }
        }
    }
    if joints.is_empty() {
        return Err(tokens.invalid(tokens.line(), "HIERARCHY has no ROOT"));
    }
    // MOTION: "Frames: N" and "Frame Time: dt" (colons may stand apart).
    tokens.expect_one_of(&["Frames:", "Frames"])?;
    tokens.eat(":");
    let (frames, frames_line) = tokens.count("frame count")?;
    tokens.expect("Frame")?;
    tokens.expect_one_of(&["Time:", "Time"])?;
    tokens.eat(":");
    let time_line = tokens.line();
    let dt = tokens.f32("frame time")?;
    if dt <= 0.0 {
        return Err(tokens.invalid(time_line, format!("frame time {dt} is not positive")));
    }
    let per_frame: usize = joints.iter().map(|j| j.channels.len()).sum();
    tokens.check_count("frame", frames, per_frame, frames_line)?;
    let n = joints.len();
    let mut rotations: Vec<Vec<Quat>> = joints
        .iter()
        .map(|j| {
            let rotated = j.channels.iter().any(|c| matches!(c, Channel::Rotation(_)));
            Vec::with_capacity(if rotated { frames } else { 0 })
        })
        .collect();
    let mut translations: Vec<Vec<Vec3>> = joints
        .iter()
        .map(|j| {
            let moved = j.channels.iter().any(|c| matches!(c, Channel::Position(_)));
            Vec::with_capacity(if moved { frames } else { 0 })
        })
        .collect();
    for _ in 0..frames {
        for (j, joint) in joints.iter().enumerate() {
            let mut q = Quat::IDENTITY;
            let mut t = joint.offset;
            for c in &joint.channels {
                let v = tokens.f32("channel value")?;
                match *c {
                    Channel::Position(axis) => t[axis] = v,
                    Channel::Rotation(axis) => {
                        let r = v.to_radians();
                        q *= match axis {
                            0 => Quat::from_rotation_x(r),
                            1 => Quat::from_rotation_y(r),
                            _ => Quat::from_rotation_z(r),
                        };
                    }
                }
            }
            if rotations[j].capacity() > 0 {
                rotations[j].push(q.normalize());
            }
            if translations[j].capacity() > 0 {
                translations[j].push(t);
            }
        }
    }
    let stem = name.rsplit_once('.').map_or(name, |(s, _)| s).to_owned();
    let mut source = SourceInfo::new(SourceFormat::Bvh);
    source.end_sites = end_sites;
    if let Some(extra) = tokens.peek() {
        source.notes.push(format!(
            "ignored data after the last frame, from line {}",
            extra.line
        ));
    }
    let rest: Vec<Transform> = joints
        .iter()
        .map(|j| Transform::from_translation(j.offset))
        .collect();
    let mut world: Vec<Mat4> = Vec::with_capacity(n);
    for (j, joint) in joints.iter().enumerate() {
        let local = rest[j].to_mat4();
        world.push(match joint.parent {
            Some(p) => world[p] * local,
            None => local,
        });
    }
    let names = unique_names(joints.iter().map(|j| j.name.clone()));
    source
        .notes
        .extend(renamed_note(joints.iter().map(|j| j.name.as_str()), &names));
    let skeleton = Skeleton::new(
        names,
        joints.iter().map(|j| j.parent).collect(),
        rest,
        world.iter().map(Mat4::inverse).collect(),
    )
    .map_err(|source| ImportError::Skeleton {
        file: name.to_owned(),
        source,
    })?;
    let mut clips = Vec::new();
    if frames > 0 {
        let times: Vec<f32> = (0..frames).map(|i| i as f32 * dt).collect();
        let clip_err = |j: usize| {
            let file = name.to_owned();
            move |source| ImportError::Clip {
                file,
                place: format!("joint {j}"),
                source,
            }
        };
        let mut channels = Vec::with_capacity(n);
        for (j, (r, t)) in rotations.into_iter().zip(translations).enumerate() {
            let mut ch = JointChannels::default();
            if !r.is_empty() {
                let track =
                    Track::new(Interpolation::Linear, times.clone(), r).map_err(clip_err(j))?;
                ch.rotation = Some(RotationChannel::Keys(track));
            }
            if !t.is_empty() {
                let track =
                    Track::new(Interpolation::Linear, times.clone(), t).map_err(clip_err(j))?;
                ch.translation = Some(VectorChannel::Keys(track));
            }
            channels.push(ch);
        }
        let end = (frames - 1) as f32 * dt;
        clips.push(Clip::new(stem.clone(), channels, Some((0.0, end))).map_err(clip_err(0))?);
    } else {
        source.notes.push("no frames: no clip".to_owned());
    }
    Ok(Asset {
        name: stem,
        skeleton,
        meshes: Vec::new(),
        clips,
        source,
        boxes: None,
        expressions: Vec::new(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn channel_order_is_product_in_listed_order() {
        let text = "HIERARCHY\nROOT a b\n{\nOFFSET 0 0 0\nCHANNELS 3 Zrotation Xrotation Yrotation\n}\nMOTION\nFrames: 1\nFrame Time: .5\n10 20 30\n";
        let a = parse("t.bvh", text).unwrap();
        assert_eq!(a.skeleton.names(), &["a b"]);
        let mut out = [Transform::IDENTITY];
        a.clips[0].sample(0.0, a.skeleton.rest(), &mut out);
        let expected = Quat::from_rotation_z(10f32.to_radians())
            * Quat::from_rotation_x(20f32.to_radians())
            * Quat::from_rotation_y(30f32.to_radians());
        assert!(out[0].rotation.dot(expected).abs() > 1.0 - 1e-6);
    }

    #[test]
    fn truncated_and_bad_counts_are_errors() {
        let head = "HIERARCHY\nROOT a\n{\nOFFSET 0 0 0\nCHANNELS 1 Xrotation\n}\nMOTION\n";
        assert!(matches!(
            parse(
                "t.bvh",
                &format!("{head}Frames: 99999999999\nFrame Time: 0.1\n1\n")
            ),
            Err(ImportError::Count { .. })
        ));
        assert!(parse("t.bvh", &format!("{head}Frames: 2\nFrame Time: 0\n1 2\n")).is_err());
        assert!(parse("t.bvh", "HIERARCHY\nROOT a\n{\nOFFSET 0 0").is_err());
        assert!(parse("t.bvh", &format!("{head}Frames: 1\nFrame Time: 0.1\nx\n")).is_err());
    }
}
