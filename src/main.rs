//! `posecast`: starts the server. With no flags it loads the built-in avatar into scene
//! `default` playing `idle` on 127.0.0.1:8080 at 60 Hz. Every flag is also an environment
//! variable.

use clap::Parser;
use posecast_server::auth::{AccessConfig, Role, Secret, TokenRule};
use posecast_server::config::{
    Config, DEFAULT_MAX_CONNECTIONS, DEFAULT_MAX_CONNECTIONS_PER_ADDRESS, DEFAULT_MAX_UPLOAD_BYTES,
    DEFAULT_TCP_NOTSENT_LOWAT, NatsSecurity, NetLimits,
};
use posecast_server::quota::{CommandRate, Quotas};
use posecast_server::readiness::Phase;
use posecast_server::service::limits::raise_nofile_limit;
use posecast_server::startup::{DEFAULT_SCENE, Server};
use posecast_server::vmc::{VmcInputs, VmcOut};
use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;
use tracing_subscriber::filter::{FilterExt, LevelFilter, Targets};
use tracing_subscriber::layer::SubscriberExt;
use tracing_subscriber::util::SubscriberInitExt;
use tracing_subscriber::{EnvFilter, Layer};

// jemalloc, built without thread caches and with 1 s decay (.cargo/config.toml), gives the
// memory of closed connections back to the OS within ~2 s; glibc's malloc and mimalloc kept
// all of it resident (`docs/src/reference/hardening.md`).
#[cfg(feature = "jemalloc")]
#[global_allocator]
static GLOBAL: tikv_jemallocator::Jemalloc = tikv_jemallocator::Jemalloc;

#[cfg(all(feature = "mimalloc", not(feature = "jemalloc")))]
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

