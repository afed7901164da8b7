//! WGSL sources. Every module that skins is built as `skinning.wgsl` followed by its own
//! source, so the compute kernel and the vertex shader run the same skinning function.

/// The shared skinning function, `skin()`.
pub const SKINNING_WGSL: &str = include_str!("skinning.wgsl");

/// Builds a shader module from the shared skinning source followed by `source`.
#[must_use]
pub fn with_skinning(device: &wgpu::Device, label: &str, source: &str) -> wgpu::ShaderModule {
    let combined = format!("{SKINNING_WGSL}\n{source}");
    device.create_shader_module(wgpu::ShaderModuleDescriptor {
        label: Some(label),
        source: wgpu::ShaderSource::Wgsl(combined.into()),
    })
}

/// Builds a shader module from `source` alone.
#[must_use]
pub fn plain(device: &wgpu::Device, label: &str, source: &'static str) -> wgpu::ShaderModule {
    device.create_shader_module(wgpu::ShaderModuleDescriptor {
        label: Some(label),
        source: wgpu::ShaderSource::Wgsl(source.into()),
    })
}
