//! The idle footprint: resident memory of a started server nobody is connected to, and how long
//! after its start `/healthz` answers `ok` — posecast (the release binary, the built-in avatar,
//! no data folder) against a plain broadcast server of the same stack.
//!
//! `cargo bench -p posecast --bench footprint` — for memory each server is started [`RUNS`]
//! times, in turn, as its own process; for the start time [`STARTS`] more times each, in turn
//! again and stopped once `/healthz` said `ok` (a start takes a few milliseconds and this
//! machine is noisy: medians of many interleaved starts, the ratio of one run). The plain server is
//! this bench binary started again with [`PLAIN`] set: tokio and axum, `/healthz` answering
//! `ok`, a websocket route that forwards one `tokio::sync::broadcast` of 221-byte frames ticked
//! at 60 Hz — the fan-out yardstick's design (`loadgen --server reference`) with nothing else.
//! Resident memory is read from `/proc/<pid>/status` twice: [`SETTLED`] after `/healthz` first
//! said `ok`, and once posecast has given its start-up code back ([`IDLE`] after; the plain
//! server is read at the same times). Each is split into anonymous memory (what the process
//! allocated) and file pages (its code and read-only data, mapped from the binary).

use std::io::{Read, Write};
use std::net::{SocketAddr, TcpListener, TcpStream};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// Set to the address to serve on: this process is the plain server.
const PLAIN: &str = "POSECAST_FOOTPRINT_PLAIN";
/// Starts of each server whose memory is measured.
const RUNS: usize = 5;
/// Starts of each server whose start time alone is measured.
const STARTS: usize = 40;
/// Time from `/healthz`'s first `ok` to the first reading of resident memory.
const SETTLED: Duration = Duration::from_secs(2);
/// Time from `/healthz`'s first `ok` to the idle reading: past the 5 s after which posecast
/// gives its start-up code back (`src/main.rs`).
const IDLE: Duration = Duration::from_secs(8);
/// Bytes of one frame of the plain server (posecast's wire v2 frame of 10 avatars is 221 B).
const FRAME_BYTES: usize = 221;

fn main() -> anyhow::Result<()> {
    if let Ok(addr) = std::env::var(PLAIN) {
        return plain::serve(addr.parse()?);
    }
    if std::env::args().any(|a| a == "--list") {
        return Ok(());
    }
    let posecast = env!("CARGO_BIN_EXE_posecast");
    let me = std::env::current_exe()?;
    let ours_command = |addr: SocketAddr| {
        let mut c = Command::new(posecast);
        c.args(["--listen", &addr.to_string(), "--no-persist"]);
        c
    };
    let theirs_command = |addr: SocketAddr| {
        let mut c = Command::new(&me);
        c.env(PLAIN, addr.to_string());
        c
    };
    let mut ours = Vec::new();
    let mut theirs = Vec::new();
    for _ in 0..RUNS {
        ours.push(measure(ours_command, true)?);
        theirs.push(measure(theirs_command, true)?);
    }
    let (mut ours_ready, mut theirs_ready) = (Vec::new(), Vec::new());
    for _ in 0..STARTS {
        ours_ready.push(measure(ours_command, false)?.ready);
        theirs_ready.push(measure(theirs_command, false)?.ready);
    }
    let (ours, theirs) = (Summary::of(&ours), Summary::of(&theirs));
    println!("idle footprint, median of {RUNS} starts each (release build, no client connected):");
    for (when, o, t) in [
        ("2 s after ready", ours.settled, theirs.settled),
        ("8 s after ready (idle)", ours.idle, theirs.idle),
    ] {
        println!(
            "  resident {when}: posecast {:.1} MB (anonymous {:.1}, file {:.1}), plain server {:.1} MB (anonymous {:.1}, file {:.1}): {:.2}x",
            mb(o.rss),
            mb(o.anon),
            mb(o.file),
            mb(t.rss),
            mb(t.anon),
            mb(t.file),
            o.rss as f64 / t.rss as f64
        );
    }
    let (ours_ready, theirs_ready) = (Quartiles::of(ours_ready), Quartiles::of(theirs_ready));
    println!(
        "  /healthz ok after start, median (quartiles) of {STARTS} starts each: posecast {ours_ready}, plain server {theirs_ready}: {:.2}x",
        ours_ready.median / theirs_ready.median
    );
    Ok(())
}

/// Milliseconds: the median and the quartiles of a set of start times.
#[derive(Clone, Copy)]
struct Quartiles {
    low: f64,
    median: f64,
    high: f64,
}

impl Quartiles {
    fn of(mut times: Vec<Duration>) -> Self {
        times.sort_unstable();
        let at = |q: usize| times[(times.len() - 1) * q / 4].as_secs_f64() * 1e3;
        Self {
            low: at(1),
            median: at(2),
            high: at(3),
        }
    }
}

impl std::fmt::Display for Quartiles {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{:.2} ms ({:.2}–{:.2})",
            self.median, self.low, self.high
        )
    }
}

fn mb(bytes: u64) -> f64 {
    bytes as f64 / 1e6
}

/// Resident memory at one moment, bytes.
#[derive(Clone, Copy)]
struct Memory {
    rss: u64,
    anon: u64,
    file: u64,
}