/// posecast: a network animation server for virtual humans.
#[derive(Debug, Parser)]
#[command(version, about)]
struct Args {
    /// Log lines as text for people, or one JSON object per line (`json`). Connections,
    /// every state-changing command and upload (target `posecast::audit`: op, target, token
    /// name, outcome, refusals included), start and stop are logged at `info`; reads at
    /// `debug`. `RUST_LOG` sets the level.
    #[arg(long, env = "POSECAST_LOG_FORMAT", value_enum, default_value_t = LogFormat::Text)]
    log_format: LogFormat,
    /// Address to listen on.
    #[arg(long, env = "POSECAST_LISTEN", default_value = "127.0.0.1:8080")]
    listen: SocketAddr,
    /// WebTransport (HTTP/3 over QUIC) on this UDP address, beside the websocket: the same
    /// protocol, frames as datagrams (no head-of-line stalls on a lossy link). Off without it.
    /// `GET /api/quic` tells clients the port and the certificate's hash;
    /// `docs/src/how-to/webtransport.md`.
    #[arg(long, env = "POSECAST_QUIC_LISTEN")]
    quic_listen: Option<SocketAddr>,
    /// The WebTransport endpoint's certificate chain (PEM), with --quic-key. Without both, a
    /// self-signed certificate valid 14 days is made at start (browsers accept it by its hash).
    #[arg(long, env = "POSECAST_QUIC_CERT", requires = "quic_key")]
    quic_cert: Option<PathBuf>,
    /// The WebTransport certificate's private key (PEM), with --quic-cert.
    #[arg(long, env = "POSECAST_QUIC_KEY", requires = "quic_cert")]
    quic_key: Option<PathBuf>,
    /// The congestion controller of the WebTransport endpoint's connections: the loss-driven
    /// `cubic` (default) and `new-reno`, or `bbr` (paces at the path's measured bandwidth:
    /// fresher frames on a path that loses at random; quinn marks it experimental).
    #[arg(long, env = "POSECAST_QUIC_CONGESTION", value_enum, default_value_t = Congestion::Cubic)]
    quic_congestion: Congestion,
    /// When a new WebTransport client must prove its address with a QUIC Retry (one round
    /// trip) before the server sends its handshake: `under-load` (default: once 64 handshakes
    /// are in progress, a flood of Initials), `always`, or `never`.
    #[arg(long, env = "POSECAST_QUIC_RETRY", value_enum, default_value_t = Retry::UnderLoad)]
    quic_retry: Retry,
    /// Folders whose assets (.glb, .vrm, .gltf, .bvh, .skel) are loaded at start (repeatable).
    #[arg(long = "assets", env = "POSECAST_ASSETS", value_delimiter = ',')]
    assets: Vec<PathBuf>,
    /// Pose frames per second of every scene.
    #[arg(long, env = "POSECAST_TICK_RATE", default_value_t = 60.0)]
    tick_rate: f32,
    /// Do not load the built-in avatar and the default scene.
    #[arg(long, env = "POSECAST_NO_BUILTIN")]
    no_builtin: bool,
    /// TOML file of tokens and their limits (see `docs/src/reference/access-control.md`).
    #[arg(long, env = "POSECAST_ACCESS_FILE")]
    access_file: Option<PathBuf>,
    /// Unlimited control token(s). With none here or in the access file, one is generated
    /// and printed at start.
    #[arg(
        long = "control-token",
        env = "POSECAST_CONTROL_TOKEN",
        value_delimiter = ',',
        hide_env_values = true
    )]
    control_tokens: Vec<String>,
    /// Key that tokens minted through `POST /api/tokens` are signed with (at least 32
    /// characters; the same on every server that should accept them). Without it the key is
    /// derived from --cluster-secret, else kept in DATA/token-key. Prefer the environment
    /// variable: a flag shows in `ps`.
    #[arg(long, env = "POSECAST_TOKEN_KEY", hide_env_values = true, value_parser = token_key)]
    token_key: Option<String>,
    /// View token(s) (needed to watch only with --require-view-token).
    #[arg(
        long = "view-token",
        env = "POSECAST_VIEW_TOKEN",
        value_delimiter = ',',
        hide_env_values = true
    )]
    view_tokens: Vec<String>,
    /// Viewers need a view or control token (default: anyone may watch).
    #[arg(long, env = "POSECAST_REQUIRE_VIEW_TOKEN")]
    require_view_token: bool,
    /// Data folder: scenes and uploaded assets are stored here and restored at start.
    #[arg(long = "data", env = "POSECAST_DATA", default_value = "posecast-data")]
    data: PathBuf,
    /// Keep everything in memory only (nothing is stored or restored).
    #[arg(long, env = "POSECAST_NO_PERSIST")]
    no_persist: bool,
    /// Largest upload request body, bytes.
    #[arg(long, env = "POSECAST_MAX_UPLOAD_BYTES", default_value_t = DEFAULT_MAX_UPLOAD_BYTES)]
    max_upload_bytes: usize,
    /// On SIGINT/SIGTERM, seconds to wait at most for HTTP requests to finish and every
    /// websocket's close frame (1001) to go out before exiting.
    #[arg(long, env = "POSECAST_SHUTDOWN_DRAIN", default_value = "2", value_parser = seconds)]
    shutdown_drain: Duration,
    #[command(flatten)]
    quotas: QuotaArgs,
    /// Seconds a live driver may stay silent before its avatar returns to its clip (or holds
    /// its last pose, as its `drive` asked).
    #[arg(long, env = "POSECAST_DRIVE_TIMEOUT", default_value = "2", value_parser = seconds)]
    drive_timeout: Duration,
    #[command(flatten)]
    net: NetArgs,
    /// VMC input: a UDP port whose VMC performer (VSeeFace, Warudo, XR Animator, …) drives
    /// an avatar, PORT=AVATAR or ADDR:PORT=AVATAR, then optionally ,from=CIDR,…: a bare port
    /// listens on loopback only (39539=avatar); with an address, from= lists the senders
    /// allowed, e.g.
    /// 0.0.0.0:39539=avatar,from=192.168.1.0/24,10.0.0.7 (others are dropped and counted).
    /// Repeatable, or several inputs comma-separated; `docs/src/how-to/vmc.md`.
    #[arg(long = "vmc-in", env = "POSECAST_VMC_IN")]
    vmc_in: Vec<VmcInputs>,
    /// VMC output: send an avatar's pose every tick to a VMC receiver, AVATAR=ADDR, e.g.
    /// avatar=127.0.0.1:39540 (repeatable). Only from here: no command can add one.
    #[arg(long = "vmc-out", env = "POSECAST_VMC_OUT", value_delimiter = ',')]
    vmc_out: Vec<VmcOut>,
    /// NATS server URLs (comma-separated; any one will do): run as one server of a cluster
    /// that shares scenes through NATS with JetStream (`docs/src/how-to/cluster.md`).
    #[arg(long, env = "POSECAST_NATS", value_delimiter = ',')]
    nats: Vec<String>,
    /// This server's name in the cluster (default: host name and port).
    #[arg(long, env = "POSECAST_NODE")]
    node: Option<String>,
    /// Seconds a scene's owner holds it without renewing (renewed every third of it); a scene
    /// whose owner died is ticked by another server within it.
    #[arg(long, env = "POSECAST_LEASE", default_value = "3", value_parser = seconds)]
    lease: Duration,
    #[command(flatten)]
    nats_security: NatsArgs,
    /// Secret the cluster's servers sign their relay messages with (HMAC-SHA256; the same on
    /// every server): a client that can publish on NATS cannot speak for a server without it.
    /// Prefer the environment variable: a flag shows in `ps`.
    #[arg(long, env = "POSECAST_CLUSTER_SECRET", hide_env_values = true)]
    cluster_secret: Option<String>,
}

