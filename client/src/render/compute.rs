//! Compute skinning: the mesh (and its morph targets) is uploaded once, each call uploads only
//! the skinning matrices `M_j = W_j · B_j⁻¹` (and the active morph weights), runs the shared
//! `morph()` and `skin()` over every vertex, and (for [`ComputeSkinner`])
//! reads the skinned positions and normals back. The renderer uses [`SkinningKernel`] directly
//! to skin into a vertex buffer it then draws.

use super::error::RenderError;
use super::gpu::Gpu;
use super::gpu_types::{
    JointMatrix, MAX_JOINTS_PER_AVATAR, SkinVertex, SkinnedVertex, gpu_mesh, joints_used,
    pack_matrices, pack_vertices,
};
use super::morph::GpuMorph;
use super::shader;
use glam::{Mat4, Vec3};
use posecast_proto::SkinnedMesh;
use wgpu::util::DeviceExt;

const WORKGROUP_SIZE: u32 = 64;

/// The compute pipeline and its bind group layout, shared by every mesh it skins.
#[derive(Debug)]
pub struct SkinningKernel {
    pipeline: wgpu::ComputePipeline,
    layout: wgpu::BindGroupLayout,
}

impl SkinningKernel {
    /// Builds the pipeline (the shared `morph()` and `skin()` run by `compute.wgsl`'s
    /// `skin_vertices`) and its
    /// bind group layout on `device`.
    #[must_use]
    pub fn new(device: &wgpu::Device) -> Self {
        let storage = |binding, read_only| wgpu::BindGroupLayoutEntry {
            binding,
            visibility: wgpu::ShaderStages::COMPUTE,
            ty: wgpu::BindingType::Buffer {
                ty: wgpu::BufferBindingType::Storage { read_only },
                has_dynamic_offset: false,
                min_binding_size: None,
            },
            count: None,
        };
        let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("compute skinning bind group layout"),
            entries: &[
                storage(0, true),
                storage(1, true),
                storage(2, false),
                storage(3, true),
                storage(4, true),
            ],
        });
        let pipeline_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("compute skinning pipeline layout"),
            bind_group_layouts: &[Some(&layout)],
            immediate_size: 0,
        });
        let module = shader::module(
            device,
            "compute skinning shader",
            &[
                shader::SKINNING_WGSL,
                shader::MORPH_WGSL,
                include_str!("compute.wgsl"),
            ],
        );
        let pipeline = device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
            label: Some("compute skinning pipeline"),
            layout: Some(&pipeline_layout),
            module: &module,
            entry_point: Some("skin_vertices"),
            compilation_options: wgpu::PipelineCompilationOptions::default(),
            cache: None,
        });
        Self { pipeline, layout }
    }

    /// The most vertices one dispatch skins on `device`: the storage binding of the bind-pose
    /// vertices and the one-dimensional dispatch both bound it.
    #[must_use]
    pub fn max_vertices(device: &wgpu::Device) -> usize {
        let limits = device.limits();
        let by_binding =
            limits.max_storage_buffer_binding_size as usize / std::mem::size_of::<SkinVertex>();
        let by_dispatch =
            limits.max_compute_workgroups_per_dimension as usize * WORKGROUP_SIZE as usize;
        by_binding.min(by_dispatch)
    }

    /// Binds bind-pose `vertices` ([`SkinVertex`]), `joints` ([`JointMatrix`]), `output`
    /// ([`SkinnedVertex`], one per vertex) and the mesh's `morph` targets.
    #[must_use]
    pub fn bind_group(
        &self,
        device: &wgpu::Device,
        label: &str,
        vertices: &wgpu::Buffer,
        joints: &wgpu::Buffer,
        output: &wgpu::Buffer,
        morph: &GpuMorph,
    ) -> wgpu::BindGroup {
        device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some(label),
            layout: &self.layout,
            entries: &[
                wgpu::BindGroupEntry {
                    binding: 0,
                    resource: vertices.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 1,
                    resource: joints.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 2,
                    resource: output.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 3,
                    resource: morph.deltas().as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 4,
                    resource: morph.state().as_entire_binding(),
                },
            ],
        })
    }

    /// Records a dispatch skinning `vertex_count` vertices into the bind group's output.
    pub fn encode(
        &self,
        pass: &mut wgpu::ComputePass<'_>,
        bind_group: &wgpu::BindGroup,
        vertex_count: usize,
    ) {
        let groups = (vertex_count as u32).div_ceil(WORKGROUP_SIZE);
        pass.set_pipeline(&self.pipeline);
        pass.set_bind_group(0, bind_group, &[]);
        pass.dispatch_workgroups(groups, 1, 1);
    }
}

/// Checks a mesh fits one dispatch and one joint buffer; returns the joints it needs.
pub(crate) fn check_mesh(device: &wgpu::Device, mesh: &SkinnedMesh) -> Result<usize, RenderError> {
    let limit = SkinningKernel::max_vertices(device);
    if mesh.vertex_count() > limit {
        return Err(RenderError::TooManyVertices {
            vertices: mesh.vertex_count(),
            limit,
        });
    }
    let joints = joints_used(mesh);
    if joints > MAX_JOINTS_PER_AVATAR {
        return Err(RenderError::TooManyJoints { joints });
    }
    Ok(joints)
}

