//! `loadgen`: fan-out load test for a posecast server, in its own process, on loopback.
//!
//! Opens N websocket clients (binary encoding: `hello`, then `subscribe`), lets them settle,
//! then measures for a bounded time: pose frames delivered per second (total and per client),
//! tick→receive latency (receive time − the header's `server_time_us`; both clocks are this
//! machine's), frames missed (gaps in `seq` per client), connection failures, and the server
//! process's CPU from `/proc/<pid>/stat`.
//!
//! ```text
//! loadgen --url ws://127.0.0.1:8080/ws --clients 100 --seconds 10 [--scene default] [--server-pid PID]
//! loadgen --spawn-server --avatars 10 --clients 2000 --seconds 10
//! ```
//!
//! `--link SPEC` (repeatable) or `--link-suite` put an emulated link between the clients and
//! the server (`posecast-linkemu`: delay, jitter, loss, a rate shared by every client — e.g.
//! `--link delay=25ms,jitter=10ms,loss=1%,rate=2mbit`) and print, per condition, what viewers
//! got: frames/s per client, frame age p50/p99, worst freeze, interpolated share of displayed
//! poses (see `link.rs`). Each condition runs once per transport (`--transport both`, the
//! default): the websocket through a TCP proxy, WebTransport through a UDP proxy that impairs
//! alike (a spawned server gets a QUIC endpoint):
//!
//! ```text
//! loadgen --spawn-server --avatars 10 --clients 50 --seconds 10 --link-suite
//! ```
//!
//! `--cluster N` (with `--spawn-server`) runs N servers joined through a `nats-server -js`
//! child, `--clients` on each, and reports every server (see `cluster.rs`):
//!
//! ```text
//! loadgen --spawn-server --cluster 3 --avatars 10 --clients 500 --seconds 10
//! ```
//!
//! `--spawn-server` runs the `posecast` binary built beside this one on a free loopback port,
//! fills its `default` scene up to M built-in avatars (it starts with one playing `idle`; the
//! others play `walk`, `wave`, `idle` in turn) with websocket commands, and stops the server at
//! the end. Every client costs one file descriptor here and one in the server:
//! raise the soft limit first (`ulimit -n 20000`, at most `ulimit -Hn`); the spawned server gets
//! the same limit.

mod client;
mod cluster;
mod link;
mod reference;
mod report;
mod server;

use anyhow::{Context, Result, bail};
use clap::Parser;
use client::{ClientStats, Phase};
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

