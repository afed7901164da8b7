//! A window showing avatars from a [`PoseSource`] (winit 0.30 `ApplicationHandler`): the network
//! client implements the trait; the viewer owns the window, surface and [`Renderer`], shows
//! frames per second and the source's status in the title, follows resizes and recovers from
//! lost or outdated surfaces.
//!
//! Camera ([`super::orbit`]): it frames every avatar until you move it. Left drag or the arrow
//! keys orbit, right (or middle) drag or W/A/S/D pan, the wheel or `+`/`-` zoom; a click on an
//! avatar — or Tab, for the next one — follows it as it moves; Esc stops following; F (or
//! Home) frames everything again.

use super::error::RenderError;
use super::gpu::Gpu;
use super::orbit::{self, Orbit};
use super::renderer::{AvatarHandle, Renderer, RendererOptions};
use glam::{Vec2, Vec3};
use posecast_proto::{Skeleton, SkinnedMesh, Transform};
use std::collections::HashMap;
use std::sync::Arc;
use std::time::{Duration, Instant};
use winit::application::ApplicationHandler;
use winit::dpi::PhysicalSize;
use winit::event::{ElementState, MouseButton, MouseScrollDelta, WindowEvent};
use winit::event_loop::{ActiveEventLoop, EventLoop};
use winit::keyboard::{Key, NamedKey};
use winit::window::{Window, WindowId};

/// One change to the scene, keyed by the source's own avatar id.
#[derive(Clone, Debug)]
pub enum AvatarUpdate {
    /// A new avatar, or a new rig for an existing id (replaces it).
    Spawn {
        /// The source's id for the avatar.
        id: u64,
        /// Its skeleton (joint order of the poses that follow).
        skeleton: Box<Skeleton>,
        /// Its skinned mesh in bind pose, joint indices into `skeleton`.
        mesh: Box<SkinnedMesh>,
    },
    /// Local joint transforms `D_j`, one per joint of the avatar's skeleton.
    Pose {
        /// The source's id for the avatar.
        id: u64,
        /// `D_j` per joint, in the parent's space (a root's in world space).
        locals: Vec<Transform>,
        /// Morph weights, one per target of the spawned mesh (its `targets()` order; missing
        /// entries are 0, so a mesh without targets takes an empty list).
        weights: Vec<f32>,
    },
    /// The avatar left.
    Despawn {
        /// The source's id for the avatar.
        id: u64,
    },
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
    /// The window's title, before the frame rate and the source's status.
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
    controls: Controls,
}

/// What the mouse and keys have done to the camera.
#[derive(Debug, Default)]
struct Controls {
    /// The camera the user moved; `None` while the viewer frames every avatar by itself.
    orbit: Option<Orbit>,
    /// The avatar followed (the source's id) and where its centre was last frame.
    follow: Option<(u64, Option<Vec3>)>,
    cursor: Option<Vec2>,
    /// The button held and where it went down (a press and release in place is a click).
    dragging: Option<(MouseButton, Vec2)>,
    moved: bool,
}

