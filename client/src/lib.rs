//! posecast clients: [`net`], the network client library (no GPU needed, usable in-process),
//! and, with the `render` feature, `render`, the wgpu renderer (GPU skinning, offscreen and
//! windowed), and `view_source`, which feeds the renderer from the network client.

pub mod net;
#[cfg(feature = "render")]
pub mod render;
#[cfg(feature = "render")]
pub mod view_source;
