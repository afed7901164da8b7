//! Every struct the GPU reads or writes, laid out by hand: `#[repr(C)]`, bytemuck, and the
//! padding WGSL's alignment rules require spelled out as fields, so the Rust and WGSL layouts can
//! be checked against each other (sizes are asserted at compile time below).

use bytemuck::{Pod, Zeroable};
use glam::{Mat4, Vec3, Vec4};
use posecast_proto::SkinnedMesh;

/// Influences per vertex on the GPU. Meshes with more are reduced with
/// [`SkinnedMesh::with_influences`]`(4)`, which keeps the four heaviest and renormalises them to
/// sum to one (so a vertex still moves rigidly when all its joints move together); meshes with
/// fewer are padded with zero weights. Compare GPU results with the CPU reference on the
/// *reduced* mesh ([`gpu_mesh`] returns it).
pub const GPU_INFLUENCES: usize = 4;

/// The most joints one avatar may have.
///
/// Each avatar owns one storage buffer of `mat4x4<f32>` skinning matrices (64 bytes a joint),
/// rewritten whole on every pose. 1024 joints make that buffer 64 KiB, which is
/// - WebGPU's guaranteed `maxUniformBufferBindingSize`, so the same buffer can be bound as a
///   uniform array on adapters without vertex-stage storage buffers (GL ES 3 class), as bevy's
///   `MAX_JOINTS` is sized for its uniform path;
/// - a bounded upload: 100 avatars re-posed each frame move at most 6.4 MB a frame.
///
/// Humanoid rigs need 20–80 joints (≈ 150 with fingers and a face), so this leaves ample room;
/// the wire format itself allows `u16::MAX` ([`posecast_proto::skeleton::MAX_JOINTS`]).
pub const MAX_JOINTS_PER_AVATAR: usize = 1024;

/// One bind-pose vertex as the GPU reads it, both as a vertex buffer (vertex-shader skinning)
/// and as a storage array (compute skinning), so one buffer serves both paths.
///
/// WGSL: `struct SkinVertex { position: vec3<f32>, normal: vec3<f32>, joints: vec4<u32>,
/// weights: vec4<f32> }`: `vec3` aligns to 16 bytes, hence the two pads; 64 bytes in all.
/// Joints are `u32` rather than `u16`: WGSL storage buffers have no 16-bit integers, and one
/// layout for both paths is worth 8 bytes a vertex.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
pub struct SkinVertex {
    /// Bind-pose position, model space, metres.
    pub position: [f32; 3],
    /// Padding to WGSL's 16-byte `vec3` alignment; always 0.
    pub _pad0: u32,
    /// Bind-pose unit normal, model space.
    pub normal: [f32; 3],
    /// Padding to WGSL's 16-byte `vec3` alignment; always 0.
    pub _pad1: u32,
    /// The four joints that move the vertex, indices into the avatar's skinning matrices.
    pub joints: [u32; 4],
    /// Their weights, summing to one; an unused slot has weight 0.
    pub weights: [f32; 4],
}

/// One skinned vertex written by the compute path, and read back as a vertex buffer when the
/// renderer draws compute-skinned meshes. WGSL: `struct SkinnedVertex { position: vec3<f32>,
/// normal: vec3<f32> }`, 32 bytes.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct SkinnedVertex {
    /// Skinned position, model space, metres.
    pub position: [f32; 3],
    /// Padding to WGSL's 16-byte `vec3` alignment.
    pub _pad0: u32,
    /// Skinned unit normal, model space.
    pub normal: [f32; 3],
    /// Padding to WGSL's 16-byte `vec3` alignment.
    pub _pad1: u32,
}

/// One skinning matrix `M_j = W_j · B_j⁻¹`, column-major like glam and WGSL's `mat4x4<f32>`.
pub type JointMatrix = [[f32; 4]; 4];

/// Per-frame camera and lighting, bound at group 0 of every render pipeline (`Camera` in
/// `camera.wgsl`).
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
pub struct CameraUniform {
    /// Projection · view, world (model) space to clip space.
    pub view_proj: [[f32; 4]; 4],
    /// Camera position in world space; `w` unused.
    pub eye: [f32; 4],
    /// Unit direction *towards* the directional light, world space; `w` is its intensity.
    pub light: [f32; 4],
    /// Ground grid: centre x, centre z, half extent, cell size (metres).
    pub grid: [f32; 4],
    /// Background colour (linear RGB), which the grid fades into with distance; `w` unused.
    pub background: [f32; 4],
}

/// Per-avatar constants, bound at group 1 next to the joint matrices.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
pub struct AvatarUniform {
    /// Base colour, linear RGB; `w` unused.
    pub color: [f32; 4],
}

/// One endpoint of an overlay line (skeleton bones), world space, linear RGB.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
pub struct LineVertex {
    /// Position, world space, metres.
    pub position: [f32; 3],
    /// Colour, linear RGB.
    pub color: [f32; 3],
}

const _: () = assert!(std::mem::size_of::<SkinVertex>() == 64);
const _: () = assert!(std::mem::size_of::<SkinnedVertex>() == 32);
const _: () = assert!(std::mem::size_of::<JointMatrix>() == 64);
const _: () = assert!(std::mem::size_of::<CameraUniform>() == 128);
const _: () = assert!(std::mem::size_of::<AvatarUniform>() == 16);
const _: () = assert!(std::mem::size_of::<LineVertex>() == 24);

