//! Command acknowledgement latency, with and without a data folder: the price of durable
//! acks (write, `sync_all`, rename, fsync of the folder before each answer).
//!
//! `cargo bench -p posecast --bench ack_latency` — an in-process server; 1 or 20 websocket
//! clients each sending `set_speed` commands one after another and timing each until its
//! `ack`. Prints p50 / p99 / max and acks per second for each mode (20 connections show the
//! group commit: acks that arrive together share one write). The data folder is a temporary folder under `target/`, so the
//! figure is this disk's fsync cost.

use futures_util::{SinkExt, StreamExt};
use posecast_proto::command::Command;
use posecast_proto::msg::{AvatarId, ClientMsg, Encoding, PROTOCOL_VERSION, ServerMsg};
use posecast_server::auth::{AccessConfig, Role, Secret, TokenRule};
use posecast_server::config::Config;
use posecast_server::startup::Server;
use std::time::{Duration, Instant};
use tokio_tungstenite::tungstenite::Message;

const TOKEN: &str = "bench-control-token";

/// One connection sending `commands` commands one after another; the latency of each.
async fn connection(url: String, commands: usize) -> anyhow::Result<Vec<Duration>> {
    let (mut ws, _) = tokio_tungstenite::connect_async(url).await?;
    let hello = ClientMsg::Hello {
        version: PROTOCOL_VERSION,
        encoding: Encoding::Json,
        token: Some(TOKEN.into()),
        client: Some("ack-latency".into()),
    };
    ws.send(Message::Text(serde_json::to_string(&hello)?.into()))
        .await?;
    let mut latencies = Vec::with_capacity(commands);
    for id in 0..=commands as u64 {
        let command = ClientMsg::Command {
            id,
            idempotency_key: None,
            command: Command::SetSpeed {
                avatar: AvatarId("avatar".into()),
                speed: 1.0 + (id % 3) as f32 * 0.1,
            },
        };
        let sent = Instant::now();
        ws.send(Message::Text(serde_json::to_string(&command)?.into()))
            .await?;
        loop {
            let Some(msg) = ws.next().await else {
                anyhow::bail!("connection closed");
            };
            if let Message::Text(t) = msg? {
                match serde_json::from_str::<ServerMsg>(t.as_str())? {
                    ServerMsg::Ack { id: a, .. } if a == id => break,
                    ServerMsg::Error(e) => anyhow::bail!("{e:?}"),
                    _ => {}
                }
            }
        }
        // The first command warms up (first write creates the file).
        if id > 0 {
            latencies.push(sent.elapsed());
        }
    }
    ws.close(None).await.ok();
    Ok(latencies)
}

/// `connections` clients at once, each sending `commands` commands one after another. Returns
/// every latency (sorted), acks per second over the whole run, and the scene writes made.
async fn measure(
    data_dir: Option<std::path::PathBuf>,
    connections: usize,
    commands: usize,
) -> anyhow::Result<(Vec<Duration>, f64, u64)> {
    let mut access = AccessConfig::default();
    access.add(TokenRule::new("bench", Secret::new(TOKEN), Role::Control))?;
    let server = Server::start(Config {
        listen: "127.0.0.1:0".parse()?,
        access,
        data_dir,
        ..Config::default()
    })
    .await?;
    server.ready().await?;
    let began = Instant::now();
    let tasks: Vec<_> = (0..connections)
        .map(|_| tokio::spawn(connection(server.ws_url(), commands)))
        .collect();
    let mut latencies = Vec::with_capacity(connections * commands);
    for t in tasks {
        latencies.extend(t.await??);
    }
    let rate = latencies.len() as f64 / began.elapsed().as_secs_f64();
    let writes = server.state.store.batches_written();
    server.stop().await;
    latencies.sort();
    Ok((latencies, rate, writes))
}

fn report(name: &str, (l, rate, writes): &(Vec<Duration>, f64, u64)) {
    let at = |q: f64| l[((l.len() - 1) as f64 * q) as usize].as_secs_f64() * 1e3;
    println!(
        "{name:<40} p50 {:6.2} ms   p99 {:6.2} ms   max {:6.2} ms   {rate:7.0} acks/s   ({} acks, {writes} scene writes)",
        at(0.5),
        at(0.99),
        at(1.0),
        l.len()
    );
}

fn main() -> anyhow::Result<()> {
    // `cargo bench` passes `--bench`; under `cargo test --all-targets` one short pass checks
    // that the benchmark still runs.
    let commands = if std::env::args().any(|a| a == "--bench") {
        500
    } else {
        20
    };
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()?;
    let dir = |n: usize| {
        std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("target")
            .join(format!("ack-latency-{}-{n}", std::process::id()))
    };
    let durable1 = runtime.block_on(measure(Some(dir(1)), 1, commands))?;
    let durable20 = runtime.block_on(measure(Some(dir(20)), 20, commands / 4))?;
    std::fs::remove_dir_all(dir(1)).ok();
    std::fs::remove_dir_all(dir(20)).ok();
    let memory = runtime.block_on(measure(None, 1, commands))?;
    report("durable acks, 1 connection", &durable1);
    report("durable acks, 20 connections (grouped)", &durable20);
    report("in memory only (--no-persist), 1 conn", &memory);
    println!(
        "grouped: {:.1}x the acks/s of one connection",
        durable20.1 / durable1.1
    );
    Ok(())
}
