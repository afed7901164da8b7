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
    NoAdapter {
        /// What the adapter request reported.
        reason: String,
    },
    /// The adapter exists but refused to create a device.
    #[error("adapter {adapter:?} refused to create a device: {reason}")]
    NoDevice {
        /// The adapter's name.
        adapter: String,
        /// What the device request reported.
        reason: String,
    },
    /// Waiting for the GPU failed (device lost or timeout).
    #[error("waiting for the GPU failed: {reason}")]
    Poll {
        /// What the poll reported.
        reason: String,
    },
    /// Mapping a read-back buffer failed.
    #[error("reading {what} back from the GPU failed: {reason}")]
    Readback {
        /// What was being read (`"skinned vertices"`, `"offscreen image"`).
        what: &'static str,
        /// What the mapping reported.
        reason: String,
    },
    /// wgpu reported a validation or out-of-memory error for an operation.
    #[error("GPU error while {during}: {reason}")]
    Gpu {
        /// The operation that failed (`"compute skinning"`, `"rendering offscreen"`, …).
        during: &'static str,
        /// The wgpu error's message.
        reason: String,
    },
    /// A skeleton has more joints than one avatar's joint buffer holds.
    #[error(
        "skeleton has {joints} joints, more than the {MAX_JOINTS_PER_AVATAR} an avatar may have"
    )]
    TooManyJoints {
        /// The skeleton's joint count.
        joints: usize,
    },
    /// A mesh has more vertices than one storage binding or one dispatch covers.
    #[error("mesh has {vertices} vertices, more than the {limit} this device can skin at once")]
    TooManyVertices {
        /// The mesh's vertex count.
        vertices: usize,
        /// The most vertices this device can skin in one binding and dispatch.
        limit: usize,
    },
    /// A mesh's morph-target displacements do not fit one storage binding of this device.
    #[error(
        "{targets} morph targets over {vertices} vertices need {bytes} bytes, more than the \
         {limit} this device binds at once"
    )]
    MorphTooLarge {
        /// Targets that displace anything.
        targets: usize,
        /// The mesh's vertex count.
        vertices: usize,
        /// Bytes the displacements need.
        bytes: u64,
        /// The device's storage binding limit.
        limit: u64,
    },
    /// The mesh's joint indices reach past the skeleton's joints.
    #[error("mesh refers to joint {joint}, but the skeleton has {joints} joints")]
    MeshJointOutOfRange {
        /// The highest joint index the mesh uses.
        joint: usize,
        /// The skeleton's joint count.
        joints: usize,
    },
    /// A pose or matrix list does not have one entry per joint.
    #[error("{what} has {actual} entries, expected {expected}")]
    Length {
        /// Which list (`"pose"`, `"skinning matrices"`).
        what: &'static str,
        /// The skeleton's joint count.
        expected: usize,
        /// The list's actual length.
        actual: usize,
    },
    /// The avatar handle does not name a live avatar (it was removed, or belongs to another
    /// renderer).
    #[error("no avatar with handle {handle}")]
    UnknownAvatar {
        /// The handle given.
        handle: u64,
    },
    /// The surface cannot be used with this adapter.
    #[error("the window surface is not supported by adapter {adapter:?}")]
    SurfaceUnsupported {
        /// The adapter's description.
        adapter: String,
    },
    /// Creating a window surface failed.
    #[error("creating the window surface failed: {reason}")]
    Surface {
        /// What surface creation reported.
        reason: String,
    },
    /// The windowing system failed.
    #[error("window system error: {reason}")]
    Window {
        /// What the windowing system reported.
        reason: String,
    },
    /// A width or height is zero or beyond the device's texture limit.
    #[error("image size {width}×{height} is empty or larger than the limit {limit}")]
    ImageSize {
        /// The width asked for, pixels.
        width: u32,
        /// The height asked for, pixels.
        height: u32,
        /// The device's largest 2D texture side, pixels.
        limit: u32,
    },
    /// Reading or writing an image file failed.
    #[error("image file {path}: {reason}")]
    ImageFile {
        /// The file's path.
        path: String,
        /// What the read, write or decode reported.
        reason: String,
    },
}