/// How the server authenticates to NATS and checks it (`docs/src/how-to/cluster.md`,
/// "Securing NATS"). One way to authenticate at most (these or credentials in a `--nats` URL).
#[derive(clap::Args)]
struct NatsArgs {
    /// NATS credentials file (a user JWT and nkey seed, as `nsc` writes them).
    #[arg(long, env = "POSECAST_NATS_CREDS", value_name = "FILE")]
    nats_creds: Option<PathBuf>,
    /// File holding this server's NATS nkey user seed (SU…, from `nk -gen user`).
    #[arg(long, env = "POSECAST_NATS_NKEY", value_name = "FILE")]
    nats_nkey: Option<PathBuf>,
    /// NATS user name (with --nats-password).
    #[arg(long, env = "POSECAST_NATS_USER")]
    nats_user: Option<String>,
    /// NATS password (prefer the environment variable: a flag shows in `ps`).
    #[arg(long, env = "POSECAST_NATS_PASSWORD", hide_env_values = true)]
    nats_password: Option<String>,
    /// NATS token (prefer the environment variable: a flag shows in `ps`).
    #[arg(long, env = "POSECAST_NATS_TOKEN", hide_env_values = true)]
    nats_token: Option<String>,
    /// CA certificates (PEM) the NATS server's certificate must chain to; requires TLS.
    #[arg(long, env = "POSECAST_NATS_TLS_CA", value_name = "FILE")]
    nats_tls_ca: Option<PathBuf>,
    /// Client certificate (PEM) for NATS servers that verify clients (with --nats-tls-key);
    /// requires TLS.
    #[arg(long, env = "POSECAST_NATS_TLS_CERT", value_name = "FILE")]
    nats_tls_cert: Option<PathBuf>,
    /// The client certificate's private key (PEM).
    #[arg(long, env = "POSECAST_NATS_TLS_KEY", value_name = "FILE")]
    nats_tls_key: Option<PathBuf>,
}

impl std::fmt::Debug for NatsArgs {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let secret = |s: &Option<String>| s.as_ref().map(|_| "***");
        f.debug_struct("NatsArgs")
            .field("nats_creds", &self.nats_creds)
            .field("nats_nkey", &self.nats_nkey)
            .field("nats_user", &self.nats_user)
            .field("nats_password", &secret(&self.nats_password))
            .field("nats_token", &secret(&self.nats_token))
            .field("nats_tls_ca", &self.nats_tls_ca)
            .field("nats_tls_cert", &self.nats_tls_cert)
            .field("nats_tls_key", &self.nats_tls_key)
            .finish()
    }
}

impl NatsArgs {
    fn security(self) -> NatsSecurity {
        NatsSecurity {
            creds: self.nats_creds,
            nkey: self.nats_nkey,
            user: self.nats_user,
            password: self.nats_password,
            token: self.nats_token,
            tls_ca: self.nats_tls_ca,
            tls_cert: self.nats_tls_cert,
            tls_key: self.nats_tls_key,
        }
    }
}

