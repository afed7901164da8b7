//! VRM animation (`.vrma`, `VRMC_vrm_animation` 1.0): a glTF whose root extension names, per
//! VRM 1.0 humanoid bone, the node that carries it (`humanoid.humanBones.{bone}.node`), with
//! the motion in the core glTF `animations` and no skin. The nodes' rest pose is the VRM
//! T-pose and the hips' translation is in metres (glTF units), so the motion needs nothing but
//! the bone map to be retargeted onto any humanoid.
//!
//! This file reads and checks the extension; `Context::animation_rig` (`vrma_rig.rs`) builds the
//! skeleton. `expressions` (a node per expression whose `translation.x` is its weight) and
//! `lookAt` (a node whose model-space position is the gaze target) are read so the notes can
//! say what was left: posecast imports neither (expression weights drive morph targets, which
//! are not imported yet).
//!
//! The extension's JSON is read with a tree of our own (`Json`) rather than
//! `serde_json::Value`, whose maps keep the last of two equal keys: a bone listed twice must be
//! an error, not a silent choice.

use std::fmt;

use serde::de::{Deserialize, Deserializer, MapAccess, SeqAccess, Visitor};

/// The extension's name, at the document root.
pub const EXTENSION: &str = "VRMC_vrm_animation";

/// The VRM 1.0 humanoid bones a file must list (VRMC_vrm 1.0 `humanoid.md`, "required"; the
/// animation extension requires the same).
pub const REQUIRED: &[&str] = &[
    "hips",
    "spine",
    "head",
    "leftUpperArm",
    "leftLowerArm",
    "leftHand",
    "rightUpperArm",
    "rightLowerArm",
    "rightHand",
    "leftUpperLeg",
    "leftLowerLeg",
    "leftFoot",
    "rightUpperLeg",
    "rightLowerLeg",
    "rightFoot",
];

/// Why a `VRMC_vrm_animation` extension cannot be used.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum VrmaError {
    /// A property is missing or has the wrong JSON type.
    #[error("{EXTENSION}.{path} is not {expected}")]
    Shape {
        /// The property's path inside the extension (`humanoid.humanBones.hips.node`).
        path: String,
        /// What it should be (`"an object"`, `"a node index (an integer ≥ 0)"`, …).
        expected: &'static str,
    },
    /// The same bone is a key of `humanBones` twice.
    #[error("{EXTENSION}: humanoid bone {bone:?} is listed twice")]
    DuplicateBone {
        /// The VRM bone name.
        bone: String,
    },
    /// Two bones name one node.
    #[error("{EXTENSION}: humanoid bones {first:?} and {second:?} both name node {node}")]
    SharedNode {
        /// The VRM name of the first bone on the node.
        first: String,
        /// The VRM name of the second bone on the node.
        second: String,
        /// The node's index in the document.
        node: usize,
    },
    /// A bone names a node the document does not have.
    #[error(
        "{EXTENSION}: humanoid bone {bone:?} names node {node}, which does not exist (the file \
         has {nodes} nodes)"
    )]
    MissingNode {
        /// The VRM bone name.
        bone: String,
        /// The node index it names.
        node: usize,
        /// How many nodes the document has.
        nodes: usize,
    },
    /// Required bones are not listed (`hips` first when it is one of them).
    #[error("{EXTENSION}: required humanoid bones missing: {}", .bones.join(", "))]
    MissingBones {
        /// The VRM names of the missing bones.
        bones: Vec<String>,
    },
    /// A bone's node does not hang from the hips' node.
    #[error(
        "{EXTENSION}: humanoid bone {bone:?} (node {node}) does not hang from the hips (node \
         {hips})"
    )]
    NotUnderHips {
        /// The VRM bone name.
        bone: String,
        /// The bone's node index.
        node: usize,
        /// The hips' node index.
        hips: usize,
    },
    /// A `.vrma` file without the extension.
    #[error("a .vrma file needs the {EXTENSION} extension at the document root")]
    Absent,
}

