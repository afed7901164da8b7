//! The renderer's bind group layouts and render pipelines, built once per colour format.

use super::gpu_types::{LineVertex, SkinVertex, SkinnedVertex};
use super::shader;

/// Depth buffer format of every pass.
pub const DEPTH_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Depth32Float;

/// Layouts and pipelines. Group 0: camera uniform; group 1: one avatar's joint matrices
/// (storage) and constants (uniform).
#[derive(Debug)]
pub struct Pipelines {
    pub camera_layout: wgpu::BindGroupLayout,
    pub avatar_layout: wgpu::BindGroupLayout,
    /// Vertex-shader skinning from [`SkinVertex`] buffers.
    pub skinned: wgpu::RenderPipeline,
    /// Already-skinned [`SkinnedVertex`] buffers (the compute path).
    pub preskinned: wgpu::RenderPipeline,
    pub ground: wgpu::RenderPipeline,
    pub lines: wgpu::RenderPipeline,
}

impl Pipelines {
    #[must_use]
    pub fn new(device: &wgpu::Device, color_format: wgpu::TextureFormat) -> Self {
        let uniform = |binding, visibility| wgpu::BindGroupLayoutEntry {
            binding,
            visibility,
            ty: wgpu::BindingType::Buffer {
                ty: wgpu::BufferBindingType::Uniform,
                has_dynamic_offset: false,
                min_binding_size: None,
            },
            count: None,
        };
        let both = wgpu::ShaderStages::VERTEX_FRAGMENT;
        let storage_in_vertex = |binding| wgpu::BindGroupLayoutEntry {
            binding,
            visibility: wgpu::ShaderStages::VERTEX,
            ty: wgpu::BindingType::Buffer {
                ty: wgpu::BufferBindingType::Storage { read_only: true },
                has_dynamic_offset: false,
                min_binding_size: None,
            },
            count: None,
        };
        let camera_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("camera bind group layout"),
            entries: &[uniform(0, both)],
        });
        let avatar_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("avatar bind group layout"),
            entries: &[
                storage_in_vertex(0),
                uniform(1, both),
                storage_in_vertex(2),
                storage_in_vertex(3),
            ],
        });
        let mesh_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("mesh pipeline layout"),
            bind_group_layouts: &[Some(&camera_layout), Some(&avatar_layout)],
            immediate_size: 0,
        });
        let camera_only = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("camera-only pipeline layout"),
            bind_group_layouts: &[Some(&camera_layout)],
            immediate_size: 0,
        });
        let (camera, skinning) = (shader::CAMERA_WGSL, shader::SKINNING_WGSL);
        let mesh_module = shader::module(
            device,
            "mesh shader",
            &[
                camera,
                skinning,
                shader::MORPH_WGSL,
                include_str!("mesh.wgsl"),
            ],
        );
        let ground_module = shader::module(
            device,
            "ground shader",
            &[camera, include_str!("ground.wgsl")],
        );
        let lines_module = shader::module(
            device,
            "lines shader",
            &[camera, include_str!("lines.wgsl")],
        );

        let target = [Some(wgpu::ColorTargetState {
            format: color_format,
            blend: None,
            write_mask: wgpu::ColorWrites::ALL,
        })];
        let depth = |write: bool, compare| wgpu::DepthStencilState {
            format: DEPTH_FORMAT,
            depth_write_enabled: Some(write),
            depth_compare: Some(compare),
            stencil: wgpu::StencilState::default(),
            bias: wgpu::DepthBiasState::default(),
        };
        let triangles = wgpu::PrimitiveState {
            topology: wgpu::PrimitiveTopology::TriangleList,
            front_face: wgpu::FrontFace::Ccw,
            // Not culled: imported meshes are often open or inconsistently wound, and the
            // fragment shader lights back faces as seen from the camera.
            cull_mode: None,
            ..Default::default()
        };
        let mesh_pipeline = |label, entry, buffer: wgpu::VertexBufferLayout<'static>| {
            device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
                label: Some(label),
                layout: Some(&mesh_layout),
                vertex: wgpu::VertexState {
                    module: &mesh_module,
                    entry_point: Some(entry),
                    compilation_options: wgpu::PipelineCompilationOptions::default(),
                    buffers: &[Some(buffer)],
                },
                primitive: triangles,
                depth_stencil: Some(depth(true, wgpu::CompareFunction::Less)),
                multisample: wgpu::MultisampleState::default(),
                fragment: Some(wgpu::FragmentState {
                    module: &mesh_module,
                    entry_point: Some("fs_lit"),
                    compilation_options: wgpu::PipelineCompilationOptions::default(),
                    targets: &target,
                }),
                multiview_mask: None,
                cache: None,
            })
        };
        let skinned = mesh_pipeline("skinned mesh pipeline", "vs_skinned", SkinVertex::LAYOUT);
        let preskinned = mesh_pipeline(
            "pre-skinned mesh pipeline",
            "vs_preskinned",
            SkinnedVertex::LAYOUT,
        );
        let ground = device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
            label: Some("ground pipeline"),
            layout: Some(&camera_only),
            vertex: wgpu::VertexState {
                module: &ground_module,
                entry_point: Some("vs_ground"),
                compilation_options: wgpu::PipelineCompilationOptions::default(),
                buffers: &[],
            },
            primitive: triangles,
            depth_stencil: Some(depth(true, wgpu::CompareFunction::Less)),
            multisample: wgpu::MultisampleState::default(),
            fragment: Some(wgpu::FragmentState {
                module: &ground_module,
                entry_point: Some("fs_ground"),
                compilation_options: wgpu::PipelineCompilationOptions::default(),
                targets: &target,
            }),
            multiview_mask: None,
            cache: None,
        });
        let lines = device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
            label: Some("overlay lines pipeline"),
            layout: Some(&camera_only),
            vertex: wgpu::VertexState {
                module: &lines_module,
                entry_point: Some("vs_line"),
                compilation_options: wgpu::PipelineCompilationOptions::default(),
                buffers: &[Some(LineVertex::LAYOUT)],
            },
            primitive: wgpu::PrimitiveState {
                topology: wgpu::PrimitiveTopology::LineList,
                ..Default::default()
            },
            // Drawn last and never hidden: bones are inside the mesh.
            depth_stencil: Some(depth(false, wgpu::CompareFunction::Always)),
            multisample: wgpu::MultisampleState::default(),
            fragment: Some(wgpu::FragmentState {
                module: &lines_module,
                entry_point: Some("fs_line"),
                compilation_options: wgpu::PipelineCompilationOptions::default(),
                targets: &target,
            }),
            multiview_mask: None,
            cache: None,
        });
        Self {
            camera_layout,
            avatar_layout,
            skinned,
            preskinned,
            ground,
            lines,
        }
    }
}
