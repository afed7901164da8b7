//! One avatar's GPU resources: its mesh and morph targets (uploaded once), its joint-matrix
//! buffer (rewritten on every pose), its active morph weights and, for the compute path, a
//! buffer of skinned vertices.

use super::bounds::{Aabb, JointBounds};
use super::compute::{SkinningKernel, check_mesh, nonempty};
use super::error::RenderError;
use super::gpu_types::{
    AvatarUniform, JointMatrix, LineVertex, SkinnedVertex, gpu_mesh, pack_matrices, pack_vertices,
    rgba,
};
use super::morph::GpuMorph;
use glam::Vec3;
use posecast_proto::fk::PoseBuffers;
use posecast_proto::{Skeleton, SkinnedMesh, Transform};
use wgpu::util::DeviceExt;

/// Compute-path resources: skinned vertices, written by the kernel and drawn as vertices.
#[derive(Debug)]
struct ComputeOutput {
    skinned: wgpu::Buffer,
    bind_group: wgpu::BindGroup,
}

#[derive(Debug)]
pub(crate) struct GpuAvatar {
    skeleton: Skeleton,
    bounds: JointBounds,
    pose: PoseBuffers,
    staging: Vec<JointMatrix>,
    vertices: wgpu::Buffer,
    indices: Option<wgpu::Buffer>,
    /// Indices to draw, or vertices when the mesh has no index list.
    draw_count: u32,
    vertex_count: usize,
    joints: wgpu::Buffer,
    uniform: wgpu::Buffer,
    morph: GpuMorph,
    pub(crate) bind_group: wgpu::BindGroup,
    compute: Option<ComputeOutput>,
    label: String,
}

impl GpuAvatar {
    /// Each joint's parent (none for a root), as in its skeleton.
    pub(crate) fn parents(&self) -> &[Option<usize>] {
        self.skeleton.parents()
    }

