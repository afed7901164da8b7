//! The built-in avatar as the export writer's input ([`crate::export::glb`]): the skeleton at
//! rest (= bind), the skinned body with its material, and the sampled clips as LINEAR
//! animations (the root's translation, then each moved joint's rotation, sharing one set of
//! key times).

use super::clips::SampledClip;
use super::mesh::MeshData;
use super::skeleton::{JOINT_COUNT, JOINTS, Rig};
use crate::clip::Interpolation;
use crate::export::ExportError;
use crate::export::glb::{Animation, Channel, Material, Mesh, Model, Output, Primitive};
use glam::{Quat, Vec3};
use posecast_proto::{Skeleton, Transform};

/// The node of the root joint (`humanoid_root`), which root translations move.
const ROOT: usize = 0;

/// Serialises the avatar: skeleton nodes at rest (= bind), the skinned mesh, one skin and the
/// clips as LINEAR animations.
///
/// # Errors
/// Never expected: every input is generated (a test writes the avatar).
pub fn write(rig: &Rig, mesh: &MeshData, clips: &[SampledClip]) -> Result<Vec<u8>, ExportError> {
    let rest = (0..JOINT_COUNT)
        .map(|j| {
            let (t, r) = rig.rest_local(j);
            Transform::from_translation_rotation(t.as_vec3(), r.as_quat())
        })
        .collect();
    let skeleton = Skeleton::new(
        JOINTS.iter().map(|j| j.name.to_owned()).collect(),
        JOINTS.iter().map(|j| j.parent).collect(),
        rest,
        (0..JOINT_COUNT)
            .map(|j| rig.inverse_bind(j).as_mat4())
            .collect(),
    )?;
    let body = Mesh {
        name: "body".into(),
        primitives: vec![Primitive {
            positions: mesh.positions.clone(),
            normals: mesh.normals.clone(),
            joints: mesh.joints.clone(),
            weights: mesh.weights.clone(),
            indices: mesh.indices.iter().map(|&i| u32::from(i)).collect(),
            material: Some(Material {
                name: "skin".into(),
                base_color: [0.80, 0.62, 0.52, 1.0],
                metallic: 0.0,
                roughness: 0.8,
            }),
            targets: Vec::new(),
        }],
        target_names: Vec::new(),
    };
    let animations: Vec<Animation> = clips.iter().map(animation).collect();
    crate::export::glb::write(&Model {
        generator: "posecast make-avatar",
        name: Some("avatar"),
        skeleton: &skeleton,
        mesh: Some(&body),
        animations: &animations,
    })
}

fn animation(clip: &SampledClip) -> Animation {
    let linear = |joint, output| Channel {
        joint,
        interpolation: Interpolation::Linear,
        times: clip.times.clone(),
        output,
    };
    let translation = clip.root_translation.as_ref().map(|keys| {
        linear(
            ROOT,
            Output::Translation(keys.iter().copied().map(Vec3::from_array).collect()),
        )
    });
    let rotations = clip.rotations.iter().map(|(joint, keys)| {
        linear(
            *joint,
            Output::Rotation(keys.iter().copied().map(Quat::from_array).collect()),
        )
    });
    Animation {
        name: clip.name.into(),
        channels: translation.into_iter().chain(rotations).collect(),
        weights: None,
    }
}
