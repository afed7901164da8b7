//! posecast clients: [`net`], the network client library (no GPU needed, usable in-process),
//! [`render`], the wgpu renderer (GPU skinning, offscreen and windowed), and [`view_source`],
//! which feeds the renderer from the network client.

pub mod net;
pub mod render;
pub mod view_source;