    pub(crate) fn new(
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        layout: &wgpu::BindGroupLayout,
        label: String,
        skeleton: &Skeleton,
        mesh: &SkinnedMesh,
        color: Vec3,
    ) -> Result<Self, RenderError> {
        if skeleton.len() > super::gpu_types::MAX_JOINTS_PER_AVATAR {
            return Err(RenderError::TooManyJoints {
                joints: skeleton.len(),
            });
        }
        let used = check_mesh(device, mesh)?;
        if used > skeleton.len() {
            return Err(RenderError::MeshJointOutOfRange {
                joint: used - 1,
                joints: skeleton.len(),
            });
        }
        let mesh = gpu_mesh(mesh);
        let morph = match GpuMorph::new(device, &label, &mesh) {
            Ok(morph) => morph,
            Err(error) => {
                // The body still draws and weights are accepted; the face just does not move.
                tracing::warn!(avatar = %label, %error, "morph targets not shown");
                GpuMorph::ignoring(device, &label, &mesh)
            }
        };
        let packed = pack_vertices(&mesh);
        let vertices = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some(&format!("{label} bind-pose vertices")),
            contents: nonempty(bytemuck::cast_slice(&packed)),
            usage: wgpu::BufferUsages::VERTEX | wgpu::BufferUsages::STORAGE,
        });
        let (indices, draw_count) = if mesh.indices().is_empty() {
            (None, (mesh.vertex_count() / 3 * 3) as u32)
        } else {
            let buffer = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(&format!("{label} indices")),
                contents: bytemuck::cast_slice(mesh.indices()),
                usage: wgpu::BufferUsages::INDEX,
            });
            (Some(buffer), mesh.indices().len() as u32)
        };
        let joints = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(&format!("{label} joint matrices")),
            size: (skeleton.len() * std::mem::size_of::<JointMatrix>()) as u64,
            usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let uniform = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some(&format!("{label} constants")),
            contents: bytemuck::bytes_of(&AvatarUniform { color: rgba(color) }),
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
        });
        let bind_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some(&format!("{label} bind group")),
            layout,
            entries: &[
                wgpu::BindGroupEntry {
                    binding: 0,
                    resource: joints.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 1,
                    resource: uniform.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 2,
                    resource: morph.deltas().as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 3,
                    resource: morph.state().as_entire_binding(),
                },
            ],
        });
        let mut avatar = Self {
            skeleton: skeleton.clone(),
            bounds: JointBounds::new(skeleton.inverse_bind(), &mesh),
            pose: PoseBuffers::new(skeleton),
            staging: Vec::with_capacity(skeleton.len()),
            vertices,
            indices,
            draw_count,
            vertex_count: mesh.vertex_count(),
            joints,
            uniform,
            morph,
            bind_group,
            compute: None,
            label,
        };
        avatar.set_pose(queue, skeleton.rest())?;
        Ok(avatar)
    }

    /// `W_j` by forward kinematics, `M_j = W_j · B_j⁻¹`, both into preallocated buffers; uploads
    /// only the matrices.
    pub(crate) fn set_pose(
        &mut self,
        queue: &wgpu::Queue,
        locals: &[Transform],
    ) -> Result<(), RenderError> {
        if locals.len() != self.skeleton.len() {
            return Err(RenderError::Length {
                what: "pose",
                expected: self.skeleton.len(),
                actual: locals.len(),
            });
        }
        self.pose.update(&self.skeleton, locals);
        pack_matrices(&self.pose.skinning, &mut self.staging);
        queue.write_buffer(&self.joints, 0, bytemuck::cast_slice(&self.staging));
        Ok(())
    }

    /// Sets the weights of the mesh's morph targets (mesh order, missing entries 0).
    pub(crate) fn set_morph_weights(
        &mut self,
        queue: &wgpu::Queue,
        weights: &[f32],
    ) -> Result<(), RenderError> {
        self.morph.set_weights(queue, weights)
    }

    /// The mesh's morph targets (what [`GpuAvatar::set_morph_weights`] indexes).
    pub(crate) fn morph_targets(&self) -> usize {
        self.morph.targets()
    }

    pub(crate) fn set_color(&self, queue: &wgpu::Queue, color: Vec3) {
        queue.write_buffer(
            &self.uniform,
            0,
            bytemuck::bytes_of(&AvatarUniform { color: rgba(color) }),
        );
    }

    /// A box holding every skinned vertex of the current pose.
    pub(crate) fn bounds(&self) -> Option<Aabb> {
        self.bounds.skinned(&self.pose.world)
    }

    /// Appends one line per bone (joint to parent) of the current pose.
    pub(crate) fn bone_lines(&self, color: Vec3, out: &mut Vec<LineVertex>) {
        let world = &self.pose.world;
        for (j, parent) in self.skeleton.parents().iter().enumerate() {
            let (Some(p), Some(w)) = (*parent, world.get(j)) else {
                continue;
            };
            let Some(wp) = world.get(p) else { continue };
            for m in [wp, w] {
                out.push(LineVertex {
                    position: m.w_axis.truncate().to_array(),
                    color: color.to_array(),
                });
            }
        }
    }

    /// Creates (once) the buffer the compute path skins into.
    pub(crate) fn ensure_compute(&mut self, device: &wgpu::Device, kernel: &SkinningKernel) {
        if self.compute.is_some() {
            return;
        }
        let skinned = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(&format!("{} compute-skinned vertices", self.label)),
            size: (self.vertex_count.max(1) * std::mem::size_of::<SkinnedVertex>()) as u64,
            usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::VERTEX,
            mapped_at_creation: false,
        });
        let bind_group = kernel.bind_group(
            device,
            &format!("{} compute skinning bind group", self.label),
            &self.vertices,
            &self.joints,
            &skinned,
            &self.morph,
        );
        self.compute = Some(ComputeOutput {
            skinned,
            bind_group,
        });
    }

    /// Records the compute dispatch, when the compute path is set up.
    pub(crate) fn encode_compute(&self, pass: &mut wgpu::ComputePass<'_>, kernel: &SkinningKernel) {
        if let Some(compute) = &self.compute {
            kernel.encode(pass, &compute.bind_group, self.vertex_count);
        }
    }

    /// Records the draw: from compute-skinned vertices when `compute` is set (and the buffer
    /// exists), else from the bind-pose vertices with vertex-shader skinning. The caller has
    /// set the matching pipeline.
    pub(crate) fn draw(&self, pass: &mut wgpu::RenderPass<'_>, compute: bool) {
        let source = match (&self.compute, compute) {
            (Some(c), true) => &c.skinned,
            _ => &self.vertices,
        };
        pass.set_bind_group(1, &self.bind_group, &[]);
        pass.set_vertex_buffer(0, source.slice(..));
        match &self.indices {
            Some(indices) => {
                pass.set_index_buffer(indices.slice(..), wgpu::IndexFormat::Uint32);
                pass.draw_indexed(0..self.draw_count, 0, 0..1);
            }
            None => pass.draw(0..self.draw_count, 0..1),
        }
    }

    pub(crate) fn has_compute(&self) -> bool {
        self.compute.is_some()
    }
}
