//! Rendering without a window: into a texture of a chosen size, read back as RGBA8.

use super::error::RenderError;
use super::gpu::Gpu;
use super::image::RgbaImage;
use super::renderer::Renderer;

/// An sRGB colour texture to render into and the buffer its pixels are copied to.
#[derive(Debug)]
pub struct Offscreen {
    gpu: Gpu,
    texture: wgpu::Texture,
    view: wgpu::TextureView,
    readback: wgpu::Buffer,
    width: u32,
    height: u32,
    padded_row: u32,
}

impl Offscreen {
    /// Colour format of the target: 8-bit sRGB, so shaders work in linear light and the read-back
    /// bytes are display-ready PNG pixels.
    pub const FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba8UnormSrgb;

    /// A `width × height` target; errors when either is zero or beyond the device's 2D texture
    /// limit.
    pub fn new(gpu: &Gpu, width: u32, height: u32) -> Result<Self, RenderError> {
        let limit = gpu.device.limits().max_texture_dimension_2d;
        if width == 0 || height == 0 || width > limit || height > limit {
            return Err(RenderError::ImageSize {
                width,
                height,
                limit,
            });
        }
        // Texture-to-buffer copies need rows padded to COPY_BYTES_PER_ROW_ALIGNMENT (256) bytes.
        let padded_row = (width * 4).next_multiple_of(wgpu::COPY_BYTES_PER_ROW_ALIGNMENT);
        gpu.scoped("creating the offscreen target", || {
            let texture = gpu.device.create_texture(&wgpu::TextureDescriptor {
                label: Some("offscreen colour target"),
                size: extent(width, height),
                mip_level_count: 1,
                sample_count: 1,
                dimension: wgpu::TextureDimension::D2,
                format: Self::FORMAT,
                usage: wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::COPY_SRC,
                view_formats: &[],
            });
            let view = texture.create_view(&wgpu::TextureViewDescriptor {
                label: Some("offscreen colour view"),
                ..Default::default()
            });
            let readback = gpu.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("offscreen readback"),
                size: u64::from(padded_row) * u64::from(height),
                usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            });
            Ok(Self {
                gpu: gpu.clone(),
                texture,
                view,
                readback,
                width,
                height,
                padded_row,
            })
        })
    }

    /// The colour texture's view, in [`Self::FORMAT`], to render into.
    #[must_use]
    pub fn view(&self) -> &wgpu::TextureView {
        &self.view
    }

    /// `(width, height)` in pixels.
    #[must_use]
    pub fn size(&self) -> (u32, u32) {
        (self.width, self.height)
    }

    /// Runs the renderer's `update` and `render` into this target and submits; does not wait.
    /// The renderer is resized to this target first if needed.
    pub fn draw(&self, renderer: &mut Renderer) -> Result<wgpu::SubmissionIndex, RenderError> {
        if renderer.size() != (self.width, self.height) {
            renderer.resize(self.width, self.height);
        }
        self.gpu.scoped("rendering offscreen", || {
            renderer.update();
            Ok(renderer.render(&self.view))
        })
    }

    /// Draws a frame and reads it back.
    pub fn render(&self, renderer: &mut Renderer) -> Result<RgbaImage, RenderError> {
        self.draw(renderer)?;
        self.read()
    }

    /// Copies the target's pixels to the CPU (waiting for the GPU), dropping row padding.
    pub fn read(&self) -> Result<RgbaImage, RenderError> {
        let gpu = &self.gpu;
        let bytes = gpu.scoped("reading the offscreen target", || {
            let mut encoder = gpu
                .device
                .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                    label: Some("offscreen readback encoder"),
                });
            encoder.copy_texture_to_buffer(
                wgpu::TexelCopyTextureInfo {
                    texture: &self.texture,
                    mip_level: 0,
                    origin: wgpu::Origin3d::ZERO,
                    aspect: wgpu::TextureAspect::All,
                },
                wgpu::TexelCopyBufferInfo {
                    buffer: &self.readback,
                    layout: wgpu::TexelCopyBufferLayout {
                        offset: 0,
                        bytes_per_row: Some(self.padded_row),
                        rows_per_image: Some(self.height),
                    },
                },
                extent(self.width, self.height),
            );
            gpu.queue.submit([encoder.finish()]);
            gpu.read_buffer(&self.readback, "offscreen image")
        })?;
        let row = self.width as usize * 4;
        let pixels = bytes
            .chunks_exact(self.padded_row as usize)
            .flat_map(|padded| &padded[..row])
            .copied()
            .collect();
        Ok(RgbaImage::new(self.width, self.height, pixels))
    }
}

fn extent(width: u32, height: u32) -> wgpu::Extent3d {
    wgpu::Extent3d {
        width,
        height,
        depth_or_array_layers: 1,
    }
}
