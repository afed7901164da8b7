//! The VMC protocol gateway (issue 17): avatars driven by VTuber tools, and avatars fed to VMC
//! receivers. VMC ("Virtual Motion Capture" protocol) is OSC over UDP: a performer (VSeeFace,
//! Warudo, XR Animator, VirtualMotionCapture, webcam trackers) sends a humanoid's bone
//! rotations, a marionette (a renderer) receives them. A service on the live-driving layer:
//! an input is a live driver like a websocket connection.
//!
//! - [`unity`]: Unity's frame and its humanoid (`HumanBodyBones`), the T-pose rig's bones.
//! - [`rig`]: that T-pose as a normalised source rig, and the maps between VMC's T-pose-relative
//!   rotations and it.
//! - [`packet`]: one datagram decoded (OSC by `rosc`) and checked.
//! - [`input`]: `--vmc-in ADDR=AVATAR`, a performer driving an avatar: by its bones, or, when
//!   it sends only tracked devices (`/VMC/Ext/{Hmd,Con,Tra}/Pos`, a VR tool), by the tracker
//!   solve (`posecast_sim::avatar::trackers`).
//! - [`output`]: `--vmc-out AVATAR=ADDR`, an avatar's pose sent every tick.
//!
//! # The maths
//!
//! **Frames.** Unity is left-handed, Y up, the model facing +Z (its left at −X); glTF and
//! posecast are right-handed, Y up, facing +Z (left at +X). Mirroring X maps one onto the other
//! with the model still facing +Z: position `(x, y, z) → (−x, y, z)`, rotation
//! `(x, y, z, w) → (x, −y, −z, w)` (the rotation conjugated by `M = diag(−1, 1, 1)`: axis
//! mirrored, angle negated); both maps are their own inverse ([`unity::mirror_rotation`]).
//!
//! **The performer is a source rig.** In VMC a bone's local rotation is relative to the
//! humanoid's T-pose (identity rotations in the T-pose; VRM 0 models are normalised so). The
//! input treats the stream as a pose of a rig built in code: Unity's bones with a typical
//! adult's T-pose offsets in metres and identity rest rotations ([`unity::BONES`]). That rig
//! goes through the normalisation every imported rig does (seed 000): its neutral pose becomes
//! the H-Anim pose (arms down) with per-bone rotations `V_i`, so a T-pose-relative rotation
//! `R_i` (after the mirror) is `R'_i = V_parent(i) · R_i · V_i⁻¹` on the normalised rig. The
//! Hips also carry the root's rotation: `R_hips = R_root · R_hips,local`.
//!
//! **Onto the avatar.** From there it is the world-space retargeting of seed 001 that
//! `drive … source` and `play … from_asset` use ([`posecast_rigs::rig::retarget::PoseRetargeter`],
//! per tick through [`posecast_sim::avatar::live::LivePose`]): world rotations down the source tree,
//! `G_i = G_parent(i) · R'_i`; every avatar joint with the H-Anim name of a Unity bone takes
//! its world rotation, and its local rotation follows, `L_j = G_parent(j)⁻¹ · G_src(j)`;
//! unmatched joints stay neutral. Then joint overrides and DOF clamping (seed 002), as for
//! every driver. Unity names map to H-Anim names ([`unity::Bone::hanim`]: `Hips` →
//! `humanoid_root`, `LeftUpperLeg` → `l_hip`, `LeftShoulder` → `l_sternoclavicular`,
//! `LeftUpperArm` → `l_shoulder`, `LeftIndexProximal` → `l_index1`, …), the torso and neck
//! fitted to the avatar's own spine joints ([`rig::VmcRig::for_target`]).
//!
//! **Root.** The hips' position is `p = (p_root + R_root (s_root ⊙ p_hips)) / s`, with `s` the
//! performer's model scale (its leg length, from the bone offsets it sends, over the T-pose
//! rig's); it reaches the avatar's `humanoid_root` scaled by the hip-height ratio, like a
//! retargeted clip's root.
//!
//! **Out** is the same retargeting the other way: the avatar is the source, the T-pose rig
//! the target, `R = V_parent⁻¹ · L' · V`, then the mirror ([`output`]). Out then in reproduces
//! every mapped joint's world rotation exactly (to float rounding).

pub mod input;
pub mod output;
pub mod packet;
pub mod rig;
pub mod unity;

use std::net::SocketAddr;
use std::sync::Arc;

use tokio::net::UdpSocket;
use tokio::task::JoinHandle;

pub use crate::config::{Cidr, VmcIn, VmcInputs, VmcOut};
use rig::VmcRig;

use crate::state::Services;

/// The running VMC tasks: the addresses the inputs listen on (in the order configured) and
/// the tasks, to stop with the server.
#[derive(Debug, Default)]
pub struct Running {
    /// Where each `--vmc-in` listens (port 0 resolved).
    pub inputs: Vec<SocketAddr>,
    tasks: Vec<JoinHandle<()>>,
}