/// The extension as the file gives it (shape checked, nodes not yet: see [`VrmAnimation::check`]).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct VrmAnimation {
    /// `specVersion` (`"1.0"`; drafts wrote `"1.0-draft"`).
    pub spec_version: Option<String>,
    /// `(VRM bone name, node)`, in file order.
    pub bones: Vec<(String, usize)>,
    /// `(preset/<name> or custom/<name>, node)`.
    pub expressions: Vec<(String, usize)>,
    /// The gaze target's node.
    pub look_at: Option<usize>,
}

impl VrmAnimation {
    /// Checks the bone map against a document of `parents.len()` nodes (`parents[n]`: node
    /// `n`'s parent): every node exists, no node carries two bones, every required bone is
    /// listed, every bone hangs from the hips.
    ///
    /// # Errors
    /// The first problem found, in that order.
    pub fn check(&self, parents: &[Option<usize>]) -> Result<(), VrmaError> {
        let nodes = parents.len();
        let mut owner: std::collections::HashMap<usize, &str> = Default::default();
        for (bone, node) in &self.bones {
            if *node >= nodes {
                return Err(VrmaError::MissingNode {
                    bone: bone.clone(),
                    node: *node,
                    nodes,
                });
            }
            if let Some(first) = owner.insert(*node, bone) {
                return Err(VrmaError::SharedNode {
                    first: first.to_owned(),
                    second: bone.clone(),
                    node: *node,
                });
            }
        }
        let missing: Vec<String> = REQUIRED
            .iter()
            .filter(|r| !self.bones.iter().any(|(b, _)| b == *r))
            .map(|r| (*r).to_owned())
            .collect();
        if !missing.is_empty() {
            return Err(VrmaError::MissingBones { bones: missing });
        }
        let hips = self
            .bones
            .iter()
            .find(|(b, _)| b == "hips")
            .map_or(0, |b| b.1);
        for (bone, node) in &self.bones {
            if *node == hips {
                continue;
            }
            // Bounded walk: `Nodes::new` refused cycles' second parents, but a loop of single
            // parents must not hang the import either.
            let mut cur = parents.get(*node).copied().flatten();
            let mut steps = 0;
            while let Some(p) = cur {
                if p == hips || steps > nodes {
                    break;
                }
                cur = parents.get(p).copied().flatten();
                steps += 1;
            }
            if cur != Some(hips) {
                return Err(VrmaError::NotUnderHips {
                    bone: bone.clone(),
                    node: *node,
                    hips,
                });
            }
        }
        Ok(())
    }
}

/// The `VRMC_vrm_animation` extension of a glTF document's JSON, if it has one.
///
/// # Errors
/// The extension is there but not shaped as the specification says.
pub fn read(json: &[u8]) -> Result<Option<VrmAnimation>, VrmaError> {
    // The glTF parser already accepted this JSON; a document that is not an object simply has
    // no extension.
    let Ok(Json::Object(root)) = serde_json::from_slice::<Json>(json) else {
        return Ok(None);
    };
    let Some(Json::Object(extensions)) = last(&root, "extensions") else {
        return Ok(None);
    };
    let Some(ext) = last(extensions, EXTENSION) else {
        return Ok(None);
    };
    let ext = object(ext, "")?;
    let spec_version = match last(ext, "specVersion") {
        None => None,
        Some(Json::Str(s)) => Some(s.clone()),
        Some(_) => {
            return Err(shape("specVersion", "a string"));
        }
    };
    let humanoid = object(
        last(ext, "humanoid").ok_or_else(|| shape("humanoid", "an object"))?,
        "humanoid",
    )?;
    let human_bones = object(
        last(humanoid, "humanBones").ok_or_else(|| shape("humanoid.humanBones", "an object"))?,
        "humanoid.humanBones",
    )?;
    let mut bones: Vec<(String, usize)> = Vec::with_capacity(human_bones.len());
    for (bone, value) in human_bones {
        if bones.iter().any(|(b, _)| b == bone) {
            return Err(VrmaError::DuplicateBone { bone: bone.clone() });
        }
        bones.push((
            bone.clone(),
            node(value, &format!("humanoid.humanBones.{bone}"))?,
        ));
    }
    let mut expressions = Vec::new();
    if let Some(e) = last(ext, "expressions") {
        let e = object(e, "expressions")?;
        for kind in ["preset", "custom"] {
            let Some(list) = last(e, kind) else { continue };
            let path = format!("expressions.{kind}");
            for (name, value) in object(list, &path)? {
                expressions.push((
                    format!("{kind}/{name}"),
                    node(value, &format!("{path}.{name}"))?,
                ));
            }
        }
    }
    let look_at = last(ext, "lookAt").map(|l| node(l, "lookAt")).transpose()?;
    Ok(Some(VrmAnimation {
        spec_version,
        bones,
        expressions,
        look_at,
    }))
}