impl SkinVertex {
    /// Vertex-buffer layout: position, normal, joints, weights at locations 0–3.
    pub const LAYOUT: wgpu::VertexBufferLayout<'static> = wgpu::VertexBufferLayout {
        array_stride: std::mem::size_of::<Self>() as wgpu::BufferAddress,
        step_mode: wgpu::VertexStepMode::Vertex,
        attributes: &[
            wgpu::VertexAttribute {
                format: wgpu::VertexFormat::Float32x3,
                offset: 0,
                shader_location: 0,
            },
            wgpu::VertexAttribute {
                format: wgpu::VertexFormat::Float32x3,
                offset: 16,
                shader_location: 1,
            },
            wgpu::VertexAttribute {
                format: wgpu::VertexFormat::Uint32x4,
                offset: 32,
                shader_location: 2,
            },
            wgpu::VertexAttribute {
                format: wgpu::VertexFormat::Float32x4,
                offset: 48,
                shader_location: 3,
            },
        ],
    };
}

impl SkinnedVertex {
    /// Vertex-buffer layout: position and normal at locations 0 and 1.
    pub const LAYOUT: wgpu::VertexBufferLayout<'static> = wgpu::VertexBufferLayout {
        array_stride: std::mem::size_of::<Self>() as wgpu::BufferAddress,
        step_mode: wgpu::VertexStepMode::Vertex,
        attributes: &[
            wgpu::VertexAttribute {
                format: wgpu::VertexFormat::Float32x3,
                offset: 0,
                shader_location: 0,
            },
            wgpu::VertexAttribute {
                format: wgpu::VertexFormat::Float32x3,
                offset: 16,
                shader_location: 1,
            },
        ],
    };

    /// [`Self::position`] as a vector.
    #[must_use]
    pub fn position(&self) -> Vec3 {
        Vec3::from(self.position)
    }

    /// [`Self::normal`] as a vector.
    #[must_use]
    pub fn normal(&self) -> Vec3 {
        Vec3::from(self.normal)
    }
}

impl LineVertex {
    /// Vertex-buffer layout: position and colour at locations 0 and 1.
    pub const LAYOUT: wgpu::VertexBufferLayout<'static> = wgpu::VertexBufferLayout {
        array_stride: std::mem::size_of::<Self>() as wgpu::BufferAddress,
        step_mode: wgpu::VertexStepMode::Vertex,
        attributes: &[
            wgpu::VertexAttribute {
                format: wgpu::VertexFormat::Float32x3,
                offset: 0,
                shader_location: 0,
            },
            wgpu::VertexAttribute {
                format: wgpu::VertexFormat::Float32x3,
                offset: 12,
                shader_location: 1,
            },
        ],
    };
}

/// The mesh as the GPU sees it: exactly [`GPU_INFLUENCES`] influences per vertex.
/// Returns the input unchanged (borrowed) when it already has four.
#[must_use]
pub fn gpu_mesh(mesh: &SkinnedMesh) -> std::borrow::Cow<'_, SkinnedMesh> {
    if mesh.influences() == GPU_INFLUENCES {
        std::borrow::Cow::Borrowed(mesh)
    } else {
        std::borrow::Cow::Owned(mesh.with_influences(GPU_INFLUENCES))
    }
}

/// Packs a mesh with [`GPU_INFLUENCES`] influences into GPU vertices.
///
/// # Panics
/// If the mesh does not have exactly [`GPU_INFLUENCES`] influences (pass it through
/// [`gpu_mesh`] first).
#[must_use]
pub fn pack_vertices(mesh: &SkinnedMesh) -> Vec<SkinVertex> {
    assert_eq!(mesh.influences(), GPU_INFLUENCES, "pack a 4-influence mesh");
    mesh.positions()
        .iter()
        .zip(mesh.normals())
        .zip(
            mesh.joints()
                .chunks_exact(4)
                .zip(mesh.weights().chunks_exact(4)),
        )
        .map(|((p, n), (j, w))| SkinVertex {
            position: p.to_array(),
            _pad0: 0,
            normal: n.to_array(),
            _pad1: 0,
            joints: [j[0].into(), j[1].into(), j[2].into(), j[3].into()],
            weights: [w[0], w[1], w[2], w[3]],
        })
        .collect()
}

/// Highest joint index any vertex of `mesh` uses with a non-zero weight, plus one: how many
/// skinning matrices the mesh needs.
#[must_use]
pub fn joints_used(mesh: &SkinnedMesh) -> usize {
    mesh.joints()
        .iter()
        .zip(mesh.weights())
        .filter(|(_, w)| **w > 0.0)
        .map(|(j, _)| usize::from(*j) + 1)
        .max()
        .unwrap_or(1)
}

/// Column-major arrays of skinning matrices, ready for upload.
pub fn pack_matrices(skinning: &[Mat4], out: &mut Vec<JointMatrix>) {
    out.clear();
    out.extend(skinning.iter().map(Mat4::to_cols_array_2d));
}

/// Linear RGB colour with `w = 1`.
#[must_use]
pub fn rgba(color: Vec3) -> [f32; 4] {
    Vec4::from((color, 1.0)).to_array()
}