impl Running {
    /// Stops every VMC task.
    pub fn abort(&self) {
        for t in &self.tasks {
            t.abort();
        }
    }
}

/// Receive buffer asked for a VMC input's socket: ~800 full performer frames (5 KB), several
/// seconds at 120 Hz, so a task that is not scheduled for a moment loses nothing (Linux caps it
/// at `net.core.rmem_max`; the default 212 KB holds ~40 frames).
pub const INPUT_RECEIVE_BUFFER: usize = 4 << 20;

/// A UDP socket bound to `addr` with [`INPUT_RECEIVE_BUFFER`] (as much of it as the system
/// grants).
fn bind_input(addr: SocketAddr) -> std::io::Result<UdpSocket> {
    use socket2::{Domain, Protocol, Socket, Type};
    let socket = Socket::new(Domain::for_address(addr), Type::DGRAM, Some(Protocol::UDP))?;
    if let Err(e) = socket.set_recv_buffer_size(INPUT_RECEIVE_BUFFER) {
        tracing::debug!(%addr, error = %e, "VMC input: receive buffer left at the default");
    }
    socket.set_nonblocking(true)?;
    socket.bind(&addr.into())?;
    UdpSocket::from_std(socket.into())
}

/// The VMC performer rig, made once (it is the same for every input, output and relayed
/// drive: Unity's humanoid in its T-pose, normalised).
///
/// # Errors
/// Never with the built-in bone table: the T-pose rig cannot be normalised.
pub fn performer_rig() -> Result<Arc<VmcRig>, posecast_rigs::rig::RigError> {
    static RIG: std::sync::OnceLock<Arc<VmcRig>> = std::sync::OnceLock::new();
    if let Some(rig) = RIG.get() {
        return Ok(rig.clone());
    }
    let rig = Arc::new(VmcRig::new()?);
    Ok(RIG.get_or_init(|| rig).clone())
}

/// Binds every configured VMC input and output socket and starts their tasks.
///
/// # Errors
/// A socket cannot be bound (the error names the address), or — never with the built-in bone
/// table — the T-pose rig cannot be normalised.
pub async fn start(state: &Arc<Services>) -> std::io::Result<Running> {
    let mut running = Running::default();
    let (inputs, outputs) = (&state.config.vmc_in, &state.config.vmc_out);
    if inputs.is_empty() && outputs.is_empty() {
        return Ok(running);
    }
    let vmc = performer_rig().map_err(std::io::Error::other)?;
    for input in inputs {
        let socket = bind_input(input.addr)
            .map_err(|e| std::io::Error::new(e.kind(), format!("--vmc-in {}: {e}", input.addr)))?;
        running.inputs.push(socket.local_addr()?);
        if input.from.is_empty() && !input.addr.ip().is_loopback() {
            tracing::warn!(
                addr = %input.addr,
                avatar = %input.avatar,
                "VMC input open to any sender that can reach it (VMC has no authentication); \
                 limit it with from=CIDR (docs/src/how-to/vmc.md)"
            );
        }
        let driver = state.new_driver_id();
        running.tasks.push(tokio::spawn(input::run(
            state.clone(),
            input.clone(),
            socket,
            vmc.clone(),
            driver,
        )));
    }
    for out in outputs {
        let local: SocketAddr = if out.addr.is_ipv4() {
            ([0, 0, 0, 0], 0).into()
        } else {
            (std::net::Ipv6Addr::UNSPECIFIED, 0).into()
        };
        let socket = UdpSocket::bind(local)
            .await
            .map_err(|e| std::io::Error::new(e.kind(), format!("--vmc-out {}: {e}", out.addr)))?;
        running.tasks.push(tokio::spawn(output::run(
            state.clone(),
            out.clone(),
            socket,
            vmc.clone(),
        )));
    }
    Ok(running)
}

#[cfg(test)]
mod tests {
    use super::*;
    use posecast_proto::msg::AvatarId;

    #[test]
    fn flags_parse() {
        let i: VmcIn = "0.0.0.0:39539=avatar".parse().unwrap();
        assert_eq!(i.addr, "0.0.0.0:39539".parse().unwrap());
        assert_eq!(i.avatar, AvatarId("avatar".into()));
        let o: VmcOut = "bob=[::1]:39540".parse().unwrap();
        assert_eq!(o.avatar, AvatarId("bob".into()));
        assert_eq!(o.addr, "[::1]:39540".parse().unwrap());
        for bad in ["0.0.0.0:39539", "host:1=a", "1.2.3.4:5=", "1.2.3.4:5=a b"] {
            assert!(bad.parse::<VmcIn>().is_err(), "{bad}");
        }
        assert!("a=nowhere".parse::<VmcOut>().is_err());
    }
}
