//! CSE169 `.skel` skeletons (seed 002): nested `balljoint name { … }` blocks with `offset`,
//! `boxmin`, `boxmax`, `rotxlimit`/`rotylimit`/`rotzlimit` and `pose`.
//!
//! Every joint is a 3-DOF ball joint with Euler angles applied X, then Y, then Z
//! ([`JointType::BallEuler`], `R = R_z · R_y · R_x`). Missing tokens take the course's
//! defaults: offset 0, box (−0.1, −0.1, −0.1)–(0.1, 0.1, 0.1), limits ±∞ (±100000 in the
//! course), pose 0. The pose is clamped to the limits. Unknown tokens are skipped one by one,
//! as the course's loader does.

use glam::{Mat4, Vec3};
use posecast_proto::{JointDofs, JointType, Skeleton, Transform};

use super::ImportError;
use super::text::Tokens;

/// The course's default box half-size.
pub const DEFAULT_BOX: (Vec3, Vec3) = (Vec3::splat(-0.1), Vec3::splat(0.1));

/// Deepest joint nesting accepted (a guard against stack-free but pathological input).
const MAX_DEPTH: usize = 4096;

/// A parsed `.skel`.
#[derive(Clone, Debug)]
pub struct Skel {
    /// Joints in the file's depth-first order (parents first). Rest transforms are
    /// `T(offset) · R(pose)` with the clamped pose; inverse binds are those of the zero pose
    /// (offsets only), the course's bind pose when no `.skin` says otherwise.
    pub skeleton: Skeleton,
    /// `boxmin`, `boxmax` per joint.
    pub boxes: Vec<(Vec3, Vec3)>,
    /// Joint offsets `r` (rest translations).
    pub offsets: Vec<Vec3>,
    /// What was changed on import (repeated names suffixed), for people.
    pub notes: Vec<String>,
}

struct Joint {
    name: String,
    parent: Option<usize>,
    offset: Vec3,
    boxes: (Vec3, Vec3),
    dofs: JointDofs,
}

/// Parses `.skel` text. `name` names the file in errors.
pub fn parse(name: &str, text: &str) -> Result<Skel, ImportError> {
    let mut tokens = Tokens::new(name, text);
    let mut joints: Vec<Joint> = Vec::new();
    // Stack of open joints; iterative so deep nesting cannot overflow the call stack.
    let mut open: Vec<usize> = Vec::new();
    let mut pose_of: Vec<Vec3> = Vec::new();
    while let Some(t) = tokens.peek() {
        let word = t.text;
        if word.eq_ignore_ascii_case("balljoint") {
            tokens.next_token("balljoint")?;
            let name_tok = tokens.next_token("joint name")?;
            if name_tok.text == "{" || name_tok.text == "}" {
                return Err(tokens.syntax(name_tok, "joint name"));
            }
            tokens.expect("{")?;
            if open.len() >= MAX_DEPTH {
                return Err(tokens.invalid(name_tok.line, "joints nested too deeply"));
            }
            let index = joints.len();
            joints.push(Joint {
                name: name_tok.text.to_owned(),
                parent: open.last().copied(),
                offset: Vec3::ZERO,
                boxes: DEFAULT_BOX,
                dofs: JointDofs::new(JointType::BallEuler),
            });
            pose_of.push(Vec3::ZERO);
            open.push(index);
            continue;
        }
        let Some(&current) = open.last() else {
            // Outside any joint only `balljoint` means something; skip anything else.
            tokens.next_token("balljoint")?;
            continue;
        };
        tokens.next_token("a joint token")?;
        let lower = word.to_ascii_lowercase();
        match lower.as_str() {
            "}" => {
                open.pop();
            }
            "offset" => joints[current].offset = tokens.vec3("offset x y z")?,
            "boxmin" => joints[current].boxes.0 = tokens.vec3("boxmin x y z")?,
            "boxmax" => joints[current].boxes.1 = tokens.vec3("boxmax x y z")?,
            "pose" => pose_of[current] = tokens.vec3("pose x y z")?,
            "rotxlimit" | "rotylimit" | "rotzlimit" => {
                let axis = usize::from(lower.as_bytes()[3] - b'x');
                let line = t.line;
                let min = tokens.f32("limit min")?;
                let max = tokens.f32("limit max")?;
                joints[current]
                    .dofs
                    .set_limits(axis, min, max)
                    .map_err(|e| tokens.invalid(line, format!("{word}: {e}")))?;
            }
            // Unknown token: skipped on its own, as the course's tokenizer does.
            _ => {}
        }
    }
    if let Some(&j) = open.last() {
        return Err(ImportError::Eof {
            file: name.to_owned(),
            expected: format!("`}}` closing joint {:?}", joints[j].name),
        });
    }
    if joints.is_empty() {
        return Err(ImportError::Eof {
            file: name.to_owned(),
            expected: "a `balljoint`".to_owned(),
        });
    }
    for (joint, pose) in joints.iter_mut().zip(&pose_of) {
        for (axis, value) in pose.to_array().into_iter().enumerate() {
            // Values are finite (checked by the tokenizer), so `set` cannot fail here.
            joint
                .dofs
                .set(axis, value)
                .map_err(|e| ImportError::Invalid {
                    file: name.to_owned(),
                    line: 0,
                    message: format!("joint {:?}: pose: {e}", joint.name),
                })?;
        }
    }
    build(name, joints)
}

