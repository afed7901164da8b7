//! `--cluster N`: N posecast servers joined through a `nats-server -js` child on a free
//! loopback port (`apt-get install nats-server`), `--clients` websocket clients on *each*, all
//! measured over the same window. The first server owns the scene (it makes `default` on a new
//! NATS; `--avatars` fills it); the others relay it. Per server: what its clients got (the
//! single-server report), its process's CPU, and the bytes it published to and received from
//! NATS per second — all for the one scene of the cluster.

use crate::client::{self, ClientStats, Phase};
use crate::server::{self, Spawned};
use crate::{Args, authority, report};
use anyhow::{Context, Result, bail};
use std::process::{Child, Command, Stdio};
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

/// The `nats-server` child and its store folder (removed once the child is gone).
struct Nats {
    child: Child,
    port: u16,
    store: std::path::PathBuf,
}

impl Nats {
    async fn start() -> Result<Self> {
        let port = std::net::TcpListener::bind("127.0.0.1:0")?
            .local_addr()?
            .port();
        let store =
            std::env::temp_dir().join(format!("loadgen-nats-{}-{port}", std::process::id()));
        let child = Command::new("nats-server")
            .args(["-js", "-a", "127.0.0.1", "-p", &port.to_string(), "-sd"])
            .arg(&store)
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .context("cannot start nats-server (apt-get install nats-server)")?;
        let nats = Self { child, port, store };
        let deadline = Instant::now() + Duration::from_secs(20);
        while tokio::net::TcpStream::connect(("127.0.0.1", port))
            .await
            .is_err()
        {
            if Instant::now() > deadline {
                bail!("nats-server did not listen on port {port} within 20 s");
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        Ok(nats)
    }

    fn url(&self) -> String {
        format!("nats://127.0.0.1:{}", self.port)
    }
}

impl Drop for Nats {
    fn drop(&mut self) {
        self.child.kill().ok();
        self.child.wait().ok();
        if let Err(e) = std::fs::remove_dir_all(&self.store) {
            eprintln!("could not remove {}: {e}", self.store.display());
        }
    }
}

/// Waits (at most 30 s) until the server at `http` is ready and lists `scene` with an owner;
/// returns the owner.
async fn owner_seen_by(http: &str, scene: &str) -> Result<String> {
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        if let Ok((200, body)) = server::http_get(http, "/api/scenes").await
            && let Ok(list) = serde_json::from_str::<serde_json::Value>(&body)
            && let Some(owner) = list
                .as_array()
                .or_else(|| list["result"].as_array())
                .and_then(|scenes| scenes.iter().find(|s| s["scene"] == scene))
                .and_then(|s| s["owner"].as_str())
        {
            return Ok(owner.to_owned());
        }
        if Instant::now() > deadline {
            bail!("{http} did not list scene {scene} with an owner within 30 s");
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

/// Starts the cluster, measures, stops it.
pub async fn run(args: &Args, nodes: usize, fd_limit: u64) -> Result<()> {
    let nats = Nats::start().await?;
    let token = args
        .control_token
        .clone()
        .unwrap_or_else(|| format!("loadgen-{:032x}", rand::random::<u128>()));
    let mut servers = Vec::with_capacity(nodes);
    for i in 0..nodes {
        let more = vec![
            "--nats".into(),
            nats.url(),
            "--node".into(),
            format!("n{i}"),
        ];
        let spawned = Spawned::start_with(
            args.server_bin.as_deref(),
            args.tick_rate,
            fd_limit,
            &token,
            more,
        )
        .await;
        match spawned {
            Ok(s) => servers.push(s),
            Err(e) => {
                for s in servers {
                    s.stop().await;
                }
                return Err(e);
            }
        }
    }
    let result = measure(args, &servers, &token).await;
    for s in servers {
        s.stop().await;
    }
    drop(nats);
    result
}

async fn measure(args: &Args, servers: &[Spawned], token: &str) -> Result<()> {
    let scene = args.scene.clone().unwrap_or_else(|| "default".into());
    let urls: Vec<String> = servers.iter().map(Spawned::ws_url).collect();
    let https = urls
        .iter()
        .map(|u| authority(u))
        .collect::<Result<Vec<_>>>()?;
    // The first server makes `default` on a new NATS once it is ready; it owns what it
    // creates.
    owner_seen_by(&https[0], "default").await?;
    server::create_scene(&urls[0], token, &scene, args.avatars, &args.clips).await?;
    let mut owners = Vec::new();
    for http in &https {
        owners.push(owner_seen_by(http, &scene).await?);
    }
    eprintln!("scene {scene} owned by {owners:?} as each server sees it");

    let shared: Vec<Arc<client::Shared>> = servers
        .iter()
        .map(|_| {
            Arc::new(client::Shared::new(args.connect_parallel, false).with_version(args.protocol))
        })
        .collect();
    let connect_began = Instant::now();
    let mut tasks = Vec::new();
    for (url, shared) in urls.iter().zip(&shared) {
        let node_tasks: Vec<_> = (0..args.clients)
            .map(|i| {
                let shared = shared.clone();
                let endpoint = client::Endpoint::WebSocket(url.clone());
                let scene = scene.clone();
                let rate = args.rate;
                tokio::spawn(async move { client::run(i, &endpoint, &scene, rate, &shared).await })
            })
            .collect();
        tasks.push(node_tasks);
    }
    let total = args.clients * servers.len();
    let deadline = Instant::now() + Duration::from_secs(30 + total as u64 / 20);
    loop {
        let done: usize = shared
            .iter()
            .map(|s| s.ready.load(Ordering::Relaxed) + s.failed.load(Ordering::Relaxed))
            .sum();
        if done >= total || Instant::now() > deadline {
            break;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let connect_s = connect_began.elapsed().as_secs_f64();
    eprintln!(
        "{} of {total} clients subscribed in {connect_s:.1} s; warming up {:.1} s",
        shared
            .iter()
            .map(|s| s.ready.load(Ordering::Relaxed))
            .sum::<usize>(),
        args.warmup
    );
    tokio::time::sleep(Duration::from_secs_f64(args.warmup)).await;

    let mut before = Vec::new();
    for http in &https {
        before.push(server::scrape_metrics(http).await.ok());
    }
    let cpu_before = servers
        .iter()
        .map(|s| server::cpu_ticks(s.pid()))
        .collect::<Result<Vec<_>>>()?;
    let self_before = server::cpu_ticks_self()?;
    let began = Instant::now();
    for s in &shared {
        s.set_phase(Phase::Measure);
    }
    tokio::time::sleep(Duration::from_secs_f64(args.seconds)).await;
    for s in &shared {
        s.set_phase(Phase::Done);
    }
    let wall = began.elapsed().as_secs_f64();
    let cpu_after = servers
        .iter()
        .map(|s| server::cpu_ticks(s.pid()))
        .collect::<Result<Vec<_>>>()?;
    let self_after = server::cpu_ticks_self()?;
    let mut after = Vec::new();
    for http in &https {
        after.push(server::scrape_metrics(http).await.ok());
    }

    let hz = server::clock_ticks_per_second();
    let cpu = |a: u64, b: u64| 100.0 * b.saturating_sub(a) as f64 / hz / wall;
    let mut delivered = 0.0;
    let mut cpus = Vec::new();
    for (i, node_tasks) in tasks.into_iter().enumerate() {
        let mut stats: Vec<ClientStats> = Vec::with_capacity(node_tasks.len());
        for t in node_tasks {
            match tokio::time::timeout(Duration::from_secs(10), t).await {
                Ok(Ok(s)) => stats.push(s),
                Ok(Err(e)) => bail!("a client task panicked: {e}"),
                Err(_) => stats.push(ClientStats::failed("did not stop within 10 s")),
            }
        }
        delivered += stats.iter().map(|s| s.frames).sum::<u64>() as f64 / wall;
        let node_cpu = cpu(cpu_before[i], cpu_after[i]);
        cpus.push(node_cpu);
        let metrics = before[i].as_ref().zip(after[i].as_ref());
        println!(
            "\n— server n{i} ({}) —",
            if owners[i] == format!("n{i}") {
                "owner"
            } else {
                "relay"
            }
        );
        // The loadgen's own CPU is reported once, for the whole run, below.
        report::Summary::new(
            args,
            &scene,
            wall,
            connect_s,
            &stats,
            Some(node_cpu),
            None,
            metrics,
        )
        .print();
        if let Some((b, a)) = metrics {
            let d = |k: &str| a.get(k).copied().unwrap_or(0.0) - b.get(k).copied().unwrap_or(0.0);
            println!(
                "NATS              published {:.1} kB/s ({:.0} messages/s) · received {:.1} kB/s ({:.0} messages/s)",
                d("posecast_nats_published_bytes_total") / wall / 1e3,
                d("posecast_nats_published_total") / wall,
                d("posecast_nats_received_bytes_total") / wall / 1e3,
                d("posecast_nats_received_total") / wall,
            );
        }
    }
    println!(
        "\ncluster: {} servers × {} clients, {:.0} frames/s delivered of {:.0} expected; server CPU {} (of one core each); loadgen {:.0} %",
        servers.len(),
        args.clients,
        delivered,
        f64::from(args.tick_rate) * total as f64,
        cpus.iter()
            .map(|c| format!("{c:.0} %"))
            .collect::<Vec<_>>()
            .join(" · "),
        cpu(self_before, self_after)
    );
    Ok(())
}