/// Quotas and the command rate limit (`posecast_server::quota`).
#[derive(Debug, clap::Args)]
struct QuotaArgs {
    /// Most scenes on the server.
    #[arg(long, env = "POSECAST_MAX_SCENES", default_value_t = Quotas::default().max_scenes)]
    max_scenes: usize,
    /// Most avatars in one scene.
    #[arg(long, env = "POSECAST_MAX_AVATARS_PER_SCENE", default_value_t = Quotas::default().max_avatars_per_scene)]
    max_avatars_per_scene: usize,
    /// Most joints of an uploaded rig.
    #[arg(long, env = "POSECAST_MAX_JOINTS", default_value_t = Quotas::default().max_joints)]
    max_joints: usize,
    /// Most joints of a rig a limited token may place in a scene.
    #[arg(long, env = "POSECAST_LIMITED_MAX_JOINTS", default_value_t = Quotas::default().limited_max_joints)]
    limited_max_joints: usize,
    /// Most clip duration × joints (joint-seconds) of an uploaded clip.
    #[arg(long, env = "POSECAST_MAX_CLIP_JOINT_SECONDS", default_value_t = Quotas::default().max_clip_joint_seconds)]
    max_clip_joint_seconds: f64,
    /// Most bytes of one uploaded asset's files, added clips included.
    #[arg(long, env = "POSECAST_MAX_ASSET_BYTES", default_value_t = Quotas::default().max_asset_bytes)]
    max_asset_bytes: u64,
    /// Most bytes of all uploaded assets together.
    #[arg(long, env = "POSECAST_MAX_UPLOAD_TOTAL_BYTES", default_value_t = Quotas::default().max_upload_total_bytes)]
    max_upload_total_bytes: u64,
    /// Commands per second one websocket connection may send, sustained.
    #[arg(long, env = "POSECAST_COMMAND_RATE", default_value_t = CommandRate::default().per_second)]
    command_rate: f64,
    /// Commands one connection may send in a burst above the sustained rate.
    #[arg(long, env = "POSECAST_COMMAND_BURST", default_value_t = CommandRate::default().burst)]
    command_burst: f64,
}

impl QuotaArgs {
    fn quotas(&self) -> Quotas {
        Quotas {
            max_scenes: self.max_scenes,
            max_avatars_per_scene: self.max_avatars_per_scene,
            max_joints: self.max_joints,
            limited_max_joints: self.limited_max_joints,
            max_clip_joint_seconds: self.max_clip_joint_seconds,
            max_asset_bytes: self.max_asset_bytes,
            max_upload_total_bytes: self.max_upload_total_bytes,
        }
    }
}

/// Network timeouts and connection caps (`NetLimits`; `docs/src/reference/hardening.md`).
#[derive(Debug, clap::Args)]
struct NetArgs {
    /// Seconds a websocket has to send its hello after the upgrade (then `timeout`, close 1008).
    #[arg(long, env = "POSECAST_HELLO_TIMEOUT", default_value = "5", value_parser = timeout)]
    hello_timeout: Duration,
    /// Seconds to receive an HTTP request head (and the idle time of a kept-alive connection).
    #[arg(long, env = "POSECAST_HEADER_READ_TIMEOUT", default_value = "10", value_parser = timeout)]
    header_read_timeout: Duration,
    /// Seconds to receive an HTTP request body (then 408 `timeout`).
    #[arg(long, env = "POSECAST_BODY_READ_TIMEOUT", default_value = "120", value_parser = timeout)]
    body_read_timeout: Duration,
    /// Seconds between the server's pings on a websocket.
    #[arg(long, env = "POSECAST_WS_PING_INTERVAL", default_value = "15", value_parser = timeout)]
    ws_ping_interval: Duration,
    /// Seconds without anything from a websocket client (not even a pong) before it is closed.
    #[arg(long, env = "POSECAST_WS_IDLE_TIMEOUT", default_value = "45", value_parser = timeout)]
    ws_idle_timeout: Duration,
    /// Open connections at most (HTTP and websocket); more get 503 / close 1013. Lowered to
    /// fit the open-files limit.
    #[arg(long, env = "POSECAST_MAX_CONNECTIONS", default_value_t = DEFAULT_MAX_CONNECTIONS,
          value_parser = at_least_one)]
    max_connections: usize,
    /// Open connections from one client address at most (IPv6: one /64).
    #[arg(long, env = "POSECAST_MAX_CONNECTIONS_PER_ADDRESS",
          default_value_t = DEFAULT_MAX_CONNECTIONS_PER_ADDRESS, value_parser = at_least_one)]
    max_connections_per_address: usize,
    /// Unsent bytes the kernel may hold per connection (TCP_NOTSENT_LOWAT; 0: the kernel's
    /// default): past them the server keeps only the newest frames itself.
    #[arg(long, env = "POSECAST_TCP_NOTSENT_LOWAT", default_value_t = DEFAULT_TCP_NOTSENT_LOWAT)]
    tcp_notsent_lowat: u32,
    /// Write websocket frames into the socket from the tick's fan-out itself, with no task
    /// woken per frame (less CPU a frame; experimental: fewer ticks at 2,000 viewers).
    #[arg(long, env = "POSECAST_WS_DIRECT_WRITES")]
    ws_direct_writes: bool,
}

