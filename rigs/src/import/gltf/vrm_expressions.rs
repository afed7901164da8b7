//! VRM expressions (issue 30): VRM 0.x `blendShapeMaster.blendShapeGroups` and VRM 1.0
//! `VRMC_vrm.expressions` (`preset` and `custom`) read as [`Expression`]s over the file's morph
//! targets, named by the targets' names (`mesh.extras.targetNames`, else `target<k>`, as the
//! mesh importer names them) so that a bind is a weighted morph channel.
//!
//! - VRM 0.x: a group's `presetName` becomes its VRM 1.0 preset (`joy` → `happy`, `a` → `aa`,
//!   `blink_l` → `blinkLeft`); `unknown` or none keeps the group's `name`. Binds name a glTF
//!   mesh and a target index, weights 0–100 (read as 0–1). VRM 0.x has no overrides.
//! - VRM 1.0: `morphTargetBinds` name a node (its mesh) and a target index, weights 0–1;
//!   `isBinary` and `overrideBlink` / `overrideLookAt` / `overrideMouth` are kept.
//!
//! Material colour, UV and texture-transform binds change materials, which posecast does not
//! stream; they are counted in a note. A bind naming a mesh, node or target that does not
//! exist is dropped with a note, as is a second expression of a name already read.

use posecast_proto::expressions::{Expression, ExpressionBind, Override, vrm0_preset};
use serde_json::Value;

/// What a file's VRM extension defines: its expressions and what the reading noticed.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Defined {
    /// The expressions, in the file's order (VRM 1.0: presets, then custom).
    pub expressions: Vec<Expression>,
    /// What was dropped and why.
    pub notes: Vec<String>,
    /// `"0.x"` or `"1.0"`.
    pub version: &'static str,
}

/// The expressions of a glTF document's JSON, if it has a VRM expression block.
#[must_use]
pub fn read(doc: &Value) -> Option<Defined> {
    let ext = doc.get("extensions")?;
    if let Some(block) = ext.pointer("/VRMC_vrm/expressions") {
        Some(read_v1(doc, block))
    } else {
        let groups = ext.pointer("/VRM/blendShapeMaster/blendShapeGroups")?;
        Some(read_v0(doc, groups.as_array()?))
    }
}

/// Most expressions read from one file (VRM 1.0 has 18 presets; avatars carry tens of custom
/// ones): every description carries them, so a file of thousands is cut here.
pub const MAX_EXPRESSIONS: usize = 256;

/// Most morph binds one expression keeps.
pub const MAX_BINDS: usize = 256;

/// Counts what [`read`] dropped, for one note each.
#[derive(Default)]
struct Dropped {
    material_binds: usize,
    bad_binds: usize,
    clamped: usize,
    over_limits: usize,
    duplicates: Vec<String>,
}

impl Dropped {
    fn notes(self, version: &str) -> Vec<String> {
        let mut notes = Vec::new();
        if self.material_binds > 0 {
            notes.push(format!(
                "VRM {version} expressions: {} material/texture bind(s) not imported (posecast \
                 streams morph weights only)",
                self.material_binds
            ));
        }
        if self.bad_binds > 0 {
            notes.push(format!(
                "VRM {version} expressions: {} morph bind(s) naming no mesh, node or target \
                 dropped",
                self.bad_binds
            ));
        }
        if self.clamped > 0 {
            notes.push(format!(
                "VRM {version} expressions: {} bind weight(s) outside the format's range clamped",
                self.clamped
            ));
        }
        if self.over_limits > 0 {
            notes.push(format!(
                "VRM {version} expressions: {} expression(s) or bind(s) past the limits \
                 ({MAX_EXPRESSIONS} expressions, {MAX_BINDS} binds each) dropped",
                self.over_limits
            ));
        }
        if !self.duplicates.is_empty() {
            notes.push(format!(
                "VRM {version} expressions: a second definition of {} dropped",
                self.duplicates.join(", ")
            ));
        }
        notes
    }
}

