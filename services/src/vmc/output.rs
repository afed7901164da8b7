//! VMC out: an avatar's pose sent every tick as one VMC bundle to a fixed UDP address.
//!
//! [`Encoder`] is the inverse of VMC in: the avatar is the *source* and the VMC T-pose rig
//! (fitted to it, [`VmcRig::for_target`]) the *target* of the same world-space retargeting
//! ([`PoseRetargeter`]): every mapped Unity bone takes the world rotation of the avatar joint
//! with its H-Anim name, its normalised local rotation `L'_j = G_parent(j)⁻¹ G_j` goes back to
//! VMC's T-pose frame (`R = V_parent⁻¹ · L' · V`, [`VmcRig::from_normalised`]) and to Unity's
//! frame (mirror X). The hips' position is the avatar's `humanoid_root` mapped onto the T-pose
//! rig's size (hip-height ratio); the root is the avatar's placement.
//!
//! The bundle: `/VMC/Ext/OK 1`, `/VMC/Ext/T seconds`, `/VMC/Ext/Root/Pos "root" p q`, one
//! `/VMC/Ext/Bone/Pos name p q` per Unity bone mapped onto the avatar (position: the T-pose
//! rig's offset; the hips: their position), and blend shapes ([`blend_values`]):
//! `/VMC/Ext/Blend/Val name value` for each and `/VMC/Ext/Blend/Apply`. An avatar with morph
//! channels sends every channel by its own name (an ARKit rig's are ARKit's, what "perfect
//! sync" receivers read) and every VRM 0.x clip name its expressions map onto a channel
//! (`Joy`, `A`, `Blink_L`: the names VMC receivers compare, case-sensitively); one without
//! passes on the values a VMC performer sent it.

use std::sync::Arc;
use std::time::Duration;

use glam::{Mat4, Quat, Vec3};
use posecast_proto::Transform;
use posecast_proto::fk::forward_kinematics;
use rosc::{OscBundle, OscMessage, OscPacket, OscTime, OscType};
use tokio::net::UdpSocket;
use tracing::debug;

use super::rig::VmcRig;
use super::unity::{BONES, mirror_position, mirror_rotation};
use crate::config::VmcOut;
use crate::state::Services;
use posecast_rigs::rig::Rig;
use posecast_rigs::rig::retarget::{PoseRetargeter, PoseScratch};
use posecast_sim::avatar::Avatar;

/// The blend shape values VMC out sends for `avatar`: with morph channels, each channel's
/// weight by the channel's own name, then by every VRM 0.x clip name (exact case) whose VRM
/// 1.0 preset the avatar's file defines (its set weight) or its expressions map onto a channel
/// (unless a channel has that name);
/// without channels, the values a VMC performer sent (passed on unchanged).
#[must_use]
pub fn blend_values(avatar: &Avatar) -> Vec<(String, f32)> {
    let d = &avatar.description;
    if d.morph_targets.is_empty() {
        return avatar
            .live
            .as_ref()
            .map(|l| l.blend_shapes.clone().into_iter().collect())
            .unwrap_or_default();
    }
    let weight = |c: usize| avatar.morph_shown.get(c).copied().unwrap_or(0.0);
    let mut out: Vec<(String, f32)> = d
        .morph_targets
        .iter()
        .enumerate()
        .map(|(c, name)| (name.clone(), weight(c)))
        .collect();
    for (vmc_name, preset) in posecast_proto::expressions::vmc_blend_names() {
        if d.morph_targets.iter().any(|n| n == vmc_name) {
            continue;
        }
        // The file's own expression of that preset (a VRM's) sends its set weight; else the
        // channel the expression map gives.
        if let Some(k) = d.expression_binds.iter().position(|e| e.name == preset) {
            let w = avatar.expression_weights.get(k).copied().unwrap_or(0.0);
            out.push((vmc_name.to_owned(), w));
            continue;
        }
        let channel = d
            .expressions
            .get(preset)
            .and_then(|own| d.morph_targets.iter().position(|n| n == own));
        if let Some(c) = channel {
            out.push((vmc_name.to_owned(), weight(c)));
        }
    }
    out
}

/// Turns poses of avatars of one rig into VMC bundles.
#[derive(Debug)]
pub struct Encoder {
    rig_name: String,
    vmc: Arc<VmcRig>,
    map: PoseRetargeter,
    scratch: PoseScratch,
    /// The Unity bones sent: those whose H-Anim name the avatar's rig has.
    bones: Vec<usize>,
    rotations: Vec<Quat>,
    out: Vec<Quat>,
    world: Vec<Mat4>,
    bytes: Vec<u8>,
}

impl Encoder {
    /// An encoder for avatars of `rig`.
    ///
    /// # Errors
    /// The rig has no `humanoid_root` (or cannot be measured, see [`PoseRetargeter::new`]).
    pub fn new(vmc: Arc<VmcRig>, rig: &Rig) -> Result<Self, posecast_rigs::rig::RigError> {
        let target = vmc.for_target(rig);
        let map = PoseRetargeter::new(rig.view(), target.view())?;
        let scratch = PoseScratch::new(rig.view(), target.view());
        let bones = target
            .hanim
            .iter()
            .enumerate()
            .filter(|(_, h)| {
                h.as_deref()
                    .is_some_and(|h| rig.hanim.iter().any(|r| r.as_deref() == Some(h)))
            })
            .map(|(j, _)| j)
            .collect();
        Ok(Self {
            rig_name: rig.name.clone(),
            vmc,
            map,
            scratch,
            bones,
            rotations: Vec::with_capacity(rig.skeleton().len()),
            out: vec![Quat::IDENTITY; BONES.len()],
            world: vec![Mat4::IDENTITY; rig.skeleton().len()],
            bytes: Vec::with_capacity(4096),
        })
    }

