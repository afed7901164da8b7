//! Counters of the VMC gateway (`posecast_services::vmc`): datagrams in and what was refused, poses
//! applied, bundles sent. Kept apart (`Metrics::vmc`) like the network counters.

use crate::metrics::{counter, labelled_counters};
use prometheus_client::metrics::counter::Counter;
use prometheus_client::registry::Registry;

/// Why a whole datagram was not used.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PacketDrop {
    /// Not OSC: truncated, a bad type tag, bytes left over, not UTF-8.
    Malformed,
    /// Bundles nested deeper than `posecast_services::vmc::packet::MAX_BUNDLE_DEPTH`.
    TooDeep,
    /// Over the input's datagram rate (`posecast_services::vmc::input::MAX_PACKETS_PER_SECOND`): not
    /// even decoded.
    Flood,
    /// From a sender outside the input's allow-list (`--vmc-in …,from=CIDR`): not decoded.
    Sender,
}

impl PacketDrop {
    const ALL: [Self; 4] = [Self::Malformed, Self::TooDeep, Self::Flood, Self::Sender];

    fn label(self) -> &'static str {
        match self {
            Self::Malformed => "malformed",
            Self::TooDeep => "too_deep",
            Self::Flood => "flood",
            Self::Sender => "sender",
        }
    }
}

/// Why one message of a usable datagram was ignored (the rest of it still applies).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MessageReject {
    /// An address VMC input does not use (counted, ignored, as the VMC reference receiver does).
    UnknownAddress,
    /// Too few arguments or ones of the wrong type.
    BadArguments,
    /// NaN or infinity, a zero quaternion, a position beyond 10 km (bones, root, devices), a
    /// scale outside [0.001, 1000].
    InvalidValue,
    /// A bone name that is not one of Unity's `HumanBodyBones`.
    UnknownBone,
    /// A blend shape past the input's limit of names, or a name too long.
    BlendShapeLimit,
    /// A tracked device (`/VMC/Ext/{Hmd,Con,Tra}/Pos`) past the input's limit of serials
    /// (`posecast_services::vmc::input::MAX_DEVICES`), or a serial too long.
    DeviceLimit,
}

impl MessageReject {
    const ALL: [Self; 6] = [
        Self::UnknownAddress,
        Self::BadArguments,
        Self::InvalidValue,
        Self::UnknownBone,
        Self::BlendShapeLimit,
        Self::DeviceLimit,
    ];

    fn label(self) -> &'static str {
        match self {
            Self::UnknownAddress => "unknown_address",
            Self::BadArguments => "bad_arguments",
            Self::InvalidValue => "invalid_value",
            Self::UnknownBone => "unknown_bone",
            Self::BlendShapeLimit => "blend_shape_limit",
            Self::DeviceLimit => "device_limit",
        }
    }
}

/// Why a decoded pose did not reach its avatar.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PoseRefusal {
    /// Another driver (a websocket connection) drives the avatar: the input waits.
    Busy,
    /// No avatar of that id (yet): the input waits.
    NoAvatar,
    /// The avatar's rig cannot be retargeted from a humanoid (no `humanoid_root`), or, for a
    /// sender of tracked devices only, lacks the joints the tracker solve needs.
    NotHumanoid,
}

impl PoseRefusal {
    const ALL: [Self; 3] = [Self::Busy, Self::NoAvatar, Self::NotHumanoid];

    /// The label in `/metrics` and logs.
    #[must_use]
    pub fn label(self) -> &'static str {
        match self {
            Self::Busy => "busy",
            Self::NoAvatar => "no_avatar",
            Self::NotHumanoid => "not_humanoid",
        }
    }
}

/// Index of `x` in `all`, for the labelled counter arrays.
fn index<T: PartialEq>(all: &[T], x: &T) -> usize {
    all.iter().position(|a| a == x).unwrap_or(0)
}