fn shape(path: &str, expected: &'static str) -> VrmaError {
    VrmaError::Shape {
        path: path.to_owned(),
        expected,
    }
}

/// The last value of `key` (JSON objects with a key twice mean the last one, as
/// `serde_json::Value` and JavaScript read them).
fn last<'a>(entries: &'a [(String, Json)], key: &str) -> Option<&'a Json> {
    entries.iter().rev().find(|(k, _)| k == key).map(|e| &e.1)
}

fn object<'a>(value: &'a Json, path: &str) -> Result<&'a [(String, Json)], VrmaError> {
    match value {
        Json::Object(entries) => Ok(entries),
        _ => Err(shape(
            if path.is_empty() { "(root)" } else { path },
            "an object",
        )),
    }
}

/// `{"node": <index>}` at `path`.
fn node(value: &Json, path: &str) -> Result<usize, VrmaError> {
    let entries = object(value, path)?;
    match last(entries, "node") {
        Some(Json::Index(n)) => Ok(*n),
        _ => Err(VrmaError::Shape {
            path: format!("{path}.node"),
            expected: "a node index (an integer ≥ 0)",
        }),
    }
}

/// The JSON values this reader tells apart; objects keep every entry, duplicates included.
#[derive(Debug)]
enum Json {
    Object(Vec<(String, Json)>),
    Str(String),
    /// A non-negative integer that fits a `usize`.
    Index(usize),
    /// Anything else (other numbers, booleans, null, arrays).
    Other,
}

impl<'de> Deserialize<'de> for Json {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        d.deserialize_any(JsonVisitor)
    }
}

struct JsonVisitor;

impl<'de> Visitor<'de> for JsonVisitor {
    type Value = Json;

    fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("a JSON value")
    }

    fn visit_map<A: MapAccess<'de>>(self, mut map: A) -> Result<Json, A::Error> {
        let mut entries = Vec::new();
        while let Some((k, v)) = map.next_entry::<String, Json>()? {
            entries.push((k, v));
        }
        Ok(Json::Object(entries))
    }

    fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<Json, A::Error> {
        while seq.next_element::<Json>()?.is_some() {}
        Ok(Json::Other)
    }

    fn visit_str<E: serde::de::Error>(self, s: &str) -> Result<Json, E> {
        Ok(Json::Str(s.to_owned()))
    }

    fn visit_u64<E: serde::de::Error>(self, n: u64) -> Result<Json, E> {
        Ok(usize::try_from(n).map_or(Json::Other, Json::Index))
    }

    fn visit_i64<E: serde::de::Error>(self, n: i64) -> Result<Json, E> {
        Ok(usize::try_from(n).map_or(Json::Other, Json::Index))
    }

    fn visit_f64<E: serde::de::Error>(self, _: f64) -> Result<Json, E> {
        Ok(Json::Other)
    }

    fn visit_bool<E: serde::de::Error>(self, _: bool) -> Result<Json, E> {
        Ok(Json::Other)
    }

    fn visit_unit<E: serde::de::Error>(self) -> Result<Json, E> {
        Ok(Json::Other)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn doc(ext: &str) -> Vec<u8> {
        format!(r#"{{"asset":{{"version":"2.0"}},"extensions":{{"VRMC_vrm_animation":{ext}}}}}"#)
            .into_bytes()
    }

    #[test]
    fn reads_bones_expressions_and_look_at() {
        let a = read(&doc(
            r#"{"specVersion":"1.0","humanoid":{"humanBones":{"hips":{"node":0},
            "spine":{"node":2}}},"expressions":{"preset":{"aa":{"node":5}},
            "custom":{"smirk":{"node":6}}},"lookAt":{"node":7}}"#,
        ))
        .unwrap()
        .unwrap();
        assert_eq!(a.spec_version.as_deref(), Some("1.0"));
        assert_eq!(a.bones, [("hips".into(), 0), ("spine".into(), 2)]);
        assert_eq!(
            a.expressions,
            [("preset/aa".into(), 5), ("custom/smirk".into(), 6)]
        );
        assert_eq!(a.look_at, Some(7));
        assert_eq!(read(br#"{"asset":{"version":"2.0"}}"#).unwrap(), None);
    }

    #[test]
    fn malformed_extensions_are_typed_errors() {
        let e = |ext: &str| read(&doc(ext)).unwrap_err();
        assert_eq!(
            e(r#"{"humanoid":{"humanBones":{"hips":{"node":0},"hips":{"node":1}}}}"#),
            VrmaError::DuplicateBone {
                bone: "hips".into()
            }
        );
        assert_eq!(
            e(r#"{"specVersion":"1.0"}"#),
            shape("humanoid", "an object")
        );
        assert_eq!(
            e(r#"{"humanoid":{"humanBones":[]}}"#),
            shape("humanoid.humanBones", "an object")
        );
        assert!(matches!(
            e(r#"{"humanoid":{"humanBones":{"hips":{"node":-1}}}}"#),
            VrmaError::Shape { path, .. } if path == "humanoid.humanBones.hips.node"
        ));
        assert!(matches!(
            e(r#"{"humanoid":{"humanBones":{"hips":{"node":1.5}}}}"#),
            VrmaError::Shape { .. }
        ));
        assert!(matches!(e("[]"), VrmaError::Shape { .. }));
    }

    #[test]
    fn bone_map_checked_against_the_nodes() {
        let mut a = VrmAnimation {
            spec_version: None,
            bones: REQUIRED
                .iter()
                .enumerate()
                .map(|(i, b)| ((*b).to_owned(), i))
                .collect(),
            expressions: Vec::new(),
            look_at: None,
        };
        // Node 0 is the hips, every other node its child.
        let mut parents: Vec<Option<usize>> = (0..REQUIRED.len()).map(|_| Some(0)).collect();
        parents[0] = None;
        assert_eq!(a.check(&parents), Ok(()));
        assert_eq!(
            a.check(&parents[..4]),
            Err(VrmaError::MissingNode {
                bone: REQUIRED[4].into(),
                node: 4,
                nodes: 4
            })
        );
        let mut loose = parents.clone();
        loose[3] = None;
        assert!(matches!(
            a.check(&loose),
            Err(VrmaError::NotUnderHips { node: 3, .. })
        ));
        a.bones[5].1 = 4;
        assert!(matches!(
            a.check(&parents),
            Err(VrmaError::SharedNode { node: 4, .. })
        ));
        a.bones[5].1 = 5;
        a.bones.remove(0);
        assert_eq!(
            a.check(&parents),
            Err(VrmaError::MissingBones {
                bones: vec!["hips".into()]
            })
        );
    }
}
