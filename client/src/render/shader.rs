//! WGSL sources. A shader module is built from shared preludes followed by its own source:
//! every render pipeline's module starts with `camera.wgsl` (the camera uniform at group 0), and
//! every module that skins includes `skinning.wgsl` and `morph.wgsl`, so the compute kernel and
//! the vertex shader run the same morphing and skinning functions.

/// The camera uniform, `camera` at group 0, binding 0 (`CameraUniform`).
pub const CAMERA_WGSL: &str = include_str!("camera.wgsl");

/// The shared skinning function, `skin()`.
pub const SKINNING_WGSL: &str = include_str!("skinning.wgsl");

/// The shared morph-target function, `morph()`; the including module declares its bindings.
pub const MORPH_WGSL: &str = include_str!("morph.wgsl");

/// Builds a shader module from `parts` (preludes, then the module's own source) in order.
#[must_use]
pub fn module(device: &wgpu::Device, label: &str, parts: &[&str]) -> wgpu::ShaderModule {
    device.create_shader_module(wgpu::ShaderModuleDescriptor {
        label: Some(label),
        source: wgpu::ShaderSource::Wgsl(parts.join("\n").into()),
    })
}
