//! Small glTF files written in code for the importer tests: a binary buffer with its buffer
//! views and accessors, and the GLB container around a JSON document.
#![allow(dead_code, clippy::expect_used, clippy::unwrap_used)]

use serde_json::{Value, json};

/// A binary buffer being filled, with the buffer views and accessors that describe it.
#[derive(Default)]
pub struct Bin {
    pub bytes: Vec<u8>,
    pub views: Vec<Value>,
    pub accessors: Vec<Value>,
}

impl Bin {
    fn view(&mut self, data: &[u8]) -> usize {
        while !self.bytes.len().is_multiple_of(4) {
            self.bytes.push(0);
        }
        let offset = self.bytes.len();
        self.bytes.extend_from_slice(data);
        self.views
            .push(json!({"buffer": 0, "byteOffset": offset, "byteLength": data.len()}));
        self.views.len() - 1
    }

    /// An accessor of f32 values, `kind` `"SCALAR"`, `"VEC3"`, `"VEC4"` or `"MAT4"`; min and
    /// max are written (the specification wants them for positions and animation inputs).
    pub fn floats(&mut self, values: &[f32], kind: &str) -> usize {
        let width = match kind {
            "SCALAR" => 1,
            "VEC2" => 2,
            "VEC3" => 3,
            "VEC4" => 4,
            "MAT4" => 16,
            _ => panic!("kind {kind}"),
        };
        let data: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
        let view = self.view(&data);
        let count = values.len() / width;
        let mut min = vec![f32::MAX; width];
        let mut max = vec![f32::MIN; width];
        for chunk in values.chunks(width) {
            for (k, v) in chunk.iter().enumerate() {
                min[k] = min[k].min(*v);
                max[k] = max[k].max(*v);
            }
        }
        let mut accessor =
            json!({"bufferView": view, "componentType": 5126, "count": count, "type": kind});
        if kind != "MAT4" {
            accessor["min"] = json!(min);
            accessor["max"] = json!(max);
        }
        self.accessors.push(accessor);
        self.accessors.len() - 1
    }

    /// An accessor of u16 values (`"SCALAR"` indices or `"VEC4"` joints).
    pub fn u16s(&mut self, values: &[u16], kind: &str) -> usize {
        let data: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
        let view = self.view(&data);
        let width = if kind == "VEC4" { 4 } else { 1 };
        self.accessors
            .push(json!({"bufferView": view, "componentType": 5123,
            "count": values.len() / width, "type": kind}));
        self.accessors.len() - 1
    }

    /// The buffer of a finished document, to append to (its views and accessors as written,
    /// edits included).
    pub fn from_document(doc: &Value, bytes: Vec<u8>) -> Self {
        let list = |key: &str| doc[key].as_array().cloned().unwrap_or_default();
        Self {
            bytes,
            views: list("bufferViews"),
            accessors: list("accessors"),
        }
    }

    /// Puts the buffer, views and accessors into `doc`.
    pub fn finish(&self, doc: &mut Value) {
        doc["buffers"] = json!([{"byteLength": self.bytes.len()}]);
        doc["bufferViews"] = json!(self.views);
        doc["accessors"] = json!(self.accessors);
    }
}

/// A GLB file: the JSON chunk (space-padded) and the binary chunk (zero-padded).
pub fn glb(doc: &Value, bin: &[u8]) -> Vec<u8> {
    glb_of_text(&serde_json::to_string(doc).unwrap(), bin)
}

/// [`glb`] of JSON `text` as it is (serde_json would drop a repeated key).
pub fn glb_of_text(text: &str, bin: &[u8]) -> Vec<u8> {
    let mut json = text.as_bytes().to_vec();
    while !json.len().is_multiple_of(4) {
        json.push(b' ');
    }
    let mut bin = bin.to_vec();
    while !bin.len().is_multiple_of(4) {
        bin.push(0);
    }
    let total = 12 + 8 + json.len() + 8 + bin.len();
    let mut out = Vec::with_capacity(total);
    out.extend_from_slice(b"glTF");
    out.extend_from_slice(&2u32.to_le_bytes());
    out.extend_from_slice(&(total as u32).to_le_bytes());
    out.extend_from_slice(&(json.len() as u32).to_le_bytes());
    out.extend_from_slice(b"JSON");
    out.extend_from_slice(&json);
    out.extend_from_slice(&(bin.len() as u32).to_le_bytes());
    out.extend_from_slice(b"BIN\0");
    out.extend_from_slice(&bin);
    out
}