/// The channel name of morph target `index` of glTF mesh `mesh`: its `targetNames` entry, else
/// `target<index>`; `None` when the mesh or target does not exist.
fn target_name(doc: &Value, mesh: usize, index: usize) -> Option<String> {
    let m = doc.get("meshes")?.get(mesh)?;
    let targets = m
        .get("primitives")?
        .as_array()?
        .iter()
        .filter_map(|p| p.get("targets").and_then(Value::as_array).map(Vec::len))
        .max()
        .unwrap_or(0);
    if index >= targets {
        return None;
    }
    let named = m
        .pointer("/extras/targetNames")
        .and_then(|n| n.get(index))
        .and_then(Value::as_str)
        .filter(|n| !n.is_empty());
    Some(named.map_or_else(|| format!("target{index}"), str::to_owned))
}

fn index(v: Option<&Value>) -> Option<usize> {
    v.and_then(Value::as_u64)
        .and_then(|n| usize::try_from(n).ok())
}

/// A bind's weight read as 0–1 (`scale` 100 for VRM 0.x), clamped; `None` when not finite.
fn weight(v: Option<&Value>, default: f64, scale: f64, dropped: &mut Dropped) -> Option<f32> {
    let w = match v {
        Some(v) => v.as_f64()?,
        None => default,
    } / scale;
    if !w.is_finite() {
        return None;
    }
    if !(0.0..=1.0).contains(&w) {
        dropped.clamped += 1;
    }
    #[allow(clippy::cast_possible_truncation)]
    Some(w.clamp(0.0, 1.0) as f32)
}

/// Adds a bind; a second bind of the same channel keeps the larger weight (several meshes may
/// carry a target of one name, e.g. face and teeth `Fcl_MTH_A`; they are one channel). A new
/// channel past [`MAX_BINDS`] is counted as dropped.
fn bind(binds: &mut Vec<ExpressionBind>, channel: String, weight: f32, dropped: &mut Dropped) {
    if let Some(b) = binds.iter_mut().find(|b| b.channel == channel) {
        b.weight = b.weight.max(weight);
    } else if binds.len() >= MAX_BINDS {
        dropped.over_limits += 1;
    } else {
        binds.push(ExpressionBind { channel, weight });
    }
}

fn push(out: &mut Vec<Expression>, e: Expression, dropped: &mut Dropped) {
    if out.iter().any(|d| d.name == e.name) {
        if dropped.duplicates.len() < 16 {
            dropped.duplicates.push(format!("{:?}", e.name));
        }
    } else if out.len() >= MAX_EXPRESSIONS {
        dropped.over_limits += 1;
    } else {
        out.push(e);
    }
}

fn count(v: Option<&Value>) -> usize {
    v.and_then(Value::as_array).map_or(0, Vec::len)
}

fn read_v0(doc: &Value, groups: &[Value]) -> Defined {
    let mut dropped = Dropped::default();
    let mut expressions = Vec::new();
    for g in groups {
        let preset = g
            .get("presetName")
            .and_then(Value::as_str)
            .and_then(vrm0_preset);
        let Some(name) = preset
            .map(str::to_owned)
            .or_else(|| g.get("name").and_then(Value::as_str).map(str::to_owned))
            .filter(|n| !n.is_empty())
        else {
            continue;
        };
        let mut binds = Vec::new();
        for b in g
            .get("binds")
            .and_then(Value::as_array)
            .into_iter()
            .flatten()
        {
            let channel = index(b.get("mesh"))
                .zip(index(b.get("index")))
                .and_then(|(m, k)| target_name(doc, m, k));
            match (channel, weight(b.get("weight"), 100.0, 100.0, &mut dropped)) {
                (Some(c), Some(w)) => bind(&mut binds, c, w, &mut dropped),
                _ => dropped.bad_binds += 1,
            }
        }
        dropped.material_binds += count(g.get("materialValues"));
        let mut e = Expression::new(name, binds);
        e.is_binary = g.get("isBinary").and_then(Value::as_bool).unwrap_or(false);
        push(&mut expressions, e, &mut dropped);
    }
    Defined {
        expressions,
        notes: dropped.notes("0.x"),
        version: "0.x",
    }
}

