//! `posecast-client`: watch a stream's statistics, render a scene offscreen to PNG, view it
//! live in a window, drive an avatar live from a BVH clip, or relay a VTuber tool's VMC stream
//! to a server. Every flag can also be set by an environment variable.

mod drive;
mod render;
mod view;
mod vmc_relay;
mod watch;

use clap::{Args, Parser, Subcommand};
use posecast_client::net::{Client, ClientOptions, TransportChoice};
use posecast_proto::msg::Encoding;

#[derive(Debug, Parser)]
#[command(name = "posecast-client", version, about)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Connect and print stream statistics once per second.
    Watch(watch::WatchArgs),
    /// Render a scene offscreen (no window; works on lavapipe) and write a PNG.
    Render(render::RenderArgs),
    /// Show a scene live in a window.
    View(view::ViewArgs),
    /// Drive an avatar live from a BVH clip (uploaded as the source rig, retargeted by the
    /// server).
    Drive(drive::DriveArgs),
    /// Relay a VTuber tool's VMC stream (UDP, on this machine) to an avatar on a server
    /// anywhere, over an authenticated websocket.
    VmcRelay(vmc_relay::VmcRelayArgs),
}

/// Where to connect; shared by every subcommand.
#[derive(Debug, Args)]
struct Connection {
    /// The server's websocket URL.
    #[arg(long, env = "POSECAST_URL", default_value = "ws://127.0.0.1:8080/ws")]
    url: String,
    /// Other servers of the same cluster (`posecast --nats`), tried in turn when `--url`
    /// cannot be reached or drops (comma-separated websocket URLs).
    #[arg(long, env = "POSECAST_FALLBACK_URLS", value_delimiter = ',')]
    fallback_url: Vec<String>,
    /// The scene to subscribe to.
    #[arg(long, env = "POSECAST_SCENE", default_value = "default")]
    scene: String,
    /// View or control token, when the server requires one.
    #[arg(long, env = "POSECAST_TOKEN")]
    token: Option<String>,
    /// Receive JSON text frames instead of binary ones.
    #[arg(long, env = "POSECAST_JSON_FRAMES")]
    json_frames: bool,
    /// The transport: `auto` tries WebTransport (frames as datagrams) when the server offers
    /// it (`--quic-listen`) and falls back to the websocket; `websocket` or `webtransport`
    /// use that one only.
    #[arg(long, env = "POSECAST_TRANSPORT", default_value = "auto", value_parser = transport_choice)]
    transport: TransportChoice,
}

fn transport_choice(s: &str) -> Result<TransportChoice, String> {
    match s {
        "auto" => Ok(TransportChoice::Auto),
        "websocket" | "ws" => Ok(TransportChoice::WebSocket),
        "webtransport" | "quic" => Ok(TransportChoice::WebTransport),
        other => Err(format!(
            "{other}: the transport is auto, websocket or webtransport"
        )),
    }
}

impl Connection {
    async fn connect(&self, reconnect: bool) -> anyhow::Result<Client> {
        let mut options = ClientOptions::new(&self.url, &self.scene);
        options.fallback_urls = self.fallback_url.clone();
        options.token = self.token.clone();
        options.reconnect = reconnect;
        options.transport = self.transport;
        if self.json_frames {
            options.encoding = Encoding::Json;
        }
        let client = Client::connect(options)
            .await
            .map_err(|e| anyhow::anyhow!("cannot connect to {}: {e}", self.url))?;
        let stats = client.stats();
        if let Some(transport) = stats.transport {
            match stats.webtransport_failure {
                Some(why) => eprintln!("connected over {transport} (WebTransport offered: {why})"),
                None => eprintln!("connected over {transport}"),
            }
        }
        Ok(client)
    }
}

fn main() -> anyhow::Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("warn")),
        )
        .with_writer(std::io::stderr)
        .init();
    let cli = Cli::parse();
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()?;
    match cli.command {
        Command::Watch(args) => runtime.block_on(watch::run(args)),
        Command::Render(args) => runtime.block_on(render::run(args)),
        Command::Drive(args) => runtime.block_on(drive::run(args)),
        Command::VmcRelay(args) => runtime.block_on(vmc_relay::run(args)),
        // winit wants the main thread; the client's tasks run on the runtime's workers.
        Command::View(args) => view::run(args, &runtime),
    }
}
