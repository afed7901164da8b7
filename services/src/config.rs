//! How a server runs: [`Config`], built by the `posecast` binary from flags and environment
//! (or by a test), with the network bounds it carries ([`NetLimits`]).

pub mod cidr;
mod nats;
mod vmc;

pub use cidr::{Cidr, CidrError};
pub use nats::NatsSecurity;
pub use vmc::{VmcIn, VmcInputs, VmcOut};

use crate::auth::AccessConfig;
use posecast_proto::msg::AvatarId;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

/// How the server runs (built by `main` from flags and environment).
#[derive(Debug, Clone)]
pub struct Config {
    /// Listen address.
    pub listen: SocketAddr,
    /// Pose frames per second of every scene.
    pub tick_rate: f32,
    /// Folders whose assets are loaded at start.
    pub asset_dirs: Vec<PathBuf>,
    /// Whether to load the built-in avatar into a `default` scene playing `idle`.
    pub builtin: bool,
    /// Tokens and what they allow ([`crate::auth`]).
    pub access: AccessConfig,
    /// The data folder scenes and uploads are stored in (see [`crate::store`]); `None` keeps
    /// everything in memory only.
    pub data_dir: Option<PathBuf>,
    /// Largest upload request body, bytes.
    pub max_upload_bytes: usize,
    /// Limits on scenes, avatars, rig and clip sizes, upload bytes ([`posecast_core::quota`]).
    pub quotas: posecast_core::quota::Quotas,
    /// Commands per second per connection ([`posecast_core::quota::CommandRate`]).
    pub command_rate: posecast_core::quota::CommandRate,
    /// How long a graceful shutdown waits, at most, for HTTP requests to finish and for every
    /// websocket's close frame to be sent (and answered) before the server stops regardless.
    pub shutdown_drain: Duration,

    // --- Live driving (issue 16) ---
    /// How long a live driver may stay silent before its avatar returns to its clip (or holds
    /// its last pose, as the `drive` asked).
    pub drive_timeout: Duration,
    /// Network timeouts and connection caps (`posecast_server::service::limits`).
    pub net: NetLimits,

    // --- VMC gateway (issue 17) ---
    /// UDP sockets whose VMC performer drives an avatar (`--vmc-in ADDR=AVATAR`).
    pub vmc_in: Vec<VmcIn>,
    /// Avatars whose pose is sent every tick as VMC to an address (`--vmc-out AVATAR=ADDR`).
    /// Only here, from the command line or environment: no command can add one, so nobody
    /// with a token can make the server send UDP to an address of their choosing.
    pub vmc_out: Vec<VmcOut>,

    // --- Scale-out (issue 15) ---
    /// NATS servers of the cluster (`--nats`); empty: a server on its own, as before.
    pub nats: Vec<String>,
    /// This server's name in the cluster (`--node`); `None`: host name and port.
    pub node: Option<String>,
    /// Credentials and TLS for the NATS connection (`--nats-creds`, `--nats-tls-ca`, …).
    pub nats_security: NatsSecurity,
    /// The secret relay messages are signed with (`--cluster-secret`, the same on every
    /// server of the cluster); `None`: they name their node, unsigned.
    pub cluster_secret: Option<crate::auth::Secret>,
    /// The key minted tokens are signed with (`--token-key`); `None`: derived from
    /// `cluster_secret`, else kept in the data folder ([`crate::auth::minted`]).
    pub token_key: Option<crate::auth::Secret>,
    /// How long a scene's ownership lasts unless its owner renews it (every third of it).
    pub lease_ttl: Duration,

    // --- WebTransport (issue 31) ---
    /// The UDP address of the WebTransport endpoint (`--quic-listen`); `None`: websocket only.
    pub quic_listen: Option<SocketAddr>,
    /// Its certificate chain and private key, PEM files (`--quic-cert`, `--quic-key`); `None`:
    /// a self-signed certificate made at start, valid 14 days (what browsers accept by hash),
    /// whose SHA-256 `GET /api/quic` publishes.
    pub quic_identity: Option<(PathBuf, PathBuf)>,
    /// The congestion controller of every QUIC connection (`--quic-congestion`).
    pub quic_congestion: QuicCongestion,
    /// When a client's address is proven by a Retry before its handshake (`--quic-retry`).
    pub quic_retry: QuicRetry,
}

