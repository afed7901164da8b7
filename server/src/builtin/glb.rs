//! Writes the built-in avatar as binary glTF 2.0: one buffer, one buffer view per accessor,
//! joints as nodes `0..JOINT_COUNT` (so a skin joint index is its node index) followed by the
//! skinned mesh node.

use super::clips::SampledClip;
use super::mesh::MeshData;
use super::skeleton::{JOINT_COUNT, JOINTS, Rig};
use gltf::binary::{Glb, Header};
use gltf::json::{self, Index, validation::Checked::Valid, validation::USize64};
use serde_json::json;
use std::borrow::Cow;
use std::collections::BTreeMap;

/// Why the document could not be serialised (never expected: every input is generated).
#[derive(Debug, thiserror::Error)]
pub enum WriteError {
    #[error("serialising the glTF JSON: {0}")]
    Json(#[from] serde_json::Error),
    #[error("writing the GLB container: {0}")]
    Glb(#[from] gltf::Error),
}

/// The binary chunk and the JSON root filled side by side.
struct Builder {
    root: json::Root,
    bin: Vec<u8>,
}

impl Builder {
    /// Appends `bytes` as a new buffer view, 4-byte aligned.
    fn view(
        &mut self,
        bytes: &[u8],
        target: Option<json::buffer::Target>,
    ) -> Index<json::buffer::View> {
        while self.bin.len() % 4 != 0 {
            self.bin.push(0);
        }
        let offset = self.bin.len();
        self.bin.extend_from_slice(bytes);
        self.root.push(json::buffer::View {
            buffer: Index::new(0),
            byte_length: USize64::from(bytes.len()),
            byte_offset: Some(USize64::from(offset)),
            byte_stride: None,
            name: None,
            target: target.map(Valid),
            extensions: None,
            extras: Default::default(),
        })
    }

    #[allow(clippy::too_many_arguments)]
    fn accessor(
        &mut self,
        bytes: &[u8],
        count: usize,
        component: json::accessor::ComponentType,
        kind: json::accessor::Type,
        target: Option<json::buffer::Target>,
        bounds: Option<(serde_json::Value, serde_json::Value)>,
    ) -> Index<json::Accessor> {
        let view = self.view(bytes, target);
        let (min, max) = bounds.unzip();
        self.root.push(json::Accessor {
            buffer_view: Some(view),
            byte_offset: None,
            count: USize64::from(count),
            component_type: Valid(json::accessor::GenericComponentType(component)),
            extensions: None,
            extras: Default::default(),
            type_: Valid(kind),
            min,
            max,
            name: None,
            normalized: false,
            sparse: None,
        })
    }

    fn f32s<const N: usize>(
        &mut self,
        values: &[[f32; N]],
        target: Option<json::buffer::Target>,
        bounds: bool,
    ) -> Index<json::Accessor> {
        let kind = match N {
            1 => json::accessor::Type::Scalar,
            3 => json::accessor::Type::Vec3,
            4 => json::accessor::Type::Vec4,
            _ => json::accessor::Type::Mat4,
        };
        let bytes: Vec<u8> = values
            .iter()
            .flatten()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        let bounds = bounds.then(|| {
            let mut lo = [f32::INFINITY; N];
            let mut hi = [f32::NEG_INFINITY; N];
            for v in values {
                for c in 0..N {
                    lo[c] = lo[c].min(v[c]);
                    hi[c] = hi[c].max(v[c]);
                }
            }
            (json!(lo.to_vec()), json!(hi.to_vec()))
        });
        let component = json::accessor::ComponentType::F32;
        self.accessor(&bytes, values.len(), component, kind, target, bounds)
    }
}

/// Serialises the avatar: skeleton nodes at rest (= bind), the skinned mesh, one skin and the
/// clips as LINEAR animations.
pub fn write(rig: &Rig, mesh: &MeshData, clips: &[SampledClip]) -> Result<Vec<u8>, WriteError> {
    let mut b = Builder {
        root: json::Root {
            asset: json::Asset {
                copyright: None,
                extensions: None,
                extras: Default::default(),
                generator: Some("posecast make-avatar".into()),
                min_version: None,
                version: "2.0".into(),
            },
            ..Default::default()
        },
        bin: Vec::new(),
    };
    let array = Some(json::buffer::Target::ArrayBuffer);

    let positions: Vec<[f32; 3]> = mesh.positions.iter().map(|p| p.to_array()).collect();
    let normals: Vec<[f32; 3]> = mesh.normals.iter().map(|n| n.to_array()).collect();
    let position = b.f32s(&positions, array, true);
    let normal = b.f32s(&normals, array, false);
    let joint_bytes: Vec<u8> = mesh
        .joints
        .iter()
        .flatten()
        .flat_map(|j| j.to_le_bytes())
        .collect();
    let joints = b.accessor(
        &joint_bytes,
        mesh.joints.len(),
        json::accessor::ComponentType::U16,
        json::accessor::Type::Vec4,
        array,
        None,
    );
    let weights = b.f32s(&mesh.weights, array, false);
    let index_bytes: Vec<u8> = mesh.indices.iter().flat_map(|i| i.to_le_bytes()).collect();
    let indices = b.accessor(
        &index_bytes,
        mesh.indices.len(),
        json::accessor::ComponentType::U16,
        json::accessor::Type::Scalar,
        Some(json::buffer::Target::ElementArrayBuffer),
        None,
    );
    let inverse_binds: Vec<[f32; 16]> = (0..JOINT_COUNT)
        .map(|j| rig.inverse_bind(j).as_mat4().to_cols_array())
        .collect();
    let inverse_binds = b.f32s(&inverse_binds, None, false);

    let material = b.root.push(json::Material {
        name: Some("skin".into()),
        pbr_metallic_roughness: json::material::PbrMetallicRoughness {
            base_color_factor: json::material::PbrBaseColorFactor([0.80, 0.62, 0.52, 1.0]),
            metallic_factor: json::material::StrengthFactor(0.0),
            roughness_factor: json::material::StrengthFactor(0.8),
            ..Default::default()
        },
        ..Default::default()
    });
    let attributes = BTreeMap::from([
        (Valid(json::mesh::Semantic::Positions), position),
        (Valid(json::mesh::Semantic::Normals), normal),
        (Valid(json::mesh::Semantic::Joints(0)), joints),
        (Valid(json::mesh::Semantic::Weights(0)), weights),
    ]);
    let body = b.root.push(json::Mesh {
        extensions: None,
        extras: Default::default(),
        name: Some("body".into()),
        primitives: vec![json::mesh::Primitive {
            attributes,
            extensions: None,
            extras: Default::default(),
            indices: Some(indices),
            material: Some(material),
            mode: Valid(json::mesh::Mode::Triangles),
            targets: None,
        }],
        weights: None,
    });

    for (j, def) in JOINTS.iter().enumerate() {
        let (t, r) = rig.rest_local(j);
        let children: Vec<Index<json::Node>> = JOINTS
            .iter()
            .enumerate()
            .filter(|(_, c)| c.parent == Some(j))
            .map(|(c, _)| Index::new(c as u32))
            .collect();
        b.root.push(json::Node {
            name: Some(def.name.into()),
            translation: Some(t.as_vec3().to_array()),
            rotation: Some(json::scene::UnitQuaternion(r.as_quat().to_array())),
            children: (!children.is_empty()).then_some(children),
            ..Default::default()
        });
    }
    let skin = b.root.push(json::Skin {
        extensions: None,
        extras: Default::default(),
        inverse_bind_matrices: Some(inverse_binds),
        joints: (0..JOINT_COUNT as u32).map(Index::new).collect(),
        name: Some("avatar".into()),
        skeleton: Some(Index::new(0)),
    });
    let body_node = b.root.push(json::Node {
        name: Some("body".into()),
        mesh: Some(body),
        skin: Some(skin),
        ..Default::default()
    });
    let scene = b.root.push(json::Scene {
        extensions: None,
        extras: Default::default(),
        name: Some("avatar".into()),
        nodes: vec![Index::new(0), body_node],
    });
    b.root.scene = Some(scene);

    for clip in clips {
        write_clip(&mut b, clip);
    }

    while b.bin.len() % 4 != 0 {
        b.bin.push(0);
    }
    b.root.push(json::Buffer {
        byte_length: USize64::from(b.bin.len()),
        name: None,
        uri: None,
        extensions: None,
        extras: Default::default(),
    });
    let json = b.root.to_vec()?;
    let glb = Glb {
        header: Header {
            magic: *b"glTF",
            version: 2,
            // Recomputed by the writer.
            length: 0,
        },
        json: Cow::Owned(json),
        bin: Some(Cow::Owned(b.bin)),
    };
    Ok(glb.to_vec()?)
}

fn write_clip(b: &mut Builder, clip: &SampledClip) {
    let times: Vec<[f32; 1]> = clip.times.iter().map(|&t| [t]).collect();
    let input = b.f32s(&times, None, true);
    let mut channels = Vec::new();
    let mut samplers = Vec::new();
    let mut channel = |node: usize, output, property| {
        samplers.push(json::animation::Sampler {
            extensions: None,
            extras: Default::default(),
            input,
            interpolation: Valid(json::animation::Interpolation::Linear),
            output,
        });
        channels.push(json::animation::Channel {
            sampler: Index::new(samplers.len() as u32 - 1),
            target: json::animation::Target {
                extensions: None,
                extras: Default::default(),
                node: Index::new(node as u32),
                path: Valid(property),
            },
            extensions: None,
            extras: Default::default(),
        });
    };
    if let Some(translation) = &clip.root_translation {
        let output = b.f32s(translation, None, false);
        channel(0, output, json::animation::Property::Translation);
    }
    for (joint, keys) in &clip.rotations {
        let output = b.f32s(keys, None, false);
        channel(*joint, output, json::animation::Property::Rotation);
    }
    b.root.push(json::Animation {
        extensions: None,
        extras: Default::default(),
        channels,
        name: Some(clip.name.into()),
        samplers,
    });
}
