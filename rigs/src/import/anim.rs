//! CSE169 `.anim` clips: `animation { range t0 t1 numchannels N channel { extrapolate in out
//! keys K { time value tanIn tanOut … } } … }`.
//!
//! A channel may carry its index (`channel 0 {`), which must then be its place.
//! Channels follow the skeleton's DOF order: root translation x, y, z, then rotation x, y, z
//! of every joint in depth-first (`.skel`) order. Root translation is added to the root's
//! offset (`L = T(r + φ) · R`, seed 002), stored as the channel map's `trans_offset`.
//! Joints with fewer than three rotation channels keep 0 for the missing angles.

use posecast_proto::Skeleton;

use super::ImportError;
use super::text::Tokens;
use crate::clip::{
    ChannelMap, Clip, Curve, Extrapolation, JointChannels, Key, RotationChannel, Tangent,
    VectorChannel,
};

/// Parses `.anim` text into a clip over `skeleton`'s joints, named `name`'s file stem by the
/// caller (here: `name` as given).
pub fn parse(name: &str, text: &str, skeleton: &Skeleton) -> Result<Clip, ImportError> {
    parse_noted(name, text, skeleton).map(|(clip, _)| clip)
}

/// [`parse`], with notes for people: a file with fewer channels than the skeleton has DOFs
/// (the joints past its last channel keep their pose).
pub fn parse_noted(
    name: &str,
    text: &str,
    skeleton: &Skeleton,
) -> Result<(Clip, Vec<String>), ImportError> {
    let mut tokens = Tokens::new(name, text);
    tokens.expect("animation")?;
    tokens.expect("{")?;
    let mut range = None;
    let mut declared = None;
    let mut curves: Vec<Curve> = Vec::new();
    let max_channels = 3 + 3 * skeleton.len();
    loop {
        let t = tokens.next_token("`channel` or `}`")?;
        match t.text.to_ascii_lowercase().as_str() {
            "}" => break,
            "range" => range = Some((tokens.f32("range start")?, tokens.f32("range end")?)),
            "numchannels" => {
                let (n, line) = tokens.count("channel count")?;
                if n > max_channels {
                    return Err(tokens.invalid(
                        line,
                        format!("{n} channels, but the skeleton has only {max_channels} DOFs"),
                    ));
                }
                tokens.check_count("channels", n, 8, line)?;
                declared = Some((n, line));
            }
            "channel" => {
                if curves.len() >= max_channels {
                    return Err(tokens.invalid(
                        t.line,
                        format!("more than the skeleton's {max_channels} DOF channels"),
                    ));
                }
                let index = curves.len();
                // Some exporters number their channels: `channel 0 {`. The number must be the
                // channel's place (channels are read in DOF order, whatever they say).
                if let Some(t) = tokens.peek().filter(|t| t.text != "{") {
                    let n: usize = tokens.count("channel index")?.0;
                    if n != index {
                        return Err(tokens.invalid(
                            t.line,
                            format!("channel {n} where channel {index} was expected"),
                        ));
                    }
                }
                curves.push(channel(&mut tokens, index)?);
            }
            _ => return Err(tokens.syntax(t, "`range`, `numchannels`, `channel` or `}`")),
        }
    }
    if let Some((n, line)) = declared
        && n != curves.len()
    {
        return Err(tokens.invalid(
            line,
            format!("numchannels says {n}, the file has {}", curves.len()),
        ));
    }
    let mut notes = Vec::new();
    if curves.len() < max_channels {
        let covered = curves.len().saturating_sub(3) / 3;
        let missing: Vec<&str> = skeleton
            .names()
            .iter()
            .skip(covered + usize::from(!(curves.len().saturating_sub(3)).is_multiple_of(3)))
            .map(String::as_str)
            .collect();
        let shown = missing.len().min(8);
        notes.push(format!(
            "{name}: {} of the skeleton's {max_channels} channels; {} joint(s) past the last \
             channel keep their pose ({}{})",
            curves.len(),
            missing.len(),
            missing[..shown].join(", "),
            if missing.len() > shown { ", …" } else { "" }
        ));
    }
    let mut curves = curves.into_iter();
    let mut joints = vec![JointChannels::default(); skeleton.len()];
    let take3 = |curves: &mut std::vec::IntoIter<Curve>| -> Option<Box<[Curve; 3]>> {
        let x = curves.next()?;
        let y = curves.next().unwrap_or_else(|| Curve::constant(0.0));
        let z = curves.next().unwrap_or_else(|| Curve::constant(0.0));
        Some(Box::new([x, y, z]))
    };
    if let Some(t) = take3(&mut curves) {
        joints[0].translation = Some(VectorChannel::Curves(t));
        joints[0].map = ChannelMap {
            trans_offset: skeleton.rest()[0].translation,
            ..ChannelMap::IDENTITY
        };
    }
    for joint in &mut joints {
        match take3(&mut curves) {
            Some(r) => joint.rotation = Some(RotationChannel::Euler(r)),
            None => break,
        }
    }
    let clip = Clip::new(name, joints, range).map_err(|source| ImportError::Clip {
        file: name.to_owned(),
        place: "range".to_owned(),
        source,
    })?;
    Ok((clip, notes))
}

