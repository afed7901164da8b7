//! Scale-out through NATS: the latency a relaying server adds, and the bytes a scene costs.
//!
//! `cargo bench -p posecast --bench cluster_latency` — a `nats-server -js` child process on a
//! free loopback port and two in-process servers joined through it: A owns a scene of 10
//! built-in avatars walking at 60 Hz, B relays it. 20 binary subscribers on A and 20 on B for
//! 10 s; each frame's latency is its arrival time minus the tick time in its header (the
//! owner's clock, the same machine's). Prints p50 / p99 / max for clients on A and on B, and the
//! NATS bytes per second A published and B received for the scene.
//!
//! Then live driving: a driver on A (the owner), then one on B (its poses go to A through
//! NATS), each sends 120 poses a second for 2.5 s to `walker0`, each a distinct `l_elbow`
//! angle, while 20 library clients on A record when each pose first shows; latency = seen −
//! sent (one machine, one clock).

#[path = "common/drive.rs"]
mod drive;

use futures_util::{SinkExt, StreamExt};
use posecast_proto::frame::read_header;
use posecast_proto::msg::AvatarId;
use posecast_proto::msg::{ClientMsg, Encoding, PROTOCOL_VERSION, ServerMsg};
use posecast_server::auth::{AccessConfig, Role, Secret, TokenRule};
use posecast_server::config::Config;
use posecast_server::startup::Server;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};
use tokio_tungstenite::tungstenite::Message;

const TOKEN: &str = "bench-control-token";
const CLIENTS: usize = 20;
const AVATARS: usize = 10;
/// Seconds measured under `cargo bench` (which passes `--bench`); under
/// `cargo test --all-targets` one short pass checks that the benchmark still runs.
fn measured_seconds() -> u64 {
    if std::env::args().any(|a| a == "--bench") {
        10
    } else {
        1
    }
}

type Ws =
    tokio_tungstenite::WebSocketStream<tokio_tungstenite::MaybeTlsStream<tokio::net::TcpStream>>;

/// The child and its store folder (removed when dropped, after the child is gone).
struct Nats {
    child: Child,
    _store: tempfile::TempDir,
}

impl Drop for Nats {
    fn drop(&mut self) {
        self.child.kill().ok();
        self.child.wait().ok();
    }
}

fn nats() -> anyhow::Result<(Nats, u16)> {
    let store = tempfile::tempdir()?;
    let port = std::net::TcpListener::bind("127.0.0.1:0")?
        .local_addr()?
        .port();
    let child = Command::new("nats-server")
        .args(["-js", "-a", "127.0.0.1", "-p", &port.to_string(), "-sd"])
        .arg(store.path())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .map_err(|e| {
            anyhow::anyhow!("cannot start nats-server (apt-get install nats-server): {e}")
        })?;
    let nats = Nats {
        child,
        _store: store,
    };
    let deadline = Instant::now() + Duration::from_secs(20);
    while std::net::TcpStream::connect(("127.0.0.1", port)).is_err() {
        anyhow::ensure!(Instant::now() < deadline, "nats-server did not listen");
        std::thread::sleep(Duration::from_millis(20));
    }
    Ok((nats, port))
}

async fn server(port: u16, node: &str) -> anyhow::Result<Server> {
    let mut access = AccessConfig::default();
    access.add(TokenRule::new("bench", Secret::new(TOKEN), Role::Control))?;
    let server = Server::start(Config {
        listen: "127.0.0.1:0".parse()?,
        access,
        nats: vec![format!("nats://127.0.0.1:{port}")],
        node: Some(node.into()),
        ..Config::default()
    })
    .await?;
    server.ready().await?;
    Ok(server)
}

async fn connect(server: &Server) -> anyhow::Result<Ws> {
    let (mut ws, _) = tokio_tungstenite::connect_async(server.ws_url()).await?;
    let hello = ClientMsg::Hello {
        version: PROTOCOL_VERSION,
        encoding: Encoding::Binary,
        token: Some(TOKEN.into()),
        client: Some("cluster-latency".into()),
    };
    ws.send(Message::Text(serde_json::to_string(&hello)?.into()))
        .await?;
    Ok(ws)
}

/// Sends a command and waits for its ack.
async fn command(ws: &mut Ws, id: u64, json: &str) -> anyhow::Result<serde_json::Value> {
    let msg = format!(r#"{{"type":"command","id":{id},"command":{json}}}"#);
    ws.send(Message::Text(msg.into())).await?;
    loop {
        let Some(m) = ws.next().await else {
            anyhow::bail!("closed")
        };
        if let Message::Text(t) = m? {
            match serde_json::from_str::<ServerMsg>(t.as_str())? {
                ServerMsg::Ack { id: a, result } if a == id => return Ok(result.to_value()),
                ServerMsg::Error(e) => anyhow::bail!("{json}: {e:?}"),
                _ => {}
            }
        }
    }
}

fn now_us() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_micros() as u64)
}

