//! The renderer's error type.

use super::gpu_types::MAX_JOINTS_PER_AVATAR;

/// What went wrong while creating GPU resources, skinning, rendering or writing images.
#[derive(Debug, thiserror::Error)]
pub enum RenderError {
    /// No GPU adapter (hardware or software) is available to this process.
    #[error(
        "no GPU adapter available ({reason}); on Linux install a Vulkan driver, e.g. \
         `apt-get install mesa-vulkan-drivers libvulkan1` for the lavapipe software adapter"
    )]
    NoAdapter { reason: String },
    /// The adapter exists but refused to create a device.
    #[error("adapter {adapter:?} refused to create a device: {reason}")]
    NoDevice { adapter: String, reason: String },
    /// Waiting for the GPU failed (device lost or timeout).
    #[error("waiting for the GPU failed: {reason}")]
    Poll { reason: String },
    /// Mapping a read-back buffer failed.
    #[error("reading {what} back from the GPU failed: {reason}")]
    Readback { what: &'static str, reason: String },
    /// wgpu reported a validation or out-of-memory error for an operation.
    #[error("GPU error while {during}: {reason}")]
    Gpu {
        during: &'static str,
        reason: String,
    },
    /// A skeleton has more joints than one avatar's joint buffer holds.
    #[error(
        "skeleton has {joints} joints, more than the {MAX_JOINTS_PER_AVATAR} an avatar may have"
    )]
    TooManyJoints { joints: usize },
    /// A mesh has more vertices than one storage binding or one dispatch covers.
    #[error("mesh has {vertices} vertices, more than the {limit} this device can skin at once")]
    TooManyVertices { vertices: usize, limit: usize },
    /// The mesh's joint indices reach past the skeleton's joints.
    #[error("mesh refers to joint {joint}, but the skeleton has {joints} joints")]
    MeshJointOutOfRange { joint: usize, joints: usize },
    /// A pose or matrix list does not have one entry per joint.
    #[error("{what} has {actual} entries, expected {expected}")]
    Length {
        what: &'static str,
        expected: usize,
        actual: usize,
    },
    /// The avatar handle does not name a live avatar (it was removed, or belongs to another
    /// renderer).
    #[error("no avatar with handle {handle}")]
    UnknownAvatar { handle: u64 },
    /// The surface cannot be used with this adapter.
    #[error("the window surface is not supported by adapter {adapter:?}")]
    SurfaceUnsupported { adapter: String },
    /// Creating a window surface failed.
    #[error("creating the window surface failed: {reason}")]
    Surface { reason: String },
    /// The windowing system failed.
    #[error("window system error: {reason}")]
    Window { reason: String },
    /// A width or height is zero or beyond the device's texture limit.
    #[error("image size {width}×{height} is empty or larger than the limit {limit}")]
    ImageSize { width: u32, height: u32, limit: u32 },
    /// Reading or writing an image file failed.
    #[error("image file {path}: {reason}")]
    ImageFile { path: String, reason: String },
}