    /// The Unity bones this encoder sends (indices into [`BONES`]).
    #[must_use]
    pub fn bones(&self) -> &[usize] {
        &self.bones
    }

    /// Encodes `avatar`'s current pose at sender time `time` (seconds); returns the bytes.
    pub fn encode(&mut self, avatar: &Avatar, time: f32) -> &[u8] {
        let rig = &avatar.rig;
        self.rotations.clear();
        self.rotations
            .extend(avatar.locals.iter().map(|t| t.rotation));
        self.map
            .solve(&self.rotations, &mut self.scratch, &mut self.out);
        // The hips: the avatar's humanoid_root in world space, onto the T-pose rig's size.
        let locals: &[Transform] = &avatar.locals;
        forward_kinematics(rig.skeleton(), locals, &mut self.world);
        let src = self
            .world
            .get(self.map.src_root)
            .map_or(Vec3::ZERO, |w| w.w_axis.truncate());
        let hips = self.map.tgt_start + self.map.k * (src - self.map.src_start);
        let placement = avatar.placing.current();
        let mut content = Vec::with_capacity(self.bones.len() + 4);
        content.push(message("/VMC/Ext/OK", vec![OscType::Int(1)]));
        content.push(message("/VMC/Ext/T", vec![OscType::Float(time)]));
        content.push(pose_message(
            "/VMC/Ext/Root/Pos",
            "root",
            mirror_position(placement.position),
            mirror_rotation(placement.rotation),
        ));
        for &j in &self.bones {
            let Some(bone) = BONES.get(j) else { continue };
            let local = self.out.get(j).copied().unwrap_or(Quat::IDENTITY);
            let r = self.vmc.from_normalised(j, local);
            let p = if j == 0 {
                hips
            } else {
                Vec3::from(bone.offset)
            };
            content.push(pose_message(
                "/VMC/Ext/Bone/Pos",
                bone.name,
                mirror_position(p),
                mirror_rotation(r),
            ));
        }
        let blends = blend_values(avatar);
        if !blends.is_empty() {
            for (name, value) in blends {
                content.push(message(
                    "/VMC/Ext/Blend/Val",
                    vec![OscType::String(name), OscType::Float(value)],
                ));
            }
            content.push(message("/VMC/Ext/Blend/Apply", Vec::new()));
        }
        let packet = OscPacket::Bundle(OscBundle {
            // "Immediately" (OSC 1.0: seconds 0, fraction 1).
            timetag: OscTime {
                seconds: 0,
                fractional: 1,
            },
            content,
        });
        self.bytes.clear();
        if rosc::encoder::encode_into(&packet, &mut self.bytes).is_err() {
            self.bytes.clear();
        }
        &self.bytes
    }
}

fn message(addr: &str, args: Vec<OscType>) -> OscPacket {
    OscPacket::Message(OscMessage {
        addr: addr.to_owned(),
        args,
    })
}

fn pose_message(addr: &str, name: &str, p: Vec3, q: Quat) -> OscPacket {
    let mut args = Vec::with_capacity(8);
    args.push(OscType::String(name.to_owned()));
    args.extend(p.to_array().map(OscType::Float));
    args.extend(q.to_array().map(OscType::Float));
    message(addr, args)
}

/// Sends `out.avatar`'s pose to `out.addr` after every tick of its scene, until the server
/// stops. Waits (checking once a second) while the avatar does not exist.
pub async fn run(state: Arc<Services>, out: VmcOut, socket: UdpSocket, vmc: Arc<VmcRig>) {
    let started = std::time::Instant::now();
    let mut encoder: Option<Encoder> = None;
    loop {
        let Ok(scene) = state.world.find_avatar(&out.avatar) else {
            tokio::time::sleep(Duration::from_secs(1)).await;
            continue;
        };
        let mut ticks = scene.ticks();
        loop {
            // A scene deleted while this waits never ticks again: look for the avatar anew.
            match tokio::time::timeout(Duration::from_secs(1), ticks.changed()).await {
                Ok(Ok(())) => {}
                Ok(Err(_)) | Err(_) => break,
            }
            let len = {
                let mut s = scene.lock();
                let Some(a) = s.avatar_mut(&out.avatar) else {
                    break;
                };
                if encoder.as_ref().is_none_or(|e| e.rig_name != a.rig.name) {
                    encoder = match Encoder::new(vmc.clone(), &a.rig) {
                        Ok(e) => Some(e),
                        Err(e) => {
                            debug!(avatar = %out.avatar, error = %e, "VMC out: rig not humanoid");
                            None
                        }
                    };
                }
                let Some(e) = encoder.as_mut() else { continue };
                e.encode(a, started.elapsed().as_secs_f32()).len()
            };
            let Some(e) = encoder.as_ref() else { continue };
            let bytes = e.bytes.get(..len).unwrap_or_default();
            let ok = match socket.send_to(bytes, out.addr).await {
                Ok(_) => true,
                Err(err) => {
                    debug!(addr = %out.addr, error = %err, "VMC out: send failed");
                    false
                }
            };
            state.metrics.vmc.sent(len, ok);
        }
    }
}
