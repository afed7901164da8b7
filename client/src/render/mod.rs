//! The wgpu renderer: GPU skinning (vertex shader and compute), offscreen rendering to PNG and a
//! windowed viewer.
//!
//! - [`gpu`]: headless device creation ([`Gpu::headless`]), with a typed error when no adapter
//!   exists.
//! - [`gpu_types`]: every struct the GPU reads, the influence count and the per-avatar joint
//!   limit.
//! - `skinning.wgsl`: the one skinning function, shared by [`compute`] and the vertex shader;
//!   `morph.wgsl` likewise the one morph-target function, run before it ([`morph`] holds its
//!   buffers).
//! - `camera.wgsl`: the camera uniform, the prelude of every render pipeline's shader.
//! - [`compute`]: compute skinning ([`ComputeSkinner`]), the path tested against the CPU
//!   reference `posecast_proto::skinning::skin_cpu`.
//! - [`renderer`]: the scene ([`Renderer`]): avatars, ground grid, skeleton overlay, camera.
//! - [`offscreen`]: render to a texture and read back an [`RgbaImage`]; [`image`] writes PNGs
//!   and compares images.
//! - [`viewer`]: a window showing avatars from a [`PoseSource`], with [`orbit`] camera controls
//!   (orbit, pan, zoom, follow and pick an avatar).
//! - [`glb_mesh`]: an avatar's skinned mesh from the server's `.glb` mesh format.
//! - [`procedural`]: tube meshes along bones and a small figure, for demos and tests.

mod avatar;
pub mod bounds;
pub mod camera;
pub mod compute;
pub mod error;
pub mod glb_mesh;
pub mod gpu;
pub mod gpu_types;
pub mod image;
pub mod morph;
pub mod offscreen;
pub mod orbit;
mod pipelines;
pub mod procedural;
pub mod renderer;
mod shader;
pub mod viewer;

pub use bounds::Aabb;
pub use camera::Camera;
pub use compute::{ComputeSkinner, SkinningKernel};
pub use error::RenderError;
pub use gpu::Gpu;
pub use gpu_types::{GPU_INFLUENCES, MAX_JOINTS_PER_AVATAR};
pub use image::{RgbaImage, Tolerance};
pub use morph::GpuMorph;
pub use offscreen::Offscreen;
pub use renderer::{AvatarHandle, Renderer, RendererOptions, SkinningPath};
pub use viewer::{AvatarUpdate, PoseSource, ViewerOptions, run_viewer};