/// Fan-out load generator for posecast (loopback only, bounded run).
#[derive(Debug, Parser)]
#[command(version)]
pub struct Args {
    /// Websocket URL of a running server.
    #[arg(
        long,
        required_unless_present_any = ["spawn_server", "serve_reference"],
        conflicts_with = "spawn_server"
    )]
    url: Option<String>,
    /// Start `posecast` as a child process on a free loopback port and create the scene.
    #[arg(long)]
    spawn_server: bool,
    /// The server binary for --spawn-server (default: `posecast` beside this executable).
    #[arg(long)]
    server_bin: Option<PathBuf>,
    /// With --url: the server's process id, to measure its CPU.
    #[arg(long)]
    server_pid: Option<u32>,
    /// The control token for creating the scene (a spawned server is given a fresh one).
    #[arg(long, env = "POSECAST_CONTROL_TOKEN", hide_env_values = true)]
    control_token: Option<String>,
    /// With --spawn-server: avatars in the scene.
    #[arg(long, default_value_t = 10)]
    avatars: usize,
    /// With --spawn-server: clips the avatars play, in turn.
    #[arg(long, value_delimiter = ',', default_value = "walk,wave,idle")]
    clips: Vec<String>,
    /// The server's tick rate (passed to a spawned server; the expected frame rate).
    #[arg(long, default_value_t = 60.0)]
    tick_rate: f32,
    /// Websocket clients.
    #[arg(long, default_value_t = 100)]
    clients: usize,
    /// Length of the measurement, seconds.
    #[arg(long, default_value_t = 10.0)]
    seconds: f64,
    /// Time after every client subscribed and before measuring, seconds.
    #[arg(long, default_value_t = 2.0)]
    warmup: f64,
    /// The scene to subscribe to (with --spawn-server: created unless it is `default`).
    #[arg(long)]
    scene: Option<String>,
    /// Connections being opened at once.
    #[arg(long, default_value_t = 64)]
    connect_parallel: usize,
    /// Frames per second each client subscribes at (posecast sends every
    /// `round(tick_rate / rate)`-th tick); absent: every tick. The reference server ignores it.
    #[arg(long)]
    rate: Option<f32>,
    /// With --spawn-server: which server to measure — posecast, the plain broadcast reference
    /// server (`reference`), or both one after the other with the ratios (`both`).
    #[arg(long, value_enum, default_value_t = Which::Posecast)]
    server: Which,
    /// Run as the reference server on this address (what `--server reference` spawns).
    #[arg(long, hide = true)]
    serve_reference: Option<std::net::SocketAddr>,
    /// Reach the server through an emulated link, e.g. `delay=25ms,jitter=10ms,loss=1%,
    /// rate=2mbit` (also `queue=32kb`, `window=16kb`, `seed=N`; `none`): one run per `--link`,
    /// then a table of what viewers got.
    #[arg(long, conflicts_with = "serve_reference")]
    link: Vec<String>,
    /// The issue's conditions, one run each: none, 25 ms, ± 10 ms jitter, 1 % and 5 % loss,
    /// 2 Mbit/s shared by every client.
    #[arg(long, conflicts_with = "link")]
    link_suite: bool,
    /// The protocol version the clients say hello with: 2 to 7 get wire v2 frames (4 with
    /// morph weights, 5 with precision per subscription, 6 with near-axis steps, 7 with packed
    /// deltas; 3 is the default), 1 v1 frames.
    /// The reference server sends the same wire. Over WebTransport versions 1 to 7 get wire
    /// v1 datagrams, 8 wire v2 datagrams (deltas naming acknowledged frames), 9 the same with
    /// deltas predicted over the ticks between; on a websocket 8 and 9 are 7.
    #[arg(long, default_value_t = 3, value_parser = clap::value_parser!(u32).range(1..=9))]
    protocol: u32,
    /// Load the machine as a busy host would be: this many busy-loop processes run beside the
    /// servers for the whole run (e.g. one per core), so both servers are measured under the
    /// same outside CPU contention (at most 64).
    #[arg(long, default_value_t = 0, value_parser = clap::value_parser!(u64).range(0..=64))]
    busy: u64,
    /// With --link/--link-suite: the transport the clients use — the websocket,
    /// WebTransport (a spawned server gets a QUIC endpoint; `--url` needs a server that
    /// offers one at `/api/quic`), or both, each condition run once per transport (the
    /// default).
    #[arg(long, value_enum, default_value_t = Transports::Both)]
    transport: Transports,
    /// With --spawn-server and WebTransport: the spawned server's `--quic-congestion`
    /// (`bbr`, its default; `cubic`; `new-reno`).
    #[arg(long)]
    quic_congestion: Option<String>,
    /// With --spawn-server: this many servers joined through a spawned `nats-server -js`,
    /// `--clients` on each; the first owns the scene, the others relay it.
    #[arg(long, requires = "spawn_server", conflicts_with_all = ["link", "link_suite", "server"])]
    cluster: Option<usize>,
}

/// The server(s) a `--spawn-server` run measures.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum Which {
    Posecast,
    Reference,
    Both,
}

/// The transports of a `--link` run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum Transports {
    #[value(name = "websocket")]
    WebSocket,
    #[value(name = "webtransport")]
    WebTransport,
    Both,
}

/// Microseconds since the Unix epoch, the clock of the frames' `server_time_us`.
fn unix_micros() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_micros() as u64)
}

/// `host:port` of a `ws://host:port/path` URL.
fn authority(url: &str) -> Result<String> {
    let rest = url
        .strip_prefix("ws://")
        .with_context(|| format!("{url}: only ws:// URLs are supported (loopback)"))?;
    Ok(rest.split('/').next().unwrap_or(rest).to_owned())
}

fn main() -> Result<()> {
    let args = Args::parse();
    if let Some(listen) = args.serve_reference {
        return reference::serve(
            listen,
            args.avatars,
            &args.clips,
            args.tick_rate,
            args.protocol,
        );
    }
    let positive = |v: f64| v.is_finite() && v > 0.0;
    if args.clients == 0
        || !positive(args.seconds)
        || !(positive(args.warmup) || args.warmup == 0.0)
    {
        bail!("--clients must be positive, --seconds positive, --warmup non-negative");
    }
    if args.cluster == Some(0) {
        bail!("--cluster needs at least one server");
    }
    let needed = (args.clients * args.cluster.unwrap_or(1)) as u64 + 64;
    let limit = server::open_files_limit()?;
    if limit < needed {
        bail!(
            "{} clients need about {needed} file descriptors but the limit is {limit}: \
             run `ulimit -n {}` first (at most `ulimit -Hn`)",
            args.clients,
            needed.max(20_000)
        );
    }
    // The clients' reads are the heavy part; the server is a separate process.
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()?;
    runtime.block_on(run(args, limit))
}