/// The congestion controller QUIC connections use: it paces the frames' datagrams.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum QuicCongestion {
    /// BBR (quinn's, after Chromium's BBRv1, marked experimental): paces at the path's
    /// measured bandwidth and round trip, and does not take random loss for congestion:
    /// fresher frames on a path that loses at random. Not the default: with the server's
    /// machine under CPU load, its pacing held datagrams past the point where new frames are
    /// superseded (ticks missing on loopback).
    Bbr,
    /// CUBIC (RFC 9438, quinn's default): cuts its window on loss; on a path that loses at
    /// random (a radio link) it falls to its minimum window and frames queue behind it.
    #[default]
    Cubic,
    /// NewReno (RFC 9002's reference): as loss-driven as CUBIC.
    NewReno,
}

/// When the WebTransport endpoint answers a new client with a QUIC Retry (RFC 9000 §8.1.2):
/// a token the client must echo from its address, proving the address before the server
/// sends its handshake. Until an address is proven, QUIC limits what a server sends it to 3×
/// what it received — but quinn lets the last datagram overshoot (up to one datagram more);
/// a Retry answers a spoofed 1,200-byte Initial with one small packet and nothing else. It
/// costs an honest client one round trip.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum QuicRetry {
    /// Never: the handshake starts at once (the 3× limit, as quinn keeps it).
    Never,
    /// When at least [`QUIC_RETRY_LOAD`] handshakes are in progress (a flood of Initials,
    /// spoofed or not): the default.
    #[default]
    UnderLoad,
    /// Always: every new client's address is proven first.
    Always,
}

/// Handshakes in progress from which [`QuicRetry::UnderLoad`] answers new clients with a Retry.
pub const QUIC_RETRY_LOAD: usize = 64;

/// Default [`Config::lease_ttl`]: 3 s (a scene whose owner died is ticked again within it).
pub const DEFAULT_LEASE_TTL: Duration = Duration::from_secs(3);

/// Default [`Config::max_upload_bytes`]: 32 MiB.
pub const DEFAULT_MAX_UPLOAD_BYTES: usize = 32 << 20;

/// Default [`Config::shutdown_drain`]: 2 s.
pub const DEFAULT_SHUTDOWN_DRAIN: Duration = Duration::from_secs(2);

/// Default [`Config::drive_timeout`]: 2 s.
pub const DEFAULT_DRIVE_TIMEOUT: Duration = Duration::from_secs(2);

impl Default for Config {
    fn default() -> Self {
        Self {
            listen: SocketAddr::from(([127, 0, 0, 1], 8080)),
            tick_rate: 60.0,
            asset_dirs: Vec::new(),
            builtin: true,
            access: AccessConfig::default(),
            data_dir: None,
            max_upload_bytes: DEFAULT_MAX_UPLOAD_BYTES,
            quotas: posecast_core::quota::Quotas::default(),
            command_rate: posecast_core::quota::CommandRate::default(),
            shutdown_drain: DEFAULT_SHUTDOWN_DRAIN,
            drive_timeout: DEFAULT_DRIVE_TIMEOUT,
            net: NetLimits::default(),
            vmc_in: Vec::new(),
            vmc_out: Vec::new(),
            nats: Vec::new(),
            node: None,
            nats_security: NatsSecurity::default(),
            cluster_secret: None,
            token_key: None,
            lease_ttl: DEFAULT_LEASE_TTL,
            quic_listen: None,
            quic_identity: None,
            quic_congestion: QuicCongestion::default(),
            quic_retry: QuicRetry::default(),
        }
    }
}

