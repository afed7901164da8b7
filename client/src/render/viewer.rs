//! A window showing avatars from a [`PoseSource`] (winit 0.30 `ApplicationHandler`): the network
//! client implements the trait; the viewer owns the window, surface and [`Renderer`], shows
//! frames per second and the source's status in the title, follows resizes and recovers from
//! lost or outdated surfaces.

use super::error::RenderError;
use super::gpu::Gpu;
use super::renderer::{AvatarHandle, Renderer, RendererOptions};
use posecast_proto::{Skeleton, SkinnedMesh, Transform};
use std::collections::HashMap;
use std::sync::Arc;
use std::time::{Duration, Instant};
use winit::application::ApplicationHandler;
use winit::dpi::PhysicalSize;
use winit::event::WindowEvent;
use winit::event_loop::{ActiveEventLoop, EventLoop};
use winit::window::{Window, WindowId};

/// One change to the scene, keyed by the source's own avatar id.
#[derive(Clone, Debug)]
pub enum AvatarUpdate {
    /// A new avatar, or a new rig for an existing id (replaces it).
    Spawn {
        id: u64,
        skeleton: Box<Skeleton>,
        mesh: Box<SkinnedMesh>,
    },
    /// Local joint transforms `D_j`, one per joint of the avatar's skeleton.
    Pose { id: u64, locals: Vec<Transform> },
    /// The avatar left.
    Despawn { id: u64 },
}

/// Where the viewer gets avatars and poses. Called once per frame on the event-loop thread, so
/// `poll` should only drain what has arrived (e.g. sample a jitter buffer at `now`), never block.
pub trait PoseSource {
    /// Updates since the last call, applied in order.
    fn poll(&mut self, now: Instant) -> Vec<AvatarUpdate>;

    /// Text for the window title next to the frame rate, e.g. `"latency 42 ms"`.
    fn status(&self) -> String {
        String::new()
    }
}

/// Window and renderer settings.
#[derive(Clone, Debug)]
pub struct ViewerOptions {
    pub title: String,
    /// Initial inner size, physical pixels.
    pub size: (u32, u32),
    /// `auto_frame` is managed by the viewer: it re-frames when avatars come or go, on resize,
    /// and when the scene leaves the framed box.
    pub renderer: RendererOptions,
}

impl Default for ViewerOptions {
    fn default() -> Self {
        Self {
            title: "posecast".into(),
            size: (1280, 720),
            renderer: RendererOptions::default(),
        }
    }
}

/// Opens a window and runs until it is closed. Errors when no adapter can present to the
/// window, or the window system fails.
pub fn run_viewer(
    source: impl PoseSource + 'static,
    options: ViewerOptions,
) -> Result<(), RenderError> {
    let event_loop = EventLoop::new().map_err(|e| RenderError::Window {
        reason: e.to_string(),
    })?;
    let mut app = Viewer {
        source: Box::new(source),
        options,
        state: None,
        error: None,
        frames: 0,
        fps: 0.0,
        since: Instant::now(),
    };
    event_loop
        .run_app(&mut app)
        .map_err(|e| RenderError::Window {
            reason: e.to_string(),
        })?;
    app.error.map_or(Ok(()), Err)
}

struct Viewer {
    source: Box<dyn PoseSource>,
    options: ViewerOptions,
    state: Option<WindowState>,
    /// The error that ended the loop, returned by [`run_viewer`].
    error: Option<RenderError>,
    frames: u32,
    fps: f64,
    since: Instant,
}

struct WindowState {
    window: Arc<Window>,
    gpu: Gpu,
    surface: wgpu::Surface<'static>,
    config: wgpu::SurfaceConfiguration,
    renderer: Renderer,
    handles: HashMap<u64, AvatarHandle>,
    framed: Option<super::bounds::Aabb>,
}

