//! What an import produces: a skeleton, the meshes skinned to it, its clips and what is known
//! about the source's conventions. Rig normalisation takes an [`Asset`] from here.

use glam::Vec3;
use posecast_proto::{Skeleton, SkinnedMesh};

use crate::clip::Clip;

/// One imported rig with its meshes and clips.
#[derive(Clone, Debug)]
pub struct Asset {
    /// File stem, plus `#<skin>` when a file holds several rigs.
    pub name: String,
    /// Joints parent-before-child. Rest transforms are the file's rest pose; inverse binds are
    /// the file's (glTF IBMs, CSE169 `bindings` inverted) or, where the format has none (BVH),
    /// the inverses of the rest-pose world matrices.
    pub skeleton: Skeleton,
    /// Meshes in bind space; joint indices refer to `skeleton`.
    pub meshes: Vec<AssetMesh>,
    /// Clips with one channel slot per skeleton joint.
    pub clips: Vec<Clip>,
    /// The format and conventions of the file it came from.
    pub source: SourceInfo,
    /// CSE169 `boxmin`/`boxmax` per joint (course defaults where the file has none).
    pub boxes: Option<Vec<(Vec3, Vec3)>>,
    /// Expressions the file defines over its morph targets (VRM 0.x `blendShapeMaster`, VRM
    /// 1.0 `expressions`); empty for other files.
    pub expressions: Vec<posecast_proto::expressions::Expression>,
}

/// A named skinned mesh.
#[derive(Clone, Debug)]
pub struct AssetMesh {
    /// The mesh's name from the file (glTF: its name or `mesh<index>`, plus `#<primitive>`
    /// when it has several; CSE169: the `.skin` file's name).
    pub name: String,
    /// Its geometry and skin weights, in bind space.
    pub mesh: SkinnedMesh,
}

/// The format an asset came from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SourceFormat {
    /// glTF 2.0 (`.gltf`, `.glb`), including VRM (`.vrm`) and VRM animations (`.vrma`).
    Gltf,
    /// CSE169 `.skel` (+ `.skin`, `.anim`).
    Cse169,
    /// Biovision hierarchy (`.bvh`).
    Bvh,
}

/// A coordinate axis named as "up".
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum UpAxis {
    /// +Y is up (posecast's own convention).
    Y,
    /// +Z is up (Blender, 3ds Max and other Z-up tools).
    Z,
}

/// What the importer learned about the source's conventions.
#[derive(Clone, Debug, PartialEq)]
pub struct SourceInfo {
    /// The file format the asset was imported from.
    pub format: SourceFormat,
    /// Up axis of the bind-space data (mesh vertices, inverse binds). glTF files exported from
    /// Z-up tools keep Z-up mesh data under a `Z_UP` node rotating −90° about X; that node is
    /// folded into the root joints, so posed world space is Y-up while this says [`UpAxis::Z`].
    /// BVH and CSE169 are Y-up by convention.
    pub up_axis: UpAxis,
    /// Metres per file unit when the format says (glTF: 1); `None` when unknown (BVH, CSE169).
    pub metres_per_unit: Option<f32>,
    /// Joints that are not joints in the file but nodes kept to place them (glTF non-joint
    /// ancestors that are animated or cannot be folded into their children).
    pub helper_joints: Vec<usize>,
    /// BVH `End Site`s: (joint, offset in the joint's space).
    pub end_sites: Vec<(usize, Vec3)>,
    /// Anything skipped, defaulted or approximated on import.
    pub notes: Vec<String>,
    /// Joint name → H-Anim name when the file says (a VRM humanoid's bone map): the
    /// normalisation takes it as the mapping, over guesses from names.
    pub bone_map: Option<std::collections::BTreeMap<String, String>>,
}

impl SourceInfo {
    /// Info for a format with its default conventions and no notes.
    #[must_use]
    pub fn new(format: SourceFormat) -> Self {
        Self {
            format,
            up_axis: UpAxis::Y,
            metres_per_unit: match format {
                SourceFormat::Gltf => Some(1.0),
                SourceFormat::Cse169 | SourceFormat::Bvh => None,
            },
            helper_joints: Vec::new(),
            end_sites: Vec::new(),
            notes: Vec::new(),
            bone_map: None,
        }
    }
}