impl NetArgs {
    fn limits(&self) -> NetLimits {
        NetLimits {
            hello_timeout: self.hello_timeout,
            header_read_timeout: self.header_read_timeout,
            body_read_timeout: self.body_read_timeout,
            ws_ping_interval: self.ws_ping_interval,
            ws_idle_timeout: self.ws_idle_timeout,
            max_connections: self.max_connections,
            max_connections_per_address: self.max_connections_per_address,
            tcp_notsent_lowat: self.tcp_notsent_lowat,
            ws_direct_writes: self.ws_direct_writes,
        }
    }
}

/// A timeout in seconds: [`seconds`], but not 0 (which would close every connection at once).
fn timeout(text: &str) -> Result<Duration, String> {
    let d = seconds(text)?;
    if d.is_zero() {
        Err("a timeout must be more than 0 s".to_owned())
    } else {
        Ok(d)
    }
}

/// A count of at least 1 (a cap of 0 would refuse everyone).
fn at_least_one(text: &str) -> Result<usize, String> {
    match text.parse::<usize>() {
        Ok(n) if n >= 1 => Ok(n),
        _ => Err(format!("{text:?} is not a whole number of at least 1")),
    }
}

/// Raises the soft open-files limit to the hard one: each connection is a descriptor, and the
/// usual soft limit of 1,024 would cap the server near a thousand clients.
fn raise_open_files_limit() {
    match raise_nofile_limit() {
        Ok((before, soft, hard)) => {
            tracing::info!(before, soft, hard, "open-files limit (RLIMIT_NOFILE)");
        }
        Err(e) => tracing::warn!(error = %e, "cannot raise the open-files limit"),
    }
}

/// A duration in seconds, 0 to 3600 (fractions allowed).
fn seconds(text: &str) -> Result<Duration, String> {
    let s: f64 = text
        .parse()
        .map_err(|_| format!("{text:?} is not a number of seconds"))?;
    if (0.0..=3600.0).contains(&s) {
        Ok(Duration::from_secs_f64(s))
    } else {
        Err(format!("{text} s is not between 0 and 3600"))
    }
}

/// `--quic-congestion`'s values ([`posecast_server::config::QuicCongestion`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum Congestion {
    Bbr,
    Cubic,
    NewReno,
}

impl From<Congestion> for posecast_server::config::QuicCongestion {
    fn from(c: Congestion) -> Self {
        match c {
            Congestion::Bbr => Self::Bbr,
            Congestion::Cubic => Self::Cubic,
            Congestion::NewReno => Self::NewReno,
        }
    }
}

/// `--quic-retry`'s values ([`posecast_server::config::QuicRetry`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum Retry {
    Never,
    UnderLoad,
    Always,
}

impl From<Retry> for posecast_server::config::QuicRetry {
    fn from(r: Retry) -> Self {
        match r {
            Retry::Never => Self::Never,
            Retry::UnderLoad => Self::UnderLoad,
            Retry::Always => Self::Always,
        }
    }
}

/// How log lines are written (`--log-format`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum LogFormat {
    /// For people.
    Text,
    /// One JSON object per line.
    Json,
}

/// Libraries whose logs are capped at `debug` whatever `RUST_LOG` asks: at `trace` they print
/// every websocket frame and message they read, which carries the `hello`'s token (tungstenite's
/// "Received message …", through the `log` bridge). Their `debug` lines name only close frames
/// and handshake steps.
const FRAME_LOGGING_TARGETS: [&str; 3] = ["tungstenite", "tokio_tungstenite", "axum::extract::ws"];

