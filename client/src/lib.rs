//! posecast clients: [`net`], the network client library (no GPU needed, usable in-process),
//! and [`render`], the wgpu renderer (GPU skinning, offscreen and windowed).

pub mod net;
pub mod render;