/// Radians the arrow keys turn the camera per press.
const KEY_TURN: f32 = 0.087;
/// Fraction of the view the W/A/S/D keys pan per press.
const KEY_PAN: f32 = 0.05;
/// Radians per pixel of a drag.
const DRAG_TURN: f32 = 0.005;

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
            controls: Controls::default(),
        })
    }

    /// The orbit to change: the user's, or — on the first touch — one that sees what the
    /// automatic framing shows.
    fn orbit(&mut self) -> &mut Orbit {
        let camera = *self.renderer.camera();
        self.controls
            .orbit
            .get_or_insert_with(|| Orbit::from_camera(&camera))
    }

    fn window_size(&self) -> Vec2 {
        Vec2::new(self.config.width as f32, self.config.height as f32)
    }

    /// Follows the avatar under `pixel`, if any.
    fn pick(&mut self, pixel: Vec2) {
        let Some((origin, direction)) =
            orbit::ray(self.renderer.camera(), pixel, self.window_size())
        else {
            return;
        };
        let boxes: Vec<(u64, super::bounds::Aabb)> = self
            .handles
            .iter()
            .filter_map(|(&id, &h)| self.renderer.avatar_bounds(h).map(|b| (id, b)))
            .collect();
        if let Some(id) = orbit::pick(boxes, origin, direction) {
            self.orbit();
            self.controls.follow = Some((id, None));
        }
    }

    /// Follows the next avatar (by id) after the one followed.
    fn follow_next(&mut self) {
        let mut ids: Vec<u64> = self.handles.keys().copied().collect();
        ids.sort_unstable();
        let current = self.controls.follow.map(|(id, _)| id);
        let next = match current {
            Some(c) => ids
                .iter()
                .copied()
                .find(|&id| id > c)
                .or(ids.first().copied()),
            None => ids.first().copied(),
        };
        if let Some(id) = next {
            self.orbit();
            self.controls.follow = Some((id, None));
        }
    }

    fn on_key(&mut self, key: &Key) {
        match key {
            Key::Named(NamedKey::ArrowLeft) => self.orbit().rotate(-KEY_TURN, 0.0),
            Key::Named(NamedKey::ArrowRight) => self.orbit().rotate(KEY_TURN, 0.0),
            Key::Named(NamedKey::ArrowUp) => self.orbit().rotate(0.0, KEY_TURN),
            Key::Named(NamedKey::ArrowDown) => self.orbit().rotate(0.0, -KEY_TURN),
            Key::Named(NamedKey::Tab) => self.follow_next(),
            Key::Named(NamedKey::Escape) => self.controls.follow = None,
            Key::Named(NamedKey::Home) => self.reframe(),
            Key::Character(c) => match c.as_str() {
                "w" | "W" => self.orbit().pan(0.0, KEY_PAN),
                "s" | "S" => self.orbit().pan(0.0, -KEY_PAN),
                "a" | "A" => self.orbit().pan(-KEY_PAN, 0.0),
                "d" | "D" => self.orbit().pan(KEY_PAN, 0.0),
                "+" | "=" => self.orbit().zoom(0.9),
                "-" | "_" => self.orbit().zoom(1.0 / 0.9),
                "f" | "F" => self.reframe(),
                _ => {}
            },
            _ => {}
        }
    }

    /// Back to framing every avatar automatically.
    fn reframe(&mut self) {
        self.controls.orbit = None;
        self.controls.follow = None;
        self.framed = None;
    }

    fn on_cursor(&mut self, to: Vec2) {
        let from = self.controls.cursor.replace(to);
        let (Some(from), Some((button, down))) = (from, self.controls.dragging) else {
            return;
        };
        if to.distance(down) > 3.0 {
            self.controls.moved = true;
        }
        let d = to - from;
        let height = self.window_size().y.max(1.0);
        match button {
            MouseButton::Left => self.orbit().rotate(-d.x * DRAG_TURN, d.y * DRAG_TURN),
            MouseButton::Right | MouseButton::Middle => {
                self.orbit().pan(-d.x / height, d.y / height)
            }
            _ => {}
        }
    }

    fn on_button(&mut self, button: MouseButton, state: ElementState) {
        let Some(cursor) = self.controls.cursor else {
            return;
        };
        match state {
            ElementState::Pressed => {
                self.controls.dragging = Some((button, cursor));
                self.controls.moved = false;
            }
            ElementState::Released => {
                let click = !self.controls.moved
                    && self
                        .controls
                        .dragging
                        .is_some_and(|(b, _)| b == MouseButton::Left);
                self.controls.dragging = None;
                if click {
                    self.pick(cursor);
                }
            }
        }
    }

    fn on_wheel(&mut self, delta: MouseScrollDelta) {
        let lines = match delta {
            MouseScrollDelta::LineDelta(_, y) => y,
            MouseScrollDelta::PixelDelta(p) => p.y as f32 / 40.0,
        };
        self.orbit().zoom(0.9f32.powf(lines));
    }

    /// The user's camera, moved along with the followed avatar.
    fn place_camera(&mut self) {
        if let Some((id, last)) = self.controls.follow {
            let centre = self
                .handles
                .get(&id)
                .and_then(|&h| self.renderer.avatar_bounds(h))
                .map(|b| b.center());
            match (centre, last) {
                (Some(now), Some(before)) => {
                    self.orbit().follow(before, now);
                    self.controls.follow = Some((id, Some(now)));
                }
                (Some(now), None) => {
                    // Just picked: look at it from where the camera is.
                    let o = self.orbit();
                    o.target = now;
                    self.controls.follow = Some((id, Some(now)));
                }
                // It left: stop following, keep the camera.
                (None, _) if !self.handles.contains_key(&id) => self.controls.follow = None,
                (None, _) => {}
            }
        }
        let radius = self.renderer.scene_bounds().map_or(1.0, |b| 0.5 * b.size());
        if let Some(orbit) = self.controls.orbit {
            let reach = radius
                + orbit.target.distance(
                    self.renderer
                        .scene_bounds()
                        .map_or(orbit.target, |b| b.center()),
                );
            self.renderer.set_camera(orbit.camera(reach));
        }
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
            AvatarUpdate::Pose {
                id,
                locals,
                weights,
            } => {
                let Some(&handle) = self.handles.get(&id) else {
                    return;
                };
                if let Err(error) = self.renderer.set_pose(handle, &locals) {
                    tracing::warn!(id, %error, "pose ignored");
                }
                if let Err(error) = self.renderer.set_morph_weights(handle, &weights) {
                    tracing::warn!(id, %error, "morph weights ignored");
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
        if self.controls.orbit.is_some() {
            self.place_camera();
        } else {
            self.keep_framed();
        }
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
            WindowEvent::KeyboardInput { event, .. } if event.state == ElementState::Pressed => {
                state.on_key(&event.logical_key);
            }
            WindowEvent::CursorMoved { position, .. } => {
                state.on_cursor(Vec2::new(position.x as f32, position.y as f32));
            }
            WindowEvent::CursorLeft { .. } => {
                state.controls.cursor = None;
                state.controls.dragging = None;
            }
            WindowEvent::MouseInput {
                state: pressed,
                button,
                ..
            } => state.on_button(button, pressed),
            WindowEvent::MouseWheel { delta, .. } => state.on_wheel(delta),
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