/// `RUST_LOG` (default `info`), with [`FRAME_LOGGING_TARGETS`] capped at `debug`. The cap is a
/// separate filter and-ed with `RUST_LOG`, so no directive in it (e.g. `tungstenite=trace`) can
/// lift it.
fn init_logging(format: LogFormat) {
    // A `RUST_LOG` that does not parse is said, not silently replaced.
    let (requested, bad) = match std::env::var("RUST_LOG") {
        Ok(v) if !v.trim().is_empty() => match EnvFilter::try_new(&v) {
            Ok(f) => (f, None),
            Err(e) => (EnvFilter::new("info"), Some(format!("{v:?}: {e}"))),
        },
        _ => (EnvFilter::new("info"), None),
    };
    let capped = FRAME_LOGGING_TARGETS.iter().fold(
        Targets::new().with_default(LevelFilter::TRACE),
        |t, target| t.with_target(*target, LevelFilter::DEBUG),
    );
    let filter = requested.and(capped);
    match format {
        LogFormat::Text => tracing_subscriber::registry()
            .with(tracing_subscriber::fmt::layer().with_filter(filter))
            .init(),
        // One JSON object per line (fields, span fields, target, level, time), for log
        // pipelines.
        LogFormat::Json => tracing_subscriber::registry()
            .with(
                tracing_subscriber::fmt::layer()
                    .json()
                    .with_current_span(true)
                    .with_filter(filter),
            )
            .init(),
    }
    if let Some(bad) = bad {
        tracing::warn!("RUST_LOG {bad}; logging at info instead");
    }
}

/// `--token-key`: long enough to resist guessing.
fn token_key(text: &str) -> Result<String, String> {
    let min = posecast_server::auth::minted::MIN_KEY_CHARS;
    if text.chars().count() < min {
        return Err(format!("shorter than {min} characters"));
    }
    Ok(text.to_owned())
}

/// The access rules from the file and flags, and a generated control token when none is
/// configured (to print once).
fn access(args: &Args) -> anyhow::Result<(AccessConfig, Option<Secret>)> {
    let mut access = match &args.access_file {
        Some(path) => {
            let text = std::fs::read_to_string(path)
                .map_err(|e| anyhow::anyhow!("cannot read {}: {e}", path.display()))?;
            AccessConfig::from_toml(&text, |var| std::env::var(var).ok())
                .map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?
        }
        None => AccessConfig::default(),
    };
    if args.require_view_token {
        access.open_view = false;
    }
    // The flags' own names in the errors (the rules' names, `control-1`, are internal).
    for (flag, role, tokens) in [
        ("control", Role::Control, &args.control_tokens),
        ("view", Role::View, &args.view_tokens),
    ] {
        for (i, t) in tokens.iter().enumerate() {
            access
                .add(TokenRule::new(
                    format!("{flag}-{}", i + 1),
                    Secret::new(t.as_str()),
                    role,
                ))
                .map_err(|e| match e {
                    posecast_server::auth::AccessConfigError::Token { message, .. } => {
                        anyhow::anyhow!("--{flag}-token (number {}): {message}", i + 1)
                    }
                    other => other.into(),
                })?;
        }
    }
    let generated = if access.has_control_token() {
        None
    } else {
        let secret = Secret::generate();
        access.add(TokenRule::new("generated", secret.clone(), Role::Control))?;
        Some(secret)
    };
    Ok((access, generated))
}

fn main() -> anyhow::Result<()> {
    let started = std::time::Instant::now();
    // First of all, before the flags are read: the loading thread, whose import of the
    // built-in avatar (the longest step of the start) then runs beside everything up to the
    // bind (`startup::prepare`).
    let prepared = posecast_server::startup::prepare();
    let args = Args::parse();
    init_logging(args.log_format);
    if let Err(e) = prepared {
        tracing::warn!(error = %e, "cannot start loading ahead; loading once listening");
    }
    tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()?
        .block_on(run(args, started))
}