fn build(file: &str, joints: Vec<Joint>) -> Result<Skel, ImportError> {
    let n = joints.len();
    let mut zero_world: Vec<Mat4> = Vec::with_capacity(n);
    for j in &joints {
        let local = Mat4::from_translation(j.offset);
        let world = match j.parent {
            Some(p) => zero_world[p] * local,
            None => local,
        };
        zero_world.push(world);
    }
    let rest: Vec<Transform> = joints
        .iter()
        .map(|j| j.dofs.local_transform(j.offset))
        .collect();
    let names = unique_names(joints.iter().map(|j| j.name.clone()));
    let notes = renamed_note(joints.iter().map(|j| j.name.as_str()), &names)
        .into_iter()
        .collect();
    let skeleton = Skeleton::new(
        names,
        joints.iter().map(|j| j.parent).collect(),
        rest,
        zero_world.iter().map(Mat4::inverse).collect(),
    )
    .and_then(|s| s.with_dofs(joints.iter().map(|j| j.dofs.clone()).collect()))
    .map_err(|source| ImportError::Skeleton {
        file: file.to_owned(),
        source,
    })?;
    Ok(Skel {
        skeleton,
        boxes: joints.iter().map(|j| j.boxes).collect(),
        offsets: joints.iter().map(|j| j.offset).collect(),
        notes,
    })
}

/// A note listing the joints [`unique_names`] renamed (none when it renamed nothing).
pub(crate) fn renamed_note<'a>(
    original: impl Iterator<Item = &'a str>,
    unique: &[String],
) -> Option<String> {
    let renamed: Vec<String> = original
        .zip(unique)
        .filter(|(a, b)| a != b)
        .map(|(a, b)| format!("{a:?} → {b:?}"))
        .collect();
    let shown = renamed.len().min(8);
    (!renamed.is_empty()).then(|| {
        format!(
            "repeated joint names suffixed: {}{}",
            renamed[..shown].join(", "),
            if renamed.len() > shown { ", …" } else { "" }
        )
    })
}

/// Names made unique by suffixing `#2`, `#3`, … to repeats (files in the wild repeat names).
pub(crate) fn unique_names(names: impl Iterator<Item = String>) -> Vec<String> {
    let mut seen = std::collections::HashSet::new();
    names
        .map(|n| {
            let base = if n.is_empty() { "joint".to_owned() } else { n };
            let mut candidate = base.clone();
            let mut k = 2;
            while !seen.insert(candidate.clone()) {
                candidate = format!("{base}#{k}");
                k += 1;
            }
            candidate
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_limits_and_unknown_tokens() {
        let text = "balljoint a{offset 1 2 3 frobnicate 7\r\n balljoint b {\r rotxlimit -1 1 pose 2 0.5 0 }\n}";
        let s = parse("t.skel", text).unwrap();
        assert_eq!(s.skeleton.names(), &["a", "b"]);
        assert_eq!(s.skeleton.parents(), &[None, Some(0)]);
        assert_eq!(s.boxes[0], DEFAULT_BOX);
        assert_eq!(s.offsets[0], Vec3::new(1.0, 2.0, 3.0));
        let d = s.skeleton.dofs()[1].dofs();
        assert_eq!((d[0].value, d[1].value), (1.0, 0.5));
    }

    #[test]
    fn errors_name_the_line() {
        let e = parse("bad.skel", "balljoint a {\n offset 1 x 3 }").unwrap_err();
        assert!(matches!(e, ImportError::Syntax { line: 2, .. }), "{e}");
        assert!(matches!(
            parse("open.skel", "balljoint a { balljoint b {"),
            Err(ImportError::Eof { .. })
        ));
        assert!(parse("empty.skel", "").is_err());
        assert!(parse("lim.skel", "balljoint a { rotxlimit 1 -1 }").is_err());
    }
}