async fn run(args: Args, fd_limit: u64) -> Result<()> {
    let _busy = server::Busy::start(args.busy)?;
    if args.busy > 0 {
        eprintln!("{} busy-loop processes load the machine", args.busy);
    }
    if args.link_suite || !args.link.is_empty() {
        return run_links(&args, fd_limit).await;
    }
    if let Some(nodes) = args.cluster {
        return cluster::run(&args, nodes, fd_limit).await;
    }
    if !args.spawn_server {
        let url = args.url.clone().context("--url or --spawn-server")?;
        let scene = args.scene.clone().unwrap_or_else(|| "default".into());
        measure(&args, &url, &scene, args.server_pid).await?.print();
        return Ok(());
    }
    let reference = match args.server {
        Which::Posecast => None,
        Which::Reference | Which::Both => {
            eprintln!("— the reference server (plain broadcast) —");
            let child = server::Spawned::start_reference(
                fd_limit,
                args.avatars,
                &args.clips,
                args.tick_rate,
                args.protocol,
            )
            .await?;
            let summary = measure(&args, &child.ws_url(), "default", Some(child.pid())).await;
            child.stop().await;
            let summary = summary?;
            summary.print();
            Some(summary)
        }
    };
    if args.server == Which::Reference {
        return Ok(());
    }
    eprintln!("— posecast —");
    let posecast = spawn_and_measure(&args, fd_limit).await?;
    posecast.print();
    if let Some(reference) = reference {
        report::compare(&posecast, &reference);
    }
    Ok(())
}

/// `--link`/`--link-suite`: one measurement per link condition and transport, through a
/// proxy in this process (TCP for the websocket, UDP for WebTransport; both impair alike),
/// each against a server of its own when spawned (a server remembers a path's round trips
/// for 10–20 s: a condition measured right after another would inherit its base), or the one
/// at `--url`; then the table.
async fn run_links(args: &Args, fd_limit: u64) -> Result<()> {
    let specs: Vec<String> = if args.link_suite {
        link::SUITE.iter().map(|s| (*s).to_owned()).collect()
    } else {
        args.link.clone()
    };
    let configs = specs
        .iter()
        .map(|s| {
            s.parse::<posecast_linkemu::LinkConfig>()
                .with_context(|| format!("--link {s}"))
        })
        .collect::<Result<Vec<_>>>()?;
    let token = args
        .control_token
        .clone()
        .unwrap_or_else(|| format!("loadgen-{:032x}", rand::random::<u128>()));
    let scene = args.scene.clone().unwrap_or_else(|| "default".into());
    let transports = [Transports::WebSocket, Transports::WebTransport]
        .into_iter()
        .filter(|t| args.transport == Transports::Both || args.transport == *t);
    let mut rows = Vec::new();
    for (spec, config) in specs.iter().zip(configs) {
        for transport in transports.clone() {
            eprintln!("— link {config}, {transport:?} —");
            let child = if args.spawn_server {
                let mut more = Vec::new();
                if transport == Transports::WebTransport {
                    more.extend(["--quic-listen".into(), "127.0.0.1:0".into()]);
                    if let Some(c) = &args.quic_congestion {
                        more.extend(["--quic-congestion".into(), c.clone()]);
                    }
                }
                let child = server::Spawned::start_with(
                    args.server_bin.as_deref(),
                    args.tick_rate,
                    fd_limit,
                    &token,
                    more,
                )
                .await?;
                server::create_scene(&child.ws_url(), &token, &scene, args.avatars, &args.clips)
                    .await?;
                Some(child)
            } else {
                None
            };
            let url = match &child {
                Some(c) => c.ws_url(),
                None => args.url.clone().context("--url or --spawn-server")?,
            };
            let row = link_row(args, spec, &config, transport, &url, &scene).await;
            if let Some(child) = child {
                child.stop().await;
            }
            rows.push(row?);
        }
    }
    link::print(&rows);
    Ok(())
}