/// The server, from its arguments to its end; `started` is when the process began.
async fn run(args: Args, started: std::time::Instant) -> anyhow::Result<()> {
    anyhow::ensure!(
        args.tick_rate.is_finite() && args.tick_rate > 0.0 && args.tick_rate <= 1000.0,
        "--tick-rate must be in (0, 1000]"
    );
    // A folder named on the command line that is not there is a typo to report, not a
    // start without its assets.
    for dir in &args.assets {
        anyhow::ensure!(
            dir.is_dir(),
            "--assets {}: not a folder (missing or not a directory)",
            dir.display()
        );
    }
    let (access, generated) = access(&args)?;
    let config = Config {
        listen: args.listen,
        tick_rate: args.tick_rate,
        asset_dirs: args.assets,
        builtin: !args.no_builtin,
        access,
        data_dir: (!args.no_persist).then_some(args.data),
        max_upload_bytes: args.max_upload_bytes,
        shutdown_drain: args.shutdown_drain,
        quotas: args.quotas.quotas(),
        command_rate: CommandRate::new(args.quotas.command_rate, args.quotas.command_burst)
            .map_err(anyhow::Error::msg)?,
        drive_timeout: args.drive_timeout,
        net: args.net.limits(),
        vmc_in: args.vmc_in.into_iter().flat_map(|VmcInputs(i)| i).collect(),
        vmc_out: args.vmc_out,
        nats: args.nats,
        node: args.node,
        nats_security: args.nats_security.security(),
        cluster_secret: args.cluster_secret.map(Secret::new),
        token_key: args.token_key.map(Secret::new),
        lease_ttl: args.lease,
        quic_listen: args.quic_listen,
        quic_identity: args.quic_cert.zip(args.quic_key),
        quic_congestion: args.quic_congestion.into(),
        quic_retry: args.quic_retry.into(),
    };
    raise_open_files_limit();
    // Registered before the server listens: a SIGTERM that arrives during start-up (as soon as
    // the address is printed) must begin a graceful shutdown, not kill the process.
    let signals = shutdown_signal();
    let (config_vmc_in, config_vmc_out) = (config.vmc_in.clone(), config.vmc_out.clone());
    let mut server = Server::start(config).await?;
    let shutdown = server.take_shutdown();
    tracing::info!(addr = %server.addr, "started");
    println!("posecast listening on {}", server.http_url());
    println!(
        "  websocket: {}  (scene \"{DEFAULT_SCENE}\")",
        server.ws_url()
    );
    println!(
        "  health:    {}/healthz   metrics: {}/metrics",
        server.http_url(),
        server.http_url()
    );
    for (input, addr) in config_vmc_in.iter().zip(&server.vmc.inputs) {
        let from = if input.from.is_empty() {
            String::new()
        } else {
            let list: Vec<String> = input.from.iter().map(ToString::to_string).collect();
            format!(" (from {})", list.join(", "))
        };
        println!(
            "  VMC in:    udp://{addr} drives avatar {}{from}",
            input.avatar
        );
    }
    for out in &config_vmc_out {
        println!("  VMC out:   avatar {} to udp://{}", out.avatar, out.addr);
    }
    match generated {
        Some(token) => {
            // Printed once for the operator (stdout, not the log); configure --control-token
            // or an access file to choose it.
            println!("  control token (generated): {}", token.expose());
            println!(
                "  dashboard: {}/#control={}",
                server.http_url(),
                token.expose()
            );
        }
        None => println!("  dashboard: {}/", server.http_url()),
    }
    tokio::spawn(async move {
        signals.await;
        if let Some(tx) = shutdown {
            tx.send(()).ok();
        }
    });
    // Listening already; rigs and scenes load in the background. A failed start ends the
    // process with its error, as a data folder that cannot be opened does before listening.
    let state = server.state.clone();
    let finished = server.wait();
    tokio::pin!(finished);
    tokio::select! {
        phase = state.readiness.settled() => match phase {
            Phase::Failed(reason) => anyhow::bail!("start-up failed: {reason}"),
            Phase::Ready => {
                println!(
                    "posecast ready ({} rigs, {} scenes) {:.2} s after start",
                    state.world.library.all().len(),
                    state.world.scenes().len(),
                    started.elapsed().as_secs_f64()
                );
                tokio::spawn(async {
                    tokio::time::sleep(STARTUP_PAGES_KEPT).await;
                    let given = tokio::task::spawn_blocking(give_back_startup_code)
                        .await
                        .unwrap_or(0);
                    if given > 0 {
                        tracing::info!(
                            mapped_mib = given >> 20,
                            "start-up code unmapped"
                        );
                    }
                });
            }
            Phase::Starting | Phase::Stopped => {}
        },
        result = &mut finished => {
            tracing::info!("stopped");
            return Ok(result?);
        }
    }
    finished.await?;
    tracing::info!("stopped");
    Ok(())
}

/// How long after the server is ready [`give_back_startup_code`] runs: the start's last
/// requests (a load balancer's first `/healthz`, a dashboard opened at once) are served first
/// from pages still mapped.
const STARTUP_PAGES_KEPT: Duration = Duration::from_secs(5);