/// Morphs and skins one mesh on the GPU with a compute shader and reads the result back: the
/// path tests compare with `posecast_proto::morph::morph_cpu` then
/// `posecast_proto::skinning::skin_cpu`.
#[derive(Debug)]
pub struct ComputeSkinner {
    gpu: Gpu,
    kernel: SkinningKernel,
    vertex_count: usize,
    joints: usize,
    joint_buffer: wgpu::Buffer,
    output: wgpu::Buffer,
    readback: wgpu::Buffer,
    bind_group: wgpu::BindGroup,
    staging: Vec<JointMatrix>,
    morph: GpuMorph,
}

impl ComputeSkinner {
    /// Uploads `mesh` (reduced to four influences per vertex, see
    /// [`GPU_INFLUENCES`](super::gpu_types::GPU_INFLUENCES)) and builds the pipeline.
    pub fn new(gpu: &Gpu, mesh: &SkinnedMesh) -> Result<Self, RenderError> {
        let device = &gpu.device;
        let joints = check_mesh(device, mesh)?;
        gpu.scoped("creating the compute skinner", || {
            let mesh = gpu_mesh(mesh);
            let vertices = pack_vertices(&mesh);
            let vertex_buffer = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("compute skinning bind-pose vertices"),
                contents: nonempty(bytemuck::cast_slice(&vertices)),
                usage: wgpu::BufferUsages::STORAGE,
            });
            let joint_buffer = device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("compute skinning joint matrices"),
                size: (joints * std::mem::size_of::<JointMatrix>()) as u64,
                usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            });
            let output_size = (vertices.len().max(1) * std::mem::size_of::<SkinnedVertex>()) as u64;
            let output = device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("compute skinning output"),
                size: output_size,
                usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
                mapped_at_creation: false,
            });
            let readback = device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("compute skinning readback"),
                size: output_size,
                usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            });
            let morph = GpuMorph::new(device, "compute skinning", &mesh)?;
            let kernel = SkinningKernel::new(device);
            let bind_group = kernel.bind_group(
                device,
                "compute skinning bind group",
                &vertex_buffer,
                &joint_buffer,
                &output,
                &morph,
            );
            Ok(Self {
                gpu: gpu.clone(),
                kernel,
                vertex_count: vertices.len(),
                joints,
                joint_buffer,
                output,
                readback,
                bind_group,
                staging: Vec::with_capacity(joints),
                morph,
            })
        })
    }

    /// How many skinning matrices [`ComputeSkinner::skin`] needs at least.
    #[must_use]
    pub fn joints(&self) -> usize {
        self.joints
    }

    /// Number of vertices the uploaded mesh has (and [`ComputeSkinner::skin`] returns).
    #[must_use]
    pub fn vertex_count(&self) -> usize {
        self.vertex_count
    }

    /// Sets the weights of the mesh's morph targets for the next [`ComputeSkinner::skin`]
    /// (mesh order, missing entries 0; see [`GpuMorph::set_weights`]).
    ///
    /// # Errors
    /// More weights than the mesh has targets.
    pub fn set_morph_weights(&mut self, weights: &[f32]) -> Result<(), RenderError> {
        self.morph.set_weights(&self.gpu.queue, weights)
    }

    /// Skins the mesh with `skinning[j] = M_j = W_j · B_j⁻¹` (model space) and returns the
    /// skinned positions and unit normals, one per vertex. Extra matrices are ignored.
    pub fn skin(&mut self, skinning: &[Mat4]) -> Result<(Vec<Vec3>, Vec<Vec3>), RenderError> {
        let skinned = self.skin_raw(skinning)?;
        Ok(skinned.iter().map(|v| (v.position(), v.normal())).unzip())
    }

    /// As [`ComputeSkinner::skin`], returning the GPU's vertex structs.
    pub fn skin_raw(&mut self, skinning: &[Mat4]) -> Result<Vec<SkinnedVertex>, RenderError> {
        let Some(used) = skinning.get(..self.joints) else {
            return Err(RenderError::Length {
                what: "skinning matrices",
                expected: self.joints,
                actual: skinning.len(),
            });
        };
        pack_matrices(used, &mut self.staging);
        let gpu = self.gpu.clone();
        gpu.scoped("compute skinning", || {
            gpu.queue
                .write_buffer(&self.joint_buffer, 0, bytemuck::cast_slice(&self.staging));
            let mut encoder = gpu
                .device
                .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                    label: Some("compute skinning encoder"),
                });
            {
                let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                    label: Some("compute skinning pass"),
                    timestamp_writes: None,
                });
                self.kernel
                    .encode(&mut pass, &self.bind_group, self.vertex_count);
            }
            encoder.copy_buffer_to_buffer(&self.output, 0, &self.readback, 0, None);
            gpu.queue.submit([encoder.finish()]);
            let bytes = gpu.read_buffer(&self.readback, "skinned vertices")?;
            let mut vertices: Vec<SkinnedVertex> = bytemuck::pod_collect_to_vec(&bytes);
            vertices.truncate(self.vertex_count);
            Ok(vertices)
        })
    }
}

/// wgpu refuses zero-sized bindings; an empty mesh gets one dummy element.
pub(crate) fn nonempty(bytes: &[u8]) -> &[u8] {
    const ZEROS: [u8; 64] = [0; 64];
    if bytes.is_empty() { &ZEROS } else { bytes }
}