/// One row of a `--link` run: `transport`'s clients through `config` to the server at `url`.
async fn link_row(
    args: &Args,
    spec: &str,
    config: &posecast_linkemu::LinkConfig,
    transport: Transports,
    url: &str,
    scene: &str,
) -> Result<link::Row> {
    let upstream: std::net::SocketAddr = authority(url)?
        .parse()
        .with_context(|| format!("{url}: --link needs an IP address and port"))?;
    // On a rate-limited link every client's join (its descriptions) crosses it first.
    let mut run_args = Args::parse_from(["loadgen", "--url", url]);
    run_args.clients = args.clients;
    run_args.seconds = args.seconds;
    run_args.warmup = if config.rate_bps.is_some() {
        args.warmup.max(25.0)
    } else {
        args.warmup
    };
    run_args.connect_parallel = args.connect_parallel;
    run_args.rate = args.rate;
    run_args.protocol = args.protocol;
    if transport == Transports::WebSocket {
        let proxy =
            posecast_linkemu::Proxy::start(upstream, posecast_linkemu::Link::new(config.clone()))
                .await?;
        let through = client::Endpoint::WebSocket(format!("ws://{}/ws", proxy.addr()));
        let (stats, wall) = measure_stats(&run_args, &through, scene, true).await?;
        let row = link::row(spec, through.transport(), &stats, wall, args.tick_rate);
        eprintln!("{row:?}");
        return Ok(row);
    }
    let offer = posecast_client::net::transport::discover(url, Duration::from_secs(10))
        .await
        .map_err(|e| anyhow::anyhow!("{e}"))?
        .with_context(|| format!("{url} offers no WebTransport endpoint (/api/quic)"))?;
    let quic_port = offer
        .url
        .rsplit(':')
        .next()
        .and_then(|p| p.trim_end_matches('/').parse::<u16>().ok())
        .with_context(|| format!("no port in {}", offer.url))?;
    let proxy = posecast_linkemu::UdpProxy::start(
        std::net::SocketAddr::new(upstream.ip(), quic_port),
        config.clone(),
    )
    .await?;
    let through = client::Endpoint::WebTransport(posecast_client::net::transport::QuicOffer {
        url: format!("https://{}/", proxy.addr),
        cert_sha256: offer.cert_sha256,
    });
    let (stats, wall) = measure_stats(&run_args, &through, scene, true).await?;
    let row = link::row(spec, through.transport(), &stats, wall, args.tick_rate);
    eprintln!("{row:?}; datagrams down {:?}", proxy.down());
    if let Ok(m) = server::scrape_metrics(&authority(url)?).await {
        let mut lines: Vec<String> = m
            .iter()
            .filter(|(k, v)| {
                **v != 0.0
                    && (k.starts_with("posecast_quic_frames")
                        || k.starts_with("posecast_rate_changes")
                        || k.starts_with("posecast_rate_cuts"))
            })
            .map(|(k, v)| format!("{k} {v}"))
            .collect();
        lines.sort();
        eprintln!("the server's counts: {}", lines.join(", "));
    }
    Ok(row)
}

/// Starts posecast, fills its scene, measures, stops it.
async fn spawn_and_measure(args: &Args, fd_limit: u64) -> Result<report::Summary> {
    let token = args
        .control_token
        .clone()
        .unwrap_or_else(|| format!("loadgen-{:032x}", rand::random::<u128>()));
    let child =
        server::Spawned::start(args.server_bin.as_deref(), args.tick_rate, fd_limit, &token)
            .await?;
    let url = child.ws_url();
    let scene = args.scene.clone().unwrap_or_else(|| "default".into());
    let result = match server::create_scene(&url, &token, &scene, args.avatars, &args.clips).await {
        Ok(()) => measure(args, &url, &scene, Some(child.pid())).await,
        Err(e) => Err(e),
    };
    child.stop().await;
    result
}

