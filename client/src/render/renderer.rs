//! The scene renderer, in the `init / resize / update / render` shape: several skinned avatars,
//! each with its own joint buffer, a ground grid, an optional skeleton overlay, and a camera
//! that frames them all. Draws into any texture view of the colour format it was built for,
//! offscreen ([`super::offscreen`]) or a window surface ([`super::viewer`]).

use super::avatar::GpuAvatar;
use super::bounds::Aabb;
use super::camera::Camera;
use super::compute::SkinningKernel;
use super::error::RenderError;
use super::gpu::Gpu;
use super::gpu_types::{CameraUniform, LineVertex, rgba};
use super::pipelines::{DEPTH_FORMAT, Pipelines};
use glam::Vec3;
use posecast_proto::placement::Placement;
use posecast_proto::{Skeleton, SkinnedMesh, Transform};
use std::collections::BTreeMap;

/// Where vertices are skinned before drawing.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum SkinningPath {
    /// In the vertex shader, every frame, from the bind-pose vertices.
    #[default]
    VertexShader,
    /// By the compute kernel into a vertex buffer, then drawn as plain vertices: the same path
    /// tests compare with the CPU reference.
    Compute,
}

/// How the scene is drawn.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RendererOptions {
    /// Where meshes are skinned: in the vertex shader or by the compute kernel.
    pub skinning: SkinningPath,
    /// Draw the ground grid at y = 0.
    pub grid: bool,
    /// Draw each skeleton's bones as lines over the meshes.
    pub skeleton_overlay: bool,
    /// Re-frame the camera around all avatars on every [`Renderer::update`].
    pub auto_frame: bool,
    /// Background colour, linear RGB.
    pub background: Vec3,
}

impl Default for RendererOptions {
    fn default() -> Self {
        Self {
            skinning: SkinningPath::VertexShader,
            grid: true,
            skeleton_overlay: false,
            auto_frame: true,
            background: Vec3::new(0.02, 0.025, 0.03),
        }
    }
}

/// Names one avatar of one [`Renderer`].
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct AvatarHandle(u64);

impl AvatarHandle {
    /// The number behind the handle (unique per renderer, never reused).
    #[must_use]
    pub fn get(self) -> u64 {
        self.0
    }
}

/// Base colours given to avatars in order of creation (linear RGB).
const PALETTE: [[f32; 3]; 6] = [
    [0.80, 0.55, 0.40],
    [0.35, 0.55, 0.80],
    [0.45, 0.75, 0.40],
    [0.80, 0.75, 0.35],
    [0.65, 0.40, 0.75],
    [0.40, 0.75, 0.75],
];
const BONE_COLOR: Vec3 = Vec3::new(1.0, 0.85, 0.1);
/// Direction towards the key light: above, from the front left.
const LIGHT: Vec3 = Vec3::new(-0.4, 0.8, 0.5);

/// Draws skinned avatars, the ground grid and bone overlays into a colour target of one
/// format, wgpu-example style: [`Renderer::new`], [`Renderer::resize`], [`Renderer::update`],
/// [`Renderer::render`]. Avatars are added with their skeleton and mesh and posed with local
/// transforms; world matrices and skinning are computed here.
#[derive(Debug)]
pub struct Renderer {
    device: wgpu::Device,
    queue: wgpu::Queue,
    options: RendererOptions,
    pipelines: Pipelines,
    kernel: Option<SkinningKernel>,
    width: u32,
    height: u32,
    depth: wgpu::TextureView,
    camera: Camera,
    camera_buffer: wgpu::Buffer,
    camera_bind_group: wgpu::BindGroup,
    avatars: BTreeMap<u64, GpuAvatar>,
    next_handle: u64,
    lines: Vec<LineVertex>,
    line_buffer: Option<wgpu::Buffer>,
    line_count: u32,
}