impl Memory {
    fn of(pid: u32) -> anyhow::Result<Self> {
        let status = std::fs::read_to_string(format!("/proc/{pid}/status"))?;
        let field = |name: &str| -> anyhow::Result<u64> {
            let kb = status
                .lines()
                .find_map(|l| l.strip_prefix(name))
                .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<u64>().ok())
                .ok_or_else(|| anyhow::anyhow!("no {name} in /proc/<pid>/status"))?;
            Ok(kb * 1024)
        };
        Ok(Self {
            rss: field("VmRSS:")?,
            anon: field("RssAnon:")?,
            file: field("RssFile:")?,
        })
    }

    /// The median of each figure.
    fn median(all: impl Iterator<Item = Self> + Clone) -> Self {
        Self {
            rss: median(all.clone().map(|m| m.rss).collect()),
            anon: median(all.clone().map(|m| m.anon).collect()),
            file: median(all.map(|m| m.file).collect()),
        }
    }
}

fn median<T: Copy + Ord>(mut v: Vec<T>) -> T {
    v.sort_unstable();
    v[v.len() / 2]
}

/// One start: how long until `/healthz` said `ok`, and the memory after (if measured).
struct Sample {
    ready: Duration,
    memory: Option<(Memory, Memory)>,
}

/// Medians of each memory figure.
struct Summary {
    settled: Memory,
    idle: Memory,
}

impl Summary {
    fn of(samples: &[Sample]) -> Self {
        let memory = samples.iter().filter_map(|s| s.memory);
        Self {
            settled: Memory::median(memory.clone().map(|(settled, _)| settled)),
            idle: Memory::median(memory.map(|(_, idle)| idle)),
        }
    }
}

/// Kills the server when the measurement ends, however it ends.
struct Killed(Child);

impl Drop for Killed {
    fn drop(&mut self) {
        self.0.kill().ok();
        self.0.wait().ok();
    }
}

/// Starts a server, waits for `/healthz` to say `ok` and, with `memory`, reads its resident
/// memory [`SETTLED`] and [`IDLE`] after that; stops it.
fn measure(command: impl Fn(SocketAddr) -> Command, memory: bool) -> anyhow::Result<Sample> {
    let addr = TcpListener::bind("127.0.0.1:0")?.local_addr()?;
    let mut command = command(addr);
    command.stdout(Stdio::null()).stderr(Stdio::null());
    let start = Instant::now();
    let child = Killed(command.spawn()?);
    loop {
        if healthz_ok(addr) {
            break;
        }
        if start.elapsed() > Duration::from_secs(60) {
            anyhow::bail!("{addr}: /healthz not ok 60 s after the start");
        }
        std::thread::sleep(Duration::from_micros(200));
    }
    let ready = start.elapsed();
    if !memory {
        return Ok(Sample {
            ready,
            memory: None,
        });
    }
    let pid = child.0.id();
    std::thread::sleep(SETTLED);
    let settled = Memory::of(pid)?;
    std::thread::sleep(IDLE - SETTLED);
    let idle = Memory::of(pid)?;
    Ok(Sample {
        ready,
        memory: Some((settled, idle)),
    })
}

/// Whether `GET /healthz` at `addr` answers 200 with `ok`.
fn healthz_ok(addr: SocketAddr) -> bool {
    let Ok(mut tcp) = TcpStream::connect(addr) else {
        return false;
    };
    let ask = b"GET /healthz HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n";
    if tcp.write_all(ask).is_err() {
        return false;
    }
    let mut answer = String::new();
    tcp.read_to_string(&mut answer).ok();
    answer.starts_with("HTTP/1.1 200") && answer.ends_with("ok")
}

/// The plain server.
mod plain {
    use super::FRAME_BYTES;
    use axum::Router;
    use axum::body::Bytes;
    use axum::extract::State;
    use axum::extract::ws::{Message, WebSocket, WebSocketUpgrade};
    use axum::response::Response;
    use axum::routing::get;
    use std::net::SocketAddr;
    use std::time::Duration;
    use tokio::sync::broadcast;

    pub fn serve(addr: SocketAddr) -> anyhow::Result<()> {
        tokio::runtime::Builder::new_multi_thread()
            .enable_all()
            .build()?
            .block_on(async move {
                let (frames, _) = broadcast::channel::<Bytes>(64);
                let ticker = frames.clone();
                tokio::spawn(async move {
                    let mut tick = tokio::time::interval(Duration::from_secs_f64(1.0 / 60.0));
                    let frame = Bytes::from(vec![0u8; FRAME_BYTES]);
                    loop {
                        tick.tick().await;
                        ticker.send(frame.clone()).ok();
                    }
                });
                let app = Router::new()
                    .route("/healthz", get(|| async { "ok" }))
                    .route("/ws", get(upgrade))
                    .with_state(frames);
                let listener = tokio::net::TcpListener::bind(addr).await?;
                axum::serve(listener, app).await?;
                Ok(())
            })
    }

    async fn upgrade(
        ws: WebSocketUpgrade,
        State(frames): State<broadcast::Sender<Bytes>>,
    ) -> Response {
        ws.on_upgrade(move |socket| forward(socket, frames.subscribe()))
    }

    async fn forward(mut socket: WebSocket, mut frames: broadcast::Receiver<Bytes>) {
        loop {
            match frames.recv().await {
                Ok(frame) => {
                    if socket.send(Message::Binary(frame)).await.is_err() {
                        return;
                    }
                }
                Err(broadcast::error::RecvError::Lagged(_)) => {}
                Err(broadcast::error::RecvError::Closed) => return,
            }
        }
    }
}