/// Connects the clients, warms up, records for `--seconds`: every client's stats and the
/// wall time measured. `record`: keep every frame's arrival.
async fn measure_stats(
    args: &Args,
    endpoint: &client::Endpoint,
    scene: &str,
    record: bool,
) -> Result<(Vec<ClientStats>, f64)> {
    let shared =
        Arc::new(client::Shared::new(args.connect_parallel, record).with_version(args.protocol));
    let tasks: Vec<_> = (0..args.clients)
        .map(|i| {
            let shared = shared.clone();
            let endpoint = endpoint.clone();
            let scene = scene.to_owned();
            let rate = args.rate;
            tokio::spawn(async move { client::run(i, &endpoint, &scene, rate, &shared).await })
        })
        .collect();
    let deadline = Instant::now() + Duration::from_secs(30 + args.clients as u64 / 20);
    loop {
        let ready = shared.ready.load(Ordering::Relaxed) + shared.failed.load(Ordering::Relaxed);
        if ready >= args.clients || Instant::now() > deadline {
            break;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    eprintln!(
        "{} of {} clients subscribed ({} failed); warming up {:.1} s",
        shared.ready.load(Ordering::Relaxed),
        args.clients,
        shared.failed.load(Ordering::Relaxed),
        args.warmup
    );
    tokio::time::sleep(Duration::from_secs_f64(args.warmup)).await;
    let began = Instant::now();
    shared.set_phase(Phase::Measure);
    tokio::time::sleep(Duration::from_secs_f64(args.seconds)).await;
    shared.set_phase(Phase::Done);
    let wall = began.elapsed().as_secs_f64();
    let mut stats = Vec::with_capacity(tasks.len());
    for t in tasks {
        match tokio::time::timeout(Duration::from_secs(10), t).await {
            Ok(Ok(s)) => stats.push(s),
            Ok(Err(e)) => bail!("a client task panicked: {e}"),
            Err(_) => stats.push(ClientStats::failed("did not stop within 10 s")),
        }
    }
    let mut failures: Vec<&str> = stats.iter().filter_map(|s| s.failure.as_deref()).collect();
    failures.dedup();
    for why in failures.iter().take(3) {
        eprintln!("a client failed: {why}");
    }
    Ok((stats, wall))
}

async fn measure(args: &Args, url: &str, scene: &str, pid: Option<u32>) -> Result<report::Summary> {
    let shared =
        Arc::new(client::Shared::new(args.connect_parallel, false).with_version(args.protocol));
    let connect_began = Instant::now();
    let endpoint = client::Endpoint::WebSocket(url.to_owned());
    let tasks: Vec<_> = (0..args.clients)
        .map(|i| {
            let shared = shared.clone();
            let endpoint = endpoint.clone();
            let scene = scene.to_owned();
            let rate = args.rate;
            tokio::spawn(async move { client::run(i, &endpoint, &scene, rate, &shared).await })
        })
        .collect();
    // Every client subscribed or failed, within a generous bound.
    let deadline = Instant::now() + Duration::from_secs(30 + args.clients as u64 / 20);
    loop {
        let ready = shared.ready.load(Ordering::Relaxed) + shared.failed.load(Ordering::Relaxed);
        if ready >= args.clients || Instant::now() > deadline {
            break;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let connect_time = connect_began.elapsed();
    eprintln!(
        "{} of {} clients subscribed in {:.1} s ({} failed); warming up {:.1} s",
        shared.ready.load(Ordering::Relaxed),
        args.clients,
        connect_time.as_secs_f64(),
        shared.failed.load(Ordering::Relaxed),
        args.warmup
    );
    tokio::time::sleep(Duration::from_secs_f64(args.warmup)).await;

    let http = authority(url)?;
    let metrics_before = server::scrape_metrics(&http).await.ok();
    let cpu_before = pid.map(server::cpu_ticks).transpose()?;
    let self_before = server::cpu_ticks_self()?;
    let began = Instant::now();
    shared.set_phase(Phase::Measure);
    tokio::time::sleep(Duration::from_secs_f64(args.seconds)).await;
    shared.set_phase(Phase::Done);
    let wall = began.elapsed().as_secs_f64();
    let cpu_after = pid.map(server::cpu_ticks).transpose()?;
    let self_after = server::cpu_ticks_self()?;
    let metrics_after = server::scrape_metrics(&http).await.ok();

    let mut stats: Vec<ClientStats> = Vec::with_capacity(tasks.len());
    for t in tasks {
        match tokio::time::timeout(Duration::from_secs(10), t).await {
            Ok(Ok(s)) => stats.push(s),
            Ok(Err(e)) => bail!("a client task panicked: {e}"),
            Err(_) => stats.push(ClientStats::failed("did not stop within 10 s")),
        }
    }
    let hz = server::clock_ticks_per_second();
    let cpu = |a: Option<u64>, b: Option<u64>| match (a, b) {
        (Some(a), Some(b)) => Some(100.0 * b.saturating_sub(a) as f64 / hz / wall),
        _ => None,
    };
    let summary = report::Summary::new(
        args,
        scene,
        wall,
        connect_time.as_secs_f64(),
        &stats,
        cpu(cpu_before, cpu_after),
        cpu(Some(self_before), Some(self_after)),
        metrics_before.as_ref().zip(metrics_after.as_ref()),
    );
    Ok(summary)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// loadgen speaks every protocol version the server accepts, and no other.
    #[test]
    fn every_supported_protocol_version_is_accepted() {
        let parse = |v: u32| {
            Args::try_parse_from([
                "loadgen",
                "--url",
                "ws://127.0.0.1:1/ws",
                "--protocol",
                &v.to_string(),
            ])
        };
        for v in posecast_proto::msg::SUPPORTED_VERSIONS {
            assert!(parse(v).is_ok(), "protocol {v}");
        }
        let newest = posecast_proto::msg::SUPPORTED_VERSIONS
            .iter()
            .max()
            .unwrap();
        assert!(parse(newest + 1).is_err());
        assert!(parse(0).is_err());
    }
}