impl Renderer {
    /// Builds pipelines for targets of `color_format` and a depth buffer of `width × height`.
    pub fn new(
        gpu: &Gpu,
        color_format: wgpu::TextureFormat,
        width: u32,
        height: u32,
        options: RendererOptions,
    ) -> Result<Self, RenderError> {
        let device = gpu.device.clone();
        gpu.scoped("creating the renderer", || {
            let pipelines = Pipelines::new(&device, color_format);
            let camera_buffer = device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("camera uniform"),
                size: std::mem::size_of::<CameraUniform>() as u64,
                usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            });
            let camera_bind_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("camera bind group"),
                layout: &pipelines.camera_layout,
                entries: &[wgpu::BindGroupEntry {
                    binding: 0,
                    resource: camera_buffer.as_entire_binding(),
                }],
            });
            let kernel =
                (options.skinning == SkinningPath::Compute).then(|| SkinningKernel::new(&device));
            let mut renderer = Self {
                depth: depth_view(&device, width, height),
                device: device.clone(),
                queue: gpu.queue.clone(),
                options,
                pipelines,
                kernel,
                width: width.max(1),
                height: height.max(1),
                camera: Camera::default(),
                camera_buffer,
                camera_bind_group,
                avatars: BTreeMap::new(),
                next_handle: 0,
                lines: Vec::new(),
                line_buffer: None,
                line_count: 0,
            };
            renderer.frame_all();
            Ok(renderer)
        })
    }

    /// Resizes the depth buffer for targets of `width × height` (zero is clamped to one).
    pub fn resize(&mut self, width: u32, height: u32) {
        self.width = width.max(1);
        self.height = height.max(1);
        self.depth = depth_view(&self.device, self.width, self.height);
    }

    /// `(width, height)` of the targets it draws into, pixels (at least 1 each).
    #[must_use]
    pub fn size(&self) -> (u32, u32) {
        (self.width, self.height)
    }

    /// The options it draws with.
    #[must_use]
    pub fn options(&self) -> &RendererOptions {
        &self.options
    }

    /// Changes the options; switching to [`SkinningPath::Compute`] creates the kernel and each
    /// avatar's skinned-vertex buffer.
    pub fn set_options(&mut self, options: RendererOptions) {
        self.options = options;
        if options.skinning == SkinningPath::Compute {
            let kernel = self
                .kernel
                .get_or_insert_with(|| SkinningKernel::new(&self.device));
            for avatar in self.avatars.values_mut() {
                avatar.ensure_compute(&self.device, kernel);
            }
        }
    }

    /// Uploads an avatar's mesh (reduced to four influences per vertex) and shows it in its
    /// skeleton's rest pose.
    pub fn add_avatar(
        &mut self,
        skeleton: &Skeleton,
        mesh: &SkinnedMesh,
    ) -> Result<AvatarHandle, RenderError> {
        let handle = self.next_handle;
        let color = PALETTE[handle as usize % PALETTE.len()];
        let mut avatar = GpuAvatar::new(
            &self.device,
            &self.queue,
            &self.pipelines.avatar_layout,
            format!("avatar {handle}"),
            skeleton,
            mesh,
            Vec3::from(color),
        )?;
        if let Some(kernel) = &self.kernel
            && self.options.skinning == SkinningPath::Compute
        {
            avatar.ensure_compute(&self.device, kernel);
        }
        self.next_handle += 1;
        self.avatars.insert(handle, avatar);
        Ok(AvatarHandle(handle))
    }

    /// Poses an avatar from local joint transforms `D_j` (one per joint, parent space): runs
    /// forward kinematics and `M_j = W_j · B_j⁻¹` into the avatar's buffers and uploads only
    /// the matrices.
    pub fn set_pose(
        &mut self,
        handle: AvatarHandle,
        locals: &[Transform],
    ) -> Result<(), RenderError> {
        let queue = &self.queue;
        self.avatars
            .get_mut(&handle.0)
            .ok_or(RenderError::UnknownAvatar { handle: handle.0 })?
            .set_pose(queue, locals)
    }

    /// Poses an avatar standing at `placement`: `placement · D_root` for its roots, then as
    /// [`Renderer::set_pose`] (forward kinematics, skinning matrices).
    pub fn set_placed_pose(
        &mut self,
        handle: AvatarHandle,
        placement: &Placement,
        locals: &[Transform],
    ) -> Result<(), RenderError> {
        let avatar = self
            .avatars
            .get_mut(&handle.0)
            .ok_or(RenderError::UnknownAvatar { handle: handle.0 })?;
        let mut placed = locals.to_vec();
        placement.place_roots(avatar.parents(), &mut placed);
        avatar.set_pose(&self.queue, &placed)
    }

    /// Sets an avatar's morph-target weights, one per target of the mesh it was added with
    /// (that mesh's `targets()` order; missing entries are 0). The GPU morphs before skinning,
    /// `v' = v + Σₖ wₖ·Δvₖ` (normals likewise), on both skinning paths; only non-zero weights
    /// cost anything. A mesh without targets accepts an empty list.
    ///
    /// # Errors
    /// An unknown handle, or more weights than the mesh has targets.
    pub fn set_morph_weights(
        &mut self,
        handle: AvatarHandle,
        weights: &[f32],
    ) -> Result<(), RenderError> {
        let queue = self.queue.clone();
        self.avatar_mut(handle)?.set_morph_weights(&queue, weights)
    }

    /// How many morph targets an avatar's mesh has (the length
    /// [`Renderer::set_morph_weights`] takes at most). Targets too large for this device
    /// are not drawn (a warning says why) and their weights change nothing.
    pub fn morph_targets(&self, handle: AvatarHandle) -> Result<usize, RenderError> {
        self.avatars
            .get(&handle.0)
            .map(GpuAvatar::morph_targets)
            .ok_or(RenderError::UnknownAvatar { handle: handle.0 })
    }

    /// Changes an avatar's base colour (linear RGB).
    pub fn set_avatar_color(
        &mut self,
        handle: AvatarHandle,
        color: Vec3,
    ) -> Result<(), RenderError> {
        let queue = self.queue.clone();
        self.avatar_mut(handle)?.set_color(&queue, color);
        Ok(())
    }

    /// Removes an avatar and frees its buffers.
    pub fn remove_avatar(&mut self, handle: AvatarHandle) -> Result<(), RenderError> {
        self.avatars
            .remove(&handle.0)
            .map(drop)
            .ok_or(RenderError::UnknownAvatar { handle: handle.0 })
    }

    /// Handles of the live avatars, oldest first.
    pub fn avatars(&self) -> impl Iterator<Item = AvatarHandle> + '_ {
        self.avatars.keys().map(|&h| AvatarHandle(h))
    }

    /// A box holding every skinned vertex of every avatar in its current pose (conservative:
    /// see [`super::bounds::JointBounds`]), or `None` without avatars.
    #[must_use]
    pub fn scene_bounds(&self) -> Option<Aabb> {
        self.avatars
            .values()
            .filter_map(GpuAvatar::bounds)
            .reduce(Aabb::union)
    }

    /// [`Renderer::scene_bounds`] of one avatar, or `None` for an unknown handle or an avatar
    /// without a pose yet.
    #[must_use]
    pub fn avatar_bounds(&self, handle: AvatarHandle) -> Option<Aabb> {
        self.avatars.get(&handle.0).and_then(GpuAvatar::bounds)
    }

    /// The camera the next [`Renderer::update`] uses (re-framed there when
    /// [`RendererOptions::auto_frame`] is on).
    #[must_use]
    pub fn camera(&self) -> &Camera {
        &self.camera
    }

    /// Sets the camera; turn [`RendererOptions::auto_frame`] off to keep it.
    pub fn set_camera(&mut self, camera: Camera) {
        self.camera = camera;
    }

    /// Points the camera at all avatars (or at a default box when there are none).
    pub fn frame_all(&mut self) {
        self.camera = match self.scene_bounds() {
            Some(bounds) => Camera::framing(&bounds, self.aspect()),
            None => Camera::default(),
        };
    }

    fn aspect(&self) -> f32 {
        self.width as f32 / self.height as f32
    }

    fn avatar_mut(&mut self, handle: AvatarHandle) -> Result<&mut GpuAvatar, RenderError> {
        self.avatars
            .get_mut(&handle.0)
            .ok_or(RenderError::UnknownAvatar { handle: handle.0 })
    }

    /// Per-frame CPU work before [`Renderer::render`]: re-frames the camera when
    /// `auto_frame` is on, uploads the camera and grid, rebuilds the skeleton overlay.
    pub fn update(&mut self) {
        if self.options.auto_frame {
            self.frame_all();
        }
        let bounds = self.scene_bounds().unwrap_or(Aabb {
            min: Vec3::splat(-1.0),
            max: Vec3::splat(1.0),
        });
        // Grid cells of a power of two metres, about a quarter of the scene's size; the ground
        // extends well past the scene and fades out before the far plane.
        let size = bounds.size().max(1e-3);
        let cell = 2f32.powf((size * 0.25).log2().round());
        let extent = size * 3.0;
        let centre = (bounds.center() / cell).round() * cell;
        let uniform = CameraUniform {
            view_proj: self.camera.view_proj(self.aspect()).to_cols_array_2d(),
            eye: self.camera.eye.extend(1.0).to_array(),
            light: LIGHT.normalize().extend(0.8).to_array(),
            grid: [centre.x, centre.z, extent, cell],
            background: rgba(self.options.background),
        };
        self.queue
            .write_buffer(&self.camera_buffer, 0, bytemuck::bytes_of(&uniform));
        self.update_lines();
    }

    fn update_lines(&mut self) {
        self.lines.clear();
        if self.options.skeleton_overlay {
            for avatar in self.avatars.values() {
                avatar.bone_lines(BONE_COLOR, &mut self.lines);
            }
        }
        self.line_count = self.lines.len() as u32;
        if self.lines.is_empty() {
            return;
        }
        let bytes: &[u8] = bytemuck::cast_slice(&self.lines);
        let fits = self
            .line_buffer
            .as_ref()
            .is_some_and(|b| b.size() >= bytes.len() as u64);
        if !fits {
            self.line_buffer = Some(self.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("skeleton overlay lines"),
                size: (bytes.len() as u64).next_power_of_two(),
                usage: wgpu::BufferUsages::VERTEX | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            }));
        }
        if let Some(buffer) = &self.line_buffer {
            self.queue.write_buffer(buffer, 0, bytes);
        }
    }

    /// Draws the scene into `target` (same size as the last [`Renderer::resize`], colour format
    /// as given to [`Renderer::new`]) and submits the work.
    pub fn render(&mut self, target: &wgpu::TextureView) -> wgpu::SubmissionIndex {
        let mut encoder = self
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("frame encoder"),
            });
        self.encode(&mut encoder, target);
        self.queue.submit([encoder.finish()])
    }

    /// Records the frame into `encoder` without submitting, for callers that add their own
    /// passes (e.g. a copy to a read-back buffer).
    pub fn encode(&self, encoder: &mut wgpu::CommandEncoder, target: &wgpu::TextureView) {
        let compute = self.options.skinning == SkinningPath::Compute;
        if let (true, Some(kernel)) = (compute, &self.kernel) {
            let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("compute skinning pass"),
                timestamp_writes: None,
            });
            for avatar in self.avatars.values() {
                avatar.encode_compute(&mut pass, kernel);
            }
        }
        let bg = self.options.background.as_dvec3();
        let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
            label: Some("scene pass"),
            color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                view: target,
                depth_slice: None,
                resolve_target: None,
                ops: wgpu::Operations {
                    load: wgpu::LoadOp::Clear(wgpu::Color {
                        r: bg.x,
                        g: bg.y,
                        b: bg.z,
                        a: 1.0,
                    }),
                    store: wgpu::StoreOp::Store,
                },
            })],
            depth_stencil_attachment: Some(wgpu::RenderPassDepthStencilAttachment {
                view: &self.depth,
                depth_ops: Some(wgpu::Operations {
                    load: wgpu::LoadOp::Clear(1.0),
                    store: wgpu::StoreOp::Discard,
                }),
                stencil_ops: None,
            }),
            timestamp_writes: None,
            occlusion_query_set: None,
            multiview_mask: None,
        });
        pass.set_bind_group(0, &self.camera_bind_group, &[]);
        if self.options.grid {
            pass.set_pipeline(&self.pipelines.ground);
            pass.draw(0..6, 0..1);
        }
        for avatar in self.avatars.values() {
            let precomputed = compute && avatar.has_compute();
            pass.set_pipeline(if precomputed {
                &self.pipelines.preskinned
            } else {
                &self.pipelines.skinned
            });
            avatar.draw(&mut pass, precomputed);
        }
        if let (true, Some(buffer)) = (self.line_count > 0, &self.line_buffer) {
            pass.set_pipeline(&self.pipelines.lines);
            pass.set_vertex_buffer(0, buffer.slice(..));
            pass.draw(0..self.line_count, 0..1);
        }
    }
}

fn depth_view(device: &wgpu::Device, width: u32, height: u32) -> wgpu::TextureView {
    device
        .create_texture(&wgpu::TextureDescriptor {
            label: Some("depth buffer"),
            size: wgpu::Extent3d {
                width: width.max(1),
                height: height.max(1),
                depth_or_array_layers: 1,
            },
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format: DEPTH_FORMAT,
            usage: wgpu::TextureUsages::RENDER_ATTACHMENT,
            view_formats: &[],
        })
        .create_view(&wgpu::TextureViewDescriptor {
            label: Some("depth buffer view"),
            ..Default::default()
        })
}
