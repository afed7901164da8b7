//! Writes a rig's normalised skinned mesh as binary glTF 2.0 for render clients
//! (`GET /api/assets/{name}/mesh.glb`): joints as nodes `0..n` at their rest transforms, in
//! the description's order and with its names, one skin with the inverse bind matrices, and
//! every mesh as a primitive (POSITION, NORMAL, JOINTS_0 as u16, WEIGHTS_0, u32 indices) of
//! one skinned mesh node. Meshes with more than four influences keep their four heaviest,
//! renormalised.

use crate::asset::AssetMesh;
use posecast_proto::Skeleton;
use serde_json::{Value, json};

struct Bin {
    bytes: Vec<u8>,
    views: Vec<Value>,
    accessors: Vec<Value>,
}

impl Bin {
    /// Appends one accessor over its own 4-byte-aligned buffer view; returns its index.
    fn accessor(
        &mut self,
        data: &[u8],
        count: usize,
        component: u32,
        kind: &str,
        extra: Value,
    ) -> usize {
        while self.bytes.len() % 4 != 0 {
            self.bytes.push(0);
        }
        self.views
            .push(json!({ "buffer": 0, "byteOffset": self.bytes.len(), "byteLength": data.len() }));
        self.bytes.extend_from_slice(data);
        let mut a = json!({ "bufferView": self.views.len() - 1, "componentType": component, "count": count, "type": kind });
        if let (Some(a), Some(extra)) = (a.as_object_mut(), extra.as_object()) {
            a.extend(extra.clone());
        }
        self.accessors.push(a);
        self.accessors.len() - 1
    }
}

fn f32_bytes(values: impl IntoIterator<Item = f32>) -> Vec<u8> {
    values.into_iter().flat_map(f32::to_le_bytes).collect()
}

/// The .glb bytes of `meshes` skinned to `skeleton`.
#[must_use]
pub fn mesh_glb(skeleton: &Skeleton, meshes: &[AssetMesh]) -> Vec<u8> {
    const FLOAT: u32 = 5126;
    const USHORT: u32 = 5123;
    const UINT: u32 = 5125;
    let mut bin = Bin {
        bytes: Vec::new(),
        views: Vec::new(),
        accessors: Vec::new(),
    };
    let mut nodes: Vec<Value> = skeleton
        .names()
        .iter()
        .zip(skeleton.rest())
        .enumerate()
        .map(|(j, (name, t))| {
            let children: Vec<usize> = (0..skeleton.len())
                .filter(|&c| skeleton.parents()[c] == Some(j))
                .collect();
            let mut node = json!({
                "name": name,
                "translation": t.translation.to_array(),
                "rotation": t.rotation.normalize().to_array(),
                "scale": t.scale.to_array(),
            });
            if !children.is_empty() {
                node["children"] = json!(children);
            }
            node
        })
        .collect();
    let ibm = bin.accessor(
        &f32_bytes(
            skeleton
                .inverse_bind()
                .iter()
                .flat_map(|m| m.to_cols_array()),
        ),
        skeleton.len(),
        FLOAT,
        "MAT4",
        json!({}),
    );
    let mut primitives = Vec::new();
    for m in meshes {
        let mesh = if m.mesh.influences() > 4 {
            m.mesh.with_influences(4)
        } else {
            m.mesh.clone()
        };
        let k = mesh.influences();
        let n = mesh.vertex_count();
        let (lo, hi) = mesh.bounds();
        let pos = bin.accessor(
            &f32_bytes(mesh.positions().iter().flat_map(|v| v.to_array())),
            n,
            FLOAT,
            "VEC3",
            json!({ "min": lo.to_array(), "max": hi.to_array() }),
        );
        let nrm = bin.accessor(
            &f32_bytes(mesh.normals().iter().flat_map(|v| v.to_array())),
            n,
            FLOAT,
            "VEC3",
            json!({}),
        );
        let mut joints = Vec::with_capacity(n * 8);
        let mut weights = Vec::with_capacity(n * 4);
        for v in 0..n {
            for i in 0..4 {
                let (j, w) = if i < k {
                    (mesh.joints()[v * k + i], mesh.weights()[v * k + i])
                } else {
                    (0, 0.0)
                };
                joints.extend_from_slice(&j.to_le_bytes());
                weights.push(w);
            }
        }
        let jnt = bin.accessor(&joints, n, USHORT, "VEC4", json!({}));
        let wgt = bin.accessor(&f32_bytes(weights), n, FLOAT, "VEC4", json!({}));
        let idx: Vec<u8> = mesh
            .indices()
            .iter()
            .flat_map(|i| i.to_le_bytes())
            .collect();
        let ind = bin.accessor(&idx, mesh.indices().len(), UINT, "SCALAR", json!({}));
        primitives.push(json!({
            "attributes": { "POSITION": pos, "NORMAL": nrm, "JOINTS_0": jnt, "WEIGHTS_0": wgt },
            "indices": ind,
        }));
    }
    let roots: Vec<usize> = skeleton.roots().collect();
    nodes.push(json!({ "name": "mesh", "mesh": 0, "skin": 0 }));
    let mut scene_nodes = roots.clone();
    scene_nodes.push(nodes.len() - 1);
    while bin.bytes.len() % 4 != 0 {
        bin.bytes.push(0);
    }
    let doc = json!({
        "asset": { "version": "2.0", "generator": "posecast" },
        "scene": 0,
        "scenes": [{ "nodes": scene_nodes }],
        "nodes": nodes,
        "meshes": [{ "name": "mesh", "primitives": primitives }],
        "skins": [{ "joints": (0..skeleton.len()).collect::<Vec<_>>(), "inverseBindMatrices": ibm, "skeleton": roots.first().copied().unwrap_or(0) }],
        "accessors": bin.accessors,
        "bufferViews": bin.views,
        "buffers": [{ "byteLength": bin.bytes.len() }],
    });
    let mut text = doc.to_string().into_bytes();
    while text.len() % 4 != 0 {
        text.push(b' ');
    }
    let total = 12 + 8 + text.len() + 8 + bin.bytes.len();
    let mut out = Vec::with_capacity(total);
    out.extend_from_slice(b"glTF");
    out.extend_from_slice(&2u32.to_le_bytes());
    out.extend_from_slice(&(total as u32).to_le_bytes());
    out.extend_from_slice(&(text.len() as u32).to_le_bytes());
    out.extend_from_slice(b"JSON");
    out.extend_from_slice(&text);
    out.extend_from_slice(&(bin.bytes.len() as u32).to_le_bytes());
    out.extend_from_slice(b"BIN\0");
    out.extend_from_slice(&bin.bytes);
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_exported_mesh_imports_back_identically() {
        let rig = crate::builtin::rig().unwrap();
        let bytes = mesh_glb(rig.skeleton(), &rig.asset.meshes);
        let back = crate::import::gltf::from_slice("export.glb", &bytes)
            .unwrap()
            .remove(0);
        assert_eq!(back.skeleton.names(), rig.skeleton().names());
        assert_eq!(back.skeleton.parents(), rig.skeleton().parents());
        for (a, b) in back
            .skeleton
            .inverse_bind()
            .iter()
            .zip(rig.skeleton().inverse_bind())
        {
            assert!(a.abs_diff_eq(*b, 1e-6));
        }
        let (m0, m1) = (&back.meshes[0].mesh, &rig.asset.meshes[0].mesh);
        assert_eq!(m0.positions(), m1.positions());
        assert_eq!(m0.indices(), m1.indices());
        assert_eq!(m0.vertex_count(), m1.vertex_count());
    }
}