fn overriding(v: Option<&Value>) -> Override {
    match v.and_then(Value::as_str) {
        Some("block") => Override::Block,
        Some("blend") => Override::Blend,
        _ => Override::None,
    }
}

fn read_v1(doc: &Value, block: &Value) -> Defined {
    let mut dropped = Dropped::default();
    let mut expressions = Vec::new();
    for group in ["preset", "custom"] {
        let Some(map) = block.get(group).and_then(Value::as_object) else {
            continue;
        };
        for (name, e) in map {
            let mut binds = Vec::new();
            for b in e
                .get("morphTargetBinds")
                .and_then(Value::as_array)
                .into_iter()
                .flatten()
            {
                let mesh = index(b.get("node"))
                    .and_then(|n| doc.get("nodes")?.get(n))
                    .and_then(|n| index(n.get("mesh")));
                let channel = mesh
                    .zip(index(b.get("index")))
                    .and_then(|(m, k)| target_name(doc, m, k));
                match (channel, weight(b.get("weight"), 1.0, 1.0, &mut dropped)) {
                    (Some(c), Some(w)) => bind(&mut binds, c, w, &mut dropped),
                    _ => dropped.bad_binds += 1,
                }
            }
            dropped.material_binds +=
                count(e.get("materialColorBinds")) + count(e.get("textureTransformBinds"));
            let mut x = Expression::new(name.clone(), binds);
            x.is_binary = e.get("isBinary").and_then(Value::as_bool).unwrap_or(false);
            x.override_blink = overriding(e.get("overrideBlink"));
            x.override_look_at = overriding(e.get("overrideLookAt"));
            x.override_mouth = overriding(e.get("overrideMouth"));
            push(&mut expressions, x, &mut dropped);
        }
    }
    Defined {
        expressions,
        notes: dropped.notes("1.0"),
        version: "1.0",
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    fn doc(ext: Value) -> Value {
        json!({
            "meshes": [
                {"primitives": [{"targets": [{}, {}, {}]}], "extras": {"targetNames": ["Fcl_A", "Fcl_Joy", ""]}},
                {"primitives": [{"targets": [{}]}, {"targets": [{}, {}]}]}
            ],
            "nodes": [{"mesh": 1}, {"mesh": 0}, {}],
            "extensions": ext
        })
    }

    #[test]
    fn vrm0_groups_become_presets_and_customs_with_weights_read_as_fractions() {
        let d = read(&doc(json!({"VRM": {"blendShapeMaster": {"blendShapeGroups": [
            {"name": "Joy", "presetName": "joy", "binds": [
                {"mesh": 0, "index": 1, "weight": 100}, {"mesh": 1, "index": 1, "weight": 40}]},
            {"name": "Smirk", "presetName": "unknown", "isBinary": true,
             "binds": [{"mesh": 0, "index": 2, "weight": 150}, {"mesh": 0, "index": 9, "weight": 1}],
             "materialValues": [{}]},
            {"name": "Joy2", "presetName": "joy", "binds": []}
        ]}}})))
        .unwrap();
        assert_eq!(d.version, "0.x");
        let names: Vec<&str> = d.expressions.iter().map(|e| e.name.as_str()).collect();
        assert_eq!(names, ["happy", "Smirk"]);
        let happy = &d.expressions[0];
        assert_eq!(
            happy.binds[0],
            ExpressionBind {
                channel: "Fcl_Joy".into(),
                weight: 1.0
            }
        );
        assert_eq!(
            happy.binds[1],
            ExpressionBind {
                channel: "target1".into(),
                weight: 0.4
            }
        );
        let smirk = &d.expressions[1];
        assert!(smirk.is_binary);
        assert_eq!(
            smirk.binds,
            [ExpressionBind {
                channel: "target2".into(),
                weight: 1.0
            }]
        );
        let notes = d.notes.join("\n");
        for expected in [
            "1 material/texture",
            "1 morph bind(s)",
            "1 bind weight(s)",
            "\"happy\"",
        ] {
            assert!(notes.contains(expected), "{expected} missing from {notes}");
        }
    }

    #[test]
    fn vrm1_presets_and_customs_keep_overrides_and_binary() {
        let d = read(&doc(json!({"VRMC_vrm": {"expressions": {
            "preset": {
                "aa": {"morphTargetBinds": [{"node": 1, "index": 0, "weight": 0.8}]},
                "happy": {"morphTargetBinds": [{"node": 1, "index": 1}, {"node": 2, "index": 0, "weight": 1}],
                          "overrideBlink": "block", "overrideMouth": "blend", "isBinary": true,
                          "textureTransformBinds": [{}], "materialColorBinds": [{}, {}]}
            },
            "custom": {"wink": {"morphTargetBinds": [{"node": 0, "index": 1, "weight": 0.5}]}}
        }}})))
        .unwrap();
        assert_eq!(d.version, "1.0");
        let names: Vec<&str> = d.expressions.iter().map(|e| e.name.as_str()).collect();
        assert_eq!(names, ["aa", "happy", "wink"]);
        assert_eq!(d.expressions[0].binds[0].weight, 0.8);
        let happy = &d.expressions[1];
        assert_eq!(
            happy.binds,
            [ExpressionBind {
                channel: "Fcl_Joy".into(),
                weight: 1.0
            }]
        );
        assert!(happy.is_binary);
        assert_eq!(happy.override_blink, Override::Block);
        assert_eq!(happy.override_mouth, Override::Blend);
        assert_eq!(happy.override_look_at, Override::None);
        assert_eq!(d.expressions[2].binds[0].channel, "target1");
        let notes = d.notes.join("\n");
        assert!(notes.contains("3 material/texture"), "{notes}");
        assert!(notes.contains("1 morph bind(s)"), "{notes}");
    }

    #[test]
    fn huge_files_are_cut_to_the_limits_with_a_note() {
        let binds: Vec<Value> = (0..400)
            .map(|k| json!({"mesh": 0, "index": k % 3, "weight": 50}))
            .collect();
        let groups: Vec<Value> = (0..300)
            .map(|g| json!({"name": format!("g{g}"), "binds": binds}))
            .collect();
        let d = read(&doc(
            json!({"VRM": {"blendShapeMaster": {"blendShapeGroups": groups}}}),
        ))
        .unwrap();
        assert_eq!(d.expressions.len(), MAX_EXPRESSIONS);
        // Binds of one channel merge: three channels, three binds.
        assert!(d.expressions.iter().all(|e| e.binds.len() == 3));
        assert!(
            d.notes
                .join("\n")
                .contains("44 expression(s) or bind(s) past the limits"),
            "{:?}",
            d.notes
        );
        // One expression binding 300 distinct targets keeps the first MAX_BINDS.
        let targets: Vec<Value> = (0..300).map(|_| json!({})).collect();
        let wide_binds: Vec<Value> = (0..300)
            .map(|k| json!({"mesh": 0, "index": k, "weight": 100}))
            .collect();
        let wide = json!({
            "meshes": [{"primitives": [{"targets": targets}]}],
            "extensions": {"VRM": {"blendShapeMaster": {"blendShapeGroups": [
                {"name": "wide", "binds": wide_binds}]}}}
        });
        let d = read(&wide).unwrap();
        assert_eq!(d.expressions[0].binds.len(), MAX_BINDS);
        assert!(
            d.notes.join("\n").contains("44 expression(s) or bind(s)"),
            "{:?}",
            d.notes
        );
    }

    #[test]
    fn files_without_expressions_read_none() {
        assert!(read(&json!({"asset": {"version": "2.0"}})).is_none());
        assert!(read(&json!({"extensions": {"VRM": {"humanoid": {}}}})).is_none());
    }
}
