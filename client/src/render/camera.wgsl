// The per-frame camera and lighting uniform at group 0, binding 0 of every render pipeline
// (`CameraUniform` in gpu_types.rs), shared by mesh.wgsl, ground.wgsl and lines.wgsl: each is
// built as this file followed by its own source.

struct Camera {
    view_proj: mat4x4<f32>,
    eye: vec4<f32>,
    light: vec4<f32>,
    grid: vec4<f32>,
    background: vec4<f32>,
}

@group(0) @binding(0) var<uniform> camera: Camera;