/// Gives back the pages of code and read-only data that the start touched:
/// argument parsing, the built-in avatar's import, the configuration, the restore. They were
/// mapped, 64 KiB around each first use, and stay resident though an idle server never runs
/// them again — 12 of its 15 MB resident, release build (`cargo bench -p posecast --bench
/// footprint`). `madvise(MADV_DONTNEED)` unmaps them from this process; they stay in the page
/// cache, unmapped pages the kernel reclaims first when memory is short, and what runs
/// afterwards maps its own pages back (a minor fault each), as at start. (Also dropping them
/// from the page cache, `posix_fadvise(POSIX_FADV_DONTNEED)`, freed 9–10 MB of the 30 MB
/// binary's cache but made the next start read them from disk: 13.3 instead of 10.7 ms to
/// `/healthz`.)
/// The shared libraries' pages go too (libc, libm, the loader: 1.4 MB more, of which an idle
/// server maps 0.5 MB back). Only mappings the process never wrote are unmapped: read-only
/// mappings of files (the binary, the libraries; the server maps no other file) with no
/// private copy of a page (`Anonymous: 0 kB` in `/proc/self/smaps`) — relocated data (RELRO),
/// whose pages are private copies, would lose its relocations. Returns the bytes unmapped (0
/// where unsupported: the pages then stay, as before).
#[cfg(target_os = "linux")]
#[allow(unsafe_code)]
fn give_back_startup_code() -> usize {
    let (Ok(exe), Ok(smaps)) = (
        std::fs::read_link("/proc/self/exe"),
        std::fs::read_to_string("/proc/self/smaps"),
    ) else {
        return 0;
    };
    let exe = format!(" {}", exe.to_string_lossy());
    // (start, end) of the binary's read-only mapping being read, until its `Anonymous:` line.
    let mut current: Option<(usize, usize)> = None;
    let mut given = 0;
    for line in smaps.lines() {
        let mut fields = line.split_whitespace();
        let Some(first) = fields.next() else {
            continue;
        };
        if let Some((start, end)) = first.split_once('-')
            && let (Ok(start), Ok(end)) = (
                usize::from_str_radix(start, 16),
                usize::from_str_radix(end, 16),
            )
        {
            // A mapping's header: `start-end perms offset dev inode path`.
            let read_only = fields.next().is_some_and(|perms| !perms.contains('w'));
            // The binary's, and the shared libraries' (libc, libm, the loader): the start ran
            // their code as much (the loader's relocation, the glTF import's maths).
            let file = fields.nth(3).is_some_and(|path| path.starts_with('/'));
            current = (read_only && (line.ends_with(&exe) || file)).then_some((start, end));
            continue;
        }
        if first != "Anonymous:" {
            continue;
        }
        let Some((start, end)) = current.take() else {
            continue;
        };
        if fields.next() != Some("0") {
            continue;
        }
        // SAFETY: the range is a whole read-only private file mapping of this process that
        // holds no private copy of any page: every page's contents are the file's, and after
        // MADV_DONTNEED an access maps the same file page back. No memory anything writes or
        // holds a `&mut` to changes.
        let rc =
            unsafe { libc::madvise(start as *mut libc::c_void, end - start, libc::MADV_DONTNEED) };
        if rc == 0 {
            given += end - start;
        }
    }
    given
}

#[cfg(not(target_os = "linux"))]
fn give_back_startup_code() -> usize {
    0
}

/// SIGINT or SIGTERM. The handlers are installed when this is called, not when the returned
/// future is first polled.
#[cfg(unix)]
fn shutdown_signal() -> impl std::future::Future<Output = ()> {
    use tokio::signal::unix::{SignalKind, signal};
    let install = |kind: SignalKind, name: &str| {
        signal(kind)
            .inspect_err(|e| tracing::warn!(error = %e, "cannot listen for {name}"))
            .ok()
    };
    let (mut int, mut term) = (
        install(SignalKind::interrupt(), "SIGINT"),
        install(SignalKind::terminate(), "SIGTERM"),
    );
    async move {
        tokio::select! {
            () = wait_for(int.as_mut()) => {}
            () = wait_for(term.as_mut()) => {}
        }
    }
}

/// The next signal of `s`, or never when it could not be installed.
#[cfg(unix)]
async fn wait_for(s: Option<&mut tokio::signal::unix::Signal>) {
    match s {
        Some(s) => {
            s.recv().await;
        }
        None => std::future::pending::<()>().await,
    }
}

/// Ctrl-C.
#[cfg(not(unix))]
fn shutdown_signal() -> impl std::future::Future<Output = ()> {
    async {
        if let Err(e) = tokio::signal::ctrl_c().await {
            tracing::warn!(error = %e, "cannot listen for Ctrl-C");
            std::future::pending::<()>().await;
        }
    }
}
