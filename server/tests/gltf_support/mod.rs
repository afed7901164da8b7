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
        while self.bytes.len() % 4 != 0 {
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

    /// Puts the buffer, views and accessors into `doc`.
    pub fn finish(&self, doc: &mut Value) {
        doc["buffers"] = json!([{"byteLength": self.bytes.len()}]);
        doc["bufferViews"] = json!(self.views);
        doc["accessors"] = json!(self.accessors);
    }
}

/// A GLB file: the JSON chunk (space-padded) and the binary chunk (zero-padded).
pub fn glb(doc: &Value, bin: &[u8]) -> Vec<u8> {
    let mut json = serde_json::to_vec(doc).unwrap();
    while json.len() % 4 != 0 {
        json.push(b' ');
    }
    let mut bin = bin.to_vec();
    while bin.len() % 4 != 0 {
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