impl WindowState {
    fn new(event_loop: &ActiveEventLoop, options: &ViewerOptions) -> Result<Self, RenderError> {
        let window = event_loop
            .create_window(
                Window::default_attributes()
                    .with_title(options.title.clone())
                    .with_inner_size(PhysicalSize::new(options.size.0, options.size.1)),
            )
            .map_err(|e| RenderError::Window {
                reason: e.to_string(),
            })?;
        let window = Arc::new(window);
        let instance =
            wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env());
        let surface =
            instance
                .create_surface(window.clone())
                .map_err(|e| RenderError::Surface {
                    reason: e.to_string(),
                })?;
        let gpu = pollster::block_on(Gpu::with_instance(instance, Some(&surface)))?;
        let size = window.inner_size();
        let mut config = surface
            .get_default_config(&gpu.adapter, size.width.max(1), size.height.max(1))
            .ok_or_else(|| RenderError::SurfaceUnsupported {
                adapter: gpu.describe(),
            })?;
        // Shaders output linear light: prefer an sRGB swapchain format so it is encoded.
        let formats = surface.get_capabilities(&gpu.adapter).formats;
        if let Some(srgb) = formats.iter().find(|f| f.is_srgb()) {
            config.format = *srgb;
        }
        surface.configure(&gpu.device, &config);
        let renderer_options = RendererOptions {
            auto_frame: false,
            ..options.renderer
        };
        let renderer = Renderer::new(
            &gpu,
            config.format,
            config.width,
            config.height,
            renderer_options,
        )?;
        Ok(Self {
            window,
            gpu,
            surface,
            config,
            renderer,
            handles: HashMap::new(),
            framed: None,
        })
    }

    fn resize(&mut self, size: PhysicalSize<u32>) {
        self.config.width = size.width.max(1);
        self.config.height = size.height.max(1);
        self.surface.configure(&self.gpu.device, &self.config);
        self.renderer.resize(self.config.width, self.config.height);
        self.framed = None;
    }

    fn apply(&mut self, update: AvatarUpdate) {
        match update {
            AvatarUpdate::Spawn { id, skeleton, mesh } => {
                if let Some(old) = self.handles.remove(&id) {
                    self.renderer.remove_avatar(old).ok();
                }
                match self.renderer.add_avatar(&skeleton, &mesh) {
                    Ok(handle) => {
                        self.handles.insert(id, handle);
                    }
                    Err(error) => tracing::warn!(id, %error, "cannot show avatar"),
                }
                self.framed = None;
            }
            AvatarUpdate::Pose { id, locals } => {
                let Some(&handle) = self.handles.get(&id) else {
                    return;
                };
                if let Err(error) = self.renderer.set_pose(handle, &locals) {
                    tracing::warn!(id, %error, "pose ignored");
                }
            }
            AvatarUpdate::Despawn { id } => {
                if let Some(handle) = self.handles.remove(&id) {
                    self.renderer.remove_avatar(handle).ok();
                }
                self.framed = None;
            }
        }
    }

    /// Re-frames when nothing is framed yet or the scene has left the framed box, with some
    /// margin so a walking avatar does not make the camera twitch every frame.
    fn keep_framed(&mut self) {
        let Some(bounds) = self.renderer.scene_bounds() else {
            return;
        };
        let inside = self.framed.is_some_and(|f| {
            let slack = 0.05 * f.size();
            f.contains(bounds.min, slack) && f.contains(bounds.max, slack)
        });
        if !inside {
            let margin = glam::Vec3::splat(0.1 * bounds.size());
            let framed = super::bounds::Aabb {
                min: bounds.min - margin,
                max: bounds.max + margin,
            };
            self.renderer.set_camera(super::camera::Camera::framing(
                &framed,
                self.config.width as f32 / self.config.height as f32,
            ));
            self.framed = Some(framed);
        }
    }

    /// Draws one frame; `Err` only for errors that end the viewer.
    fn draw(&mut self) -> Result<(), RenderError> {
        self.keep_framed();
        self.renderer.update();
        let frame = match self.surface.get_current_texture() {
            wgpu::CurrentSurfaceTexture::Success(frame) => frame,
            wgpu::CurrentSurfaceTexture::Suboptimal(frame) => {
                // Draw this one, reconfigure for the next.
                self.draw_into(frame);
                self.surface.configure(&self.gpu.device, &self.config);
                return Ok(());
            }
            wgpu::CurrentSurfaceTexture::Timeout | wgpu::CurrentSurfaceTexture::Occluded => {
                return Ok(());
            }
            wgpu::CurrentSurfaceTexture::Outdated => {
                self.surface.configure(&self.gpu.device, &self.config);
                return Ok(());
            }
            wgpu::CurrentSurfaceTexture::Lost => {
                self.surface = self
                    .gpu
                    .instance
                    .create_surface(self.window.clone())
                    .map_err(|e| RenderError::Surface {
                        reason: e.to_string(),
                    })?;
                self.surface.configure(&self.gpu.device, &self.config);
                return Ok(());
            }
            wgpu::CurrentSurfaceTexture::Validation => {
                return Err(RenderError::Surface {
                    reason: "validation error acquiring the next frame".into(),
                });
            }
        };
        self.draw_into(frame);
        Ok(())
    }

    fn draw_into(&mut self, frame: wgpu::SurfaceTexture) {
        let view = frame.texture.create_view(&wgpu::TextureViewDescriptor {
            label: Some("swapchain view"),
            ..Default::default()
        });
        self.renderer.render(&view);
        self.window.pre_present_notify();
        self.gpu.queue.present(frame);
    }
}

impl ApplicationHandler for Viewer {
    fn resumed(&mut self, event_loop: &ActiveEventLoop) {
        if self.state.is_some() {
            return;
        }
        match WindowState::new(event_loop, &self.options) {
            Ok(state) => self.state = Some(state),
            Err(error) => {
                self.error = Some(error);
                event_loop.exit();
            }
        }
    }

    fn window_event(&mut self, event_loop: &ActiveEventLoop, _id: WindowId, event: WindowEvent) {
        let Some(state) = self.state.as_mut() else {
            return;
        };
        match event {
            WindowEvent::CloseRequested => event_loop.exit(),
            WindowEvent::Resized(size) => state.resize(size),
            WindowEvent::RedrawRequested => {
                let now = Instant::now();
                for update in self.source.poll(now) {
                    state.apply(update);
                }
                if let Err(error) = state.draw() {
                    self.error = Some(error);
                    event_loop.exit();
                    return;
                }
                self.frames += 1;
                let elapsed = now.duration_since(self.since);
                if elapsed >= Duration::from_millis(500) {
                    self.fps = f64::from(self.frames) / elapsed.as_secs_f64();
                    self.frames = 0;
                    self.since = now;
                    let status = self.source.status();
                    let separator = if status.is_empty() { "" } else { " — " };
                    state.window.set_title(&format!(
                        "{} — {:.0} fps{separator}{status}",
                        self.options.title, self.fps
                    ));
                }
            }
            _ => {}
        }
    }

    fn about_to_wait(&mut self, _event_loop: &ActiveEventLoop) {
        // Continuous redraw: poses stream in at the server's tick rate.
        if let Some(state) = &self.state {
            state.window.request_redraw();
        }
    }
}