fn extrapolation(tokens: &mut Tokens<'_>) -> Result<Extrapolation, ImportError> {
    let t = tokens.next_token("extrapolation mode")?;
    Ok(match t.text.to_ascii_lowercase().as_str() {
        "constant" => Extrapolation::Constant,
        "linear" => Extrapolation::Linear,
        "cycle" => Extrapolation::Cycle,
        "cycle_offset" => Extrapolation::CycleOffset,
        "bounce" => Extrapolation::Bounce,
        _ => {
            return Err(tokens.syntax(t, "constant, linear, cycle, cycle_offset or bounce"));
        }
    })
}

fn tangent(tokens: &mut Tokens<'_>) -> Result<Tangent, ImportError> {
    let t = tokens.next_token("tangent rule")?;
    Ok(match t.text.to_ascii_lowercase().as_str() {
        "flat" => Tangent::Flat,
        "linear" => Tangent::Linear,
        "smooth" => Tangent::Smooth,
        other => match other.parse::<f32>() {
            Ok(v) if v.is_finite() => Tangent::Value(v),
            _ => return Err(tokens.syntax(t, "flat, linear, smooth or a number")),
        },
    })
}

fn channel(tokens: &mut Tokens<'_>, index: usize) -> Result<Curve, ImportError> {
    tokens.expect("{")?;
    let mut modes = (Extrapolation::Constant, Extrapolation::Constant);
    let mut keys = Vec::new();
    let line = tokens.line();
    loop {
        let t = tokens.next_token("`extrapolate`, `keys` or `}`")?;
        match t.text.to_ascii_lowercase().as_str() {
            "}" => break,
            "extrapolate" => modes = (extrapolation(tokens)?, extrapolation(tokens)?),
            "keys" => {
                let (k, line) = tokens.count("key count")?;
                tokens.check_count("keys", k, 4, line)?;
                tokens.expect("{")?;
                keys = Vec::with_capacity(k);
                for _ in 0..k {
                    keys.push(Key {
                        time: tokens.f32("key time")?,
                        value: tokens.f32("key value")?,
                        tangent_in: tangent(tokens)?,
                        tangent_out: tangent(tokens)?,
                    });
                }
                tokens.expect("}")?;
            }
            _ => return Err(tokens.syntax(t, "`extrapolate`, `keys` or `}`")),
        }
    }
    let file = tokens.file().to_owned();
    Curve::new(&keys, modes.0, modes.1).map_err(|source| ImportError::Clip {
        file,
        place: format!("channel {index} (line {line})"),
        source,
    })
}