/// Network timeouts and connection caps (`Config::net`; flags in `posecast --help`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct NetLimits {
    /// A websocket must send its `hello` this soon after the upgrade, or it gets a `timeout`
    /// error and close 1008. A viewer says hello at once; a socket that says nothing is
    /// anonymous and must not hold a connection slot for long.
    pub hello_timeout: Duration,
    /// An HTTP request head (request line and headers) must arrive within this, counted from
    /// the connection's accept or from the previous response on a kept-alive connection; so
    /// this is also the keep-alive idle time. Silent TCP connections and half-sent headers
    /// (slowloris) are closed after it.
    pub header_read_timeout: Duration,
    /// A request body must be read completely within this, counted from its head (`408
    /// timeout`). Long enough for a [`crate::config::Config::max_upload_bytes`] upload over a
    /// slow link, short enough that a client trickling a byte a second cannot keep a
    /// request open for hours.
    pub body_read_timeout: Duration,
    /// How often the server pings a websocket that said hello.
    pub ws_ping_interval: Duration,
    /// A websocket from which nothing (not even a pong) arrived for this long is closed
    /// (1008 `idle timeout`). Should span a few ping intervals so one lost pong is not fatal.
    pub ws_idle_timeout: Duration,
    /// Open TCP connections (HTTP and websocket) the server holds at most; more are refused
    /// with 503 (websocket upgrades: close 1013). Lowered at start to what the descriptor
    /// limit allows (`effective_max_connections`).
    pub max_connections: usize,
    /// Open connections from one client address at most (IPv6: one /64, which one host
    /// usually holds whole); more are refused like over [`Self::max_connections`]. Keeps one
    /// client from taking every slot.
    pub max_connections_per_address: usize,
    /// Unsent bytes the kernel may hold for one connection (`TCP_NOTSENT_LOWAT`, Linux); past
    /// them a write waits, so on a thin link the backlog stays in the connection's outbox —
    /// where a newer frame replaces an older one — not in the kernel, where it would only go
    /// stale. `0` leaves the kernel's default (no bound).
    pub tcp_notsent_lowat: u32,
    /// A websocket's frames are written into its socket by the tick's fan-out itself (no
    /// task woken per frame: `server/src/service/ws/direct.rs`) rather than by the
    /// connection's writer task. Off by default until it delivers as much as the writer
    /// tasks at 2,000 viewers and on a busy host (issue 38: it takes less CPU a frame, but the
    /// writes' shares hold up the ticker there).
    pub ws_direct_writes: bool,
}

/// Default [`NetLimits::tcp_notsent_lowat`]: 16 KiB, about one JSON frame of 10 avatars (a
/// binary one is ~1 KB).
pub const DEFAULT_TCP_NOTSENT_LOWAT: u32 = 16 << 10;

/// Default [`NetLimits::hello_timeout`]: 5 s.
pub const DEFAULT_HELLO_TIMEOUT: Duration = Duration::from_secs(5);
/// Default [`NetLimits::header_read_timeout`]: 10 s.
pub const DEFAULT_HEADER_READ_TIMEOUT: Duration = Duration::from_secs(10);
/// Default [`NetLimits::body_read_timeout`]: 120 s (32 MiB at ~280 KB/s).
pub const DEFAULT_BODY_READ_TIMEOUT: Duration = Duration::from_secs(120);
/// Default [`NetLimits::ws_ping_interval`]: 15 s.
pub const DEFAULT_WS_PING_INTERVAL: Duration = Duration::from_secs(15);
/// Default [`NetLimits::ws_idle_timeout`]: 45 s (three pings).
pub const DEFAULT_WS_IDLE_TIMEOUT: Duration = Duration::from_secs(45);
/// Default [`NetLimits::max_connections`]: 10,000.
pub const DEFAULT_MAX_CONNECTIONS: usize = 10_000;
/// Default [`NetLimits::max_connections_per_address`]: 256.
pub const DEFAULT_MAX_CONNECTIONS_PER_ADDRESS: usize = 256;

impl Default for NetLimits {
    fn default() -> Self {
        Self {
            hello_timeout: DEFAULT_HELLO_TIMEOUT,
            header_read_timeout: DEFAULT_HEADER_READ_TIMEOUT,
            body_read_timeout: DEFAULT_BODY_READ_TIMEOUT,
            ws_ping_interval: DEFAULT_WS_PING_INTERVAL,
            ws_idle_timeout: DEFAULT_WS_IDLE_TIMEOUT,
            max_connections: DEFAULT_MAX_CONNECTIONS,
            max_connections_per_address: DEFAULT_MAX_CONNECTIONS_PER_ADDRESS,
            tcp_notsent_lowat: DEFAULT_TCP_NOTSENT_LOWAT,
            ws_direct_writes: false,
        }
    }
}

/// An avatar id given on the command line.
pub(crate) fn avatar_id(s: &str) -> Result<AvatarId, String> {
    posecast_proto::msg::check_id("avatar", s).map_err(|e| e.message)?;
    Ok(AvatarId(s.to_owned()))
}