/// The VMC counters. Relaxed atomics: exact totals, no ordering.
#[derive(Debug)]
pub struct VmcCounters {
    packets: Counter,
    packet_bytes: Counter,
    dropped: [Counter; PacketDrop::ALL.len()],
    rejected: [Counter; MessageReject::ALL.len()],
    poses: Counter,
    refused: [Counter; PoseRefusal::ALL.len()],
    bundles_sent: Counter,
    bytes_sent: Counter,
    send_errors: Counter,
}

impl VmcCounters {
    /// All zero, in a registry of their own (a relay that decodes VMC outside a server).
    #[must_use]
    pub fn standalone() -> Self {
        Self::new(&mut Registry::default())
    }

    /// All zero, registered in `registry`.
    pub(crate) fn new(registry: &mut Registry) -> Self {
        let r = registry;
        Self {
            packets: counter(r, "vmc_packets", "VMC datagrams received"),
            packet_bytes: counter(r, "vmc_packet_bytes", "Bytes of VMC datagrams received"),
            dropped: labelled_counters(
                r,
                "vmc_packets_dropped",
                "VMC datagrams not used at all",
                "reason",
                PacketDrop::ALL.map(PacketDrop::label),
            ),
            rejected: labelled_counters(
                r,
                "vmc_messages_rejected",
                "VMC messages ignored (the rest of their datagram applied)",
                "reason",
                MessageReject::ALL.map(MessageReject::label),
            ),
            poses: counter(r, "vmc_poses", "VMC poses applied to avatars"),
            refused: labelled_counters(
                r,
                "vmc_poses_refused",
                "VMC poses that could not be applied to their avatar",
                "reason",
                PoseRefusal::ALL.map(PoseRefusal::label),
            ),
            bundles_sent: counter(r, "vmc_bundles_sent", "VMC bundles sent by --vmc-out"),
            bytes_sent: counter(r, "vmc_bytes_sent", "Bytes of VMC bundles sent"),
            send_errors: counter(r, "vmc_send_errors", "VMC bundles the socket refused"),
        }
    }

    /// A datagram of `bytes` arrived.
    pub fn packet(&self, bytes: usize) {
        self.packets.inc();
        self.packet_bytes.inc_by(bytes as u64);
    }

    /// A datagram was not used.
    pub fn dropped(&self, why: PacketDrop) {
        self.dropped[index(&PacketDrop::ALL, &why)].inc();
    }

    /// A message was ignored.
    pub fn rejected(&self, why: MessageReject) {
        self.rejected[index(&MessageReject::ALL, &why)].inc();
    }

    /// A pose reached its avatar.
    pub fn pose(&self) {
        self.poses.inc();
    }

    /// A pose could not reach its avatar.
    pub fn refused(&self, why: PoseRefusal) {
        self.refused[index(&PoseRefusal::ALL, &why)].inc();
    }

    /// A bundle of `bytes` went out; `ok` whether the socket took it.
    pub fn sent(&self, bytes: usize, ok: bool) {
        if ok {
            self.bundles_sent.inc();
            self.bytes_sent.inc_by(bytes as u64);
        } else {
            self.send_errors.inc();
        }
    }

    /// Datagrams received so far.
    #[must_use]
    pub fn packets(&self) -> u64 {
        self.packets.get()
    }

    /// Datagrams dropped so far for `why`.
    #[must_use]
    pub fn dropped_total(&self, why: PacketDrop) -> u64 {
        self.dropped[index(&PacketDrop::ALL, &why)].get()
    }

    /// Messages rejected so far for `why`.
    #[must_use]
    pub fn rejected_total(&self, why: MessageReject) -> u64 {
        self.rejected[index(&MessageReject::ALL, &why)].get()
    }

    /// Poses applied so far.
    #[must_use]
    pub fn poses(&self) -> u64 {
        self.poses.get()
    }

    /// Poses refused so far for `why`.
    #[must_use]
    pub fn refused_total(&self, why: PoseRefusal) -> u64 {
        self.refused[index(&PoseRefusal::ALL, &why)].get()
    }

    /// Bundles sent so far.
    #[must_use]
    pub fn bundles_sent(&self) -> u64 {
        self.bundles_sent.get()
    }
}