/// One subscriber for [`measured_seconds`]: the latency of every frame, µs.
async fn subscriber(mut ws: Ws) -> anyhow::Result<Vec<u64>> {
    ws.send(Message::Text(
        r#"{"type":"subscribe","scene":"bench"}"#.into(),
    ))
    .await?;
    let end = Instant::now() + Duration::from_secs(measured_seconds());
    let mut latencies = Vec::new();
    while let Ok(Some(m)) = tokio::time::timeout_at(end.into(), ws.next()).await {
        if let Message::Binary(b) = m? {
            let (header, _) = read_header(&b)?;
            latencies.push(now_us().saturating_sub(header.server_time_us));
        }
    }
    Ok(latencies)
}

fn report(name: &str, what: &str, mut l: Vec<u64>) {
    l.sort_unstable();
    let at = |q: f64| l[((l.len() - 1) as f64 * q) as usize] as f64 / 1e3;
    println!(
        "{name}: {} {what}, p50 {:.2} ms, p99 {:.2} ms, max {:.2} ms",
        l.len(),
        at(0.5),
        at(0.99),
        at(1.0)
    );
}

#[tokio::main(flavor = "multi_thread", worker_threads = 2)]
async fn main() -> anyhow::Result<()> {
    let (_nats, port) = nats()?;
    let a = server(port, "a").await?;
    let b = server(port, "b").await?;
    let mut control = connect(&a).await?;
    // Only the bench's scene goes through NATS (the first server made `default`).
    command(
        &mut control,
        100,
        r#"{"op":"delete_scene","scene":"default"}"#,
    )
    .await?;
    command(&mut control, 1, r#"{"op":"create_scene","scene":"bench"}"#).await?;
    for i in 0..AVATARS {
        let add = format!(
            r#"{{"op":"add_avatar","scene":"bench","asset":"avatar","avatar":"walker{i}","clip":"walk","position":[{i},0,0]}}"#
        );
        command(&mut control, 2 + i as u64, &add).await?;
    }
    // B relays the scene once its lease loop has seen it.
    let mut on_b = connect(&b).await?;
    let deadline = Instant::now() + Duration::from_secs(20);
    loop {
        let listed = command(&mut on_b, 1, r#"{"op":"list_scenes"}"#).await?;
        if listed.to_string().contains(r#""owner":"a""#) {
            break;
        }
        anyhow::ensure!(
            Instant::now() < deadline,
            "B never listed the scene: {listed}"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    tokio::time::sleep(Duration::from_secs(1)).await;
    let (published, received) = (
        a.state.metrics.cluster.bytes().0,
        b.state.metrics.cluster.bytes().1,
    );
    let started = Instant::now();
    let mut tasks = Vec::new();
    for server in [&a, &b] {
        for _ in 0..CLIENTS {
            tasks.push(tokio::spawn(subscriber(connect(server).await?)));
        }
    }
    let mut on_a_lat = Vec::new();
    let mut on_b_lat = Vec::new();
    for (i, t) in tasks.into_iter().enumerate() {
        let l = t.await??;
        if i < CLIENTS {
            on_a_lat.extend(l);
        } else {
            on_b_lat.extend(l);
        }
    }
    let seconds = started.elapsed().as_secs_f64();
    let published = a.state.metrics.cluster.bytes().0 - published;
    let received = b.state.metrics.cluster.bytes().1 - received;
    println!(
        "{AVATARS} avatars at 60 Hz, {CLIENTS} binary subscribers on the owner A and {CLIENTS} on the relay B, {} s",
        measured_seconds()
    );
    report("clients on A (owner)", "frames", on_a_lat);
    report("clients on B (relay)", "frames", on_b_lat);
    println!(
        "NATS: A published {:.1} kB/s, B received {:.1} kB/s for the scene",
        published as f64 / seconds / 1e3,
        received as f64 / seconds / 1e3
    );
    for (name, server) in [("A (owner)", &a), ("B (relay)", &b)] {
        let mut l = drive_latency(&a, server).await?;
        anyhow::ensure!(!l.is_empty(), "no pose of the driver on {name} was seen");
        l.sort_unstable();
        report(
            &format!("driver on {name} → clients on A"),
            "poses seen",
            l.iter().map(|d| d.as_micros() as u64).collect(),
        );
    }
    b.stop().await;
    a.stop().await;
    Ok(())
}

/// Pose in → pose out: a driver on `via` drives `walker0` (ticked by `owner`); 20 clients on
/// the owner record when each pose first shows.
async fn drive_latency(owner: &Server, via: &Server) -> anyhow::Result<Vec<Duration>> {
    drive::pose_latencies(drive::Run {
        watch: owner,
        scene: "bench",
        drive_url: via.ws_url(),
        token: TOKEN,
        avatar: AvatarId("walker0".into()),
        clients: CLIENTS,
        poses: 2 * 120 * measured_seconds() as usize / 4 + 10,
    })
    .await
}