/// One triangle: positions (0,0,0), (1,0,0), (0,1,0) and its indices.
pub fn triangle(bin: &mut Bin) -> (usize, usize) {
    let p = bin.floats(&[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0], "VEC3");
    let i = bin.u16s(&[0, 1, 2], "SCALAR");
    (p, i)
}

/// The built-in avatar's skeleton in T-pose as a glTF skin of nodes named by `name(j)` (joint
/// `j` of `builtin::skeleton::JOINTS`), every length times `scale`, plus `extra` nodes
/// `(name, parent joint, translation)`, one skinned triangle, and `extensions` on the root
/// when given. Returns the GLB and each extra node's index.
pub fn builtin_skeleton_glb(
    scale: f32,
    name: impl Fn(usize) -> String,
    extra: &[(&str, usize, [f32; 3])],
    extensions: Option<Value>,
) -> Vec<u8> {
    use glam::{Mat4, Vec3};
    use posecast_rigs::builtin::skeleton::JOINTS;
    let mut bin = Bin::default();
    let (pos, idx) = triangle(&mut bin);
    let joints = bin.u16s(&[0; 12], "VEC4");
    let weights = bin.floats(&[1.0, 0.0, 0.0, 0.0].repeat(3), "VEC4");
    let n = JOINTS.len();
    let head = |j: usize| Vec3::from(JOINTS[j].head.map(|x| x as f32)) * scale;
    let mut nodes: Vec<Value> = (0..n)
        .map(|j| {
            let t = match JOINTS[j].parent {
                Some(p) => head(j) - head(p),
                None => head(j),
            };
            json!({"name": name(j), "translation": t.to_array()})
        })
        .collect();
    let mut world: Vec<Vec3> = (0..n).map(head).collect();
    for (extra_name, parent, t) in extra {
        nodes.push(json!({"name": extra_name, "translation": t}));
        world.push(world[*parent] + Vec3::from(*t));
    }
    let parent_of = |i: usize| -> Option<usize> {
        if i < n {
            JOINTS[i].parent
        } else {
            Some(extra[i - n].1)
        }
    };
    let total = nodes.len();
    for (i, node) in nodes.iter_mut().enumerate() {
        let children: Vec<usize> = (0..total).filter(|&c| parent_of(c) == Some(i)).collect();
        if !children.is_empty() {
            node["children"] = json!(children);
        }
    }
    nodes.push(json!({"name": "body", "mesh": 0, "skin": 0}));
    let mut ibm = Vec::new();
    for w in &world {
        ibm.extend(Mat4::from_translation(-*w).to_cols_array());
    }
    let ibm = bin.floats(&ibm, "MAT4");
    let mut doc = json!({
        "asset": {"version": "2.0"},
        "scenes": [{"nodes": [0, total]}],
        "nodes": nodes,
        "skins": [{"joints": (0..total).collect::<Vec<_>>(), "inverseBindMatrices": ibm}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": pos, "JOINTS_0": joints, "WEIGHTS_0": weights}, "indices": idx}]}]
    });
    if let Some(e) = extensions {
        let used: Vec<String> = e
            .as_object()
            .map(|o| o.keys().cloned().collect())
            .unwrap_or_default();
        doc["extensionsUsed"] = json!(used);
        doc["extensions"] = e;
    }
    bin.finish(&mut doc);
    glb(&doc, &bin.bytes)
}

/// The VRM 1.0 bone of each built-in joint (`sacroiliac` has none: it stays a node between
/// the hips and the legs).
pub fn vrm_bone(hanim: &str) -> Option<&'static str> {
    Some(match hanim {
        "humanoid_root" => "hips",
        "vl5" => "spine",
        "vt10" => "chest",
        "vt1" => "upperChest",
        "vc4" => "neck",
        "skullbase" => "head",
        "l_sternoclavicular" => "leftShoulder",
        "l_shoulder" => "leftUpperArm",
        "l_elbow" => "leftLowerArm",
        "l_wrist" => "leftHand",
        "l_hip" => "leftUpperLeg",
        "l_knee" => "leftLowerLeg",
        "l_ankle" => "leftFoot",
        "l_midtarsal" => "leftToes",
        "r_sternoclavicular" => "rightShoulder",
        "r_shoulder" => "rightUpperArm",
        "r_elbow" => "rightLowerArm",
        "r_wrist" => "rightHand",
        "r_hip" => "rightUpperLeg",
        "r_knee" => "rightLowerLeg",
        "r_ankle" => "rightFoot",
        "r_midtarsal" => "rightToes",
        _ => return None,
    })
}
