//! The server side of a run: the spawned `posecast` child, the scene set up over a command
//! connection, `/metrics` scrapes and process CPU from `/proc`.

use crate::client;
use anyhow::{Context, Result, bail};
use futures_util::SinkExt;
use posecast_client::net::transport::Link;
use posecast_proto::command::Command;
use posecast_proto::msg::{AvatarId, ClientMsg, SceneId, ServerMsg};
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::process::{Child, Stdio};
use std::time::{Duration, Instant};
use tokio::io::{AsyncReadExt, AsyncWriteExt};

/// The soft limit on open files of this process (`/proc/self/limits`).
pub fn open_files_limit() -> Result<u64> {
    let limits = std::fs::read_to_string("/proc/self/limits").context("read /proc/self/limits")?;
    limits
        .lines()
        .find(|l| l.starts_with("Max open files"))
        .and_then(|l| l.split_whitespace().nth(3))
        .and_then(|v| v.parse().ok())
        .context("no 'Max open files' in /proc/self/limits")
}

/// Clock ticks per second of `/proc/<pid>/stat` times (`getconf CLK_TCK`; 100 on Linux).
pub fn clock_ticks_per_second() -> f64 {
    std::process::Command::new("getconf")
        .arg("CLK_TCK")
        .output()
        .ok()
        .and_then(|o| String::from_utf8(o.stdout).ok())
        .and_then(|s| s.trim().parse().ok())
        .unwrap_or(100.0)
}

fn stat_ticks(path: &str) -> Result<u64> {
    let stat = std::fs::read_to_string(path).with_context(|| format!("read {path}"))?;
    // The command name (field 2) may hold spaces; fields after its ')' are plain.
    let after = stat
        .rsplit_once(')')
        .map(|(_, rest)| rest)
        .with_context(|| format!("{path}: no ')'"))?;
    let fields: Vec<&str> = after.split_whitespace().collect();
    // utime and stime are fields 14 and 15 of the whole line: 12 and 13 after the name.
    let field = |i: usize| -> Result<u64> {
        fields
            .get(i)
            .and_then(|v| v.parse().ok())
            .with_context(|| format!("{path}: field {} missing", i + 2))
    };
    Ok(field(11)? + field(12)?)
}

/// User + system CPU time of process `pid`, in clock ticks.
pub fn cpu_ticks(pid: u32) -> Result<u64> {
    stat_ticks(&format!("/proc/{pid}/stat"))
}

/// User + system CPU time of this process, in clock ticks.
pub fn cpu_ticks_self() -> Result<u64> {
    stat_ticks("/proc/self/stat")
}

/// A `posecast` server run as a child process on a free loopback port.
#[derive(Debug)]
pub struct Spawned {
    child: Child,
    port: u16,
}

impl Spawned {
    /// Starts `bin` (default: `posecast` beside this executable) with the open-files limit
    /// raised to `fd_limit`, and waits until it accepts connections.
    pub async fn start(
        bin: Option<&Path>,
        tick_rate: f32,
        fd_limit: u64,
        control_token: &str,
    ) -> Result<Self> {
        Self::start_with(bin, tick_rate, fd_limit, control_token, Vec::new()).await
    }

    /// [`Spawned::start`] with more arguments (a cluster node's `--nats`, `--node`).
    pub async fn start_with(
        bin: Option<&Path>,
        tick_rate: f32,
        fd_limit: u64,
        control_token: &str,
        more: Vec<String>,
    ) -> Result<Self> {
        let bin = match bin {
            Some(b) => b.to_owned(),
            None => sibling("posecast")?,
        };
        Self::launch(
            &bin,
            fd_limit,
            &[("POSECAST_CONTROL_TOKEN", control_token)],
            |port| {
                vec![
                    "--listen".into(),
                    format!("127.0.0.1:{port}"),
                    "--tick-rate".into(),
                    tick_rate.to_string(),
                    // Measure the fan-out, not fsync; and start from the same state every run.
                    "--no-persist".into(),
                    // Every load client comes from 127.0.0.1: lift the per-address cap (default
                    // 256) to the global one.
                    "--max-connections-per-address".into(),
                    posecast_server::config::DEFAULT_MAX_CONNECTIONS.to_string(),
                ]
                .into_iter()
                .chain(more)
                .collect()
            },
        )
        .await
    }

    /// Starts this executable as the reference server ([`crate::reference`]) with `avatars`
    /// avatars playing `clips` at `tick_rate`, sending the frames of protocol `protocol`.
    pub async fn start_reference(
        fd_limit: u64,
        avatars: usize,
        clips: &[String],
        tick_rate: f32,
        protocol: u32,
    ) -> Result<Self> {
        let bin = std::env::current_exe()?;
        Self::launch(&bin, fd_limit, &[], |port| {
            vec![
                "--serve-reference".into(),
                format!("127.0.0.1:{port}"),
                "--avatars".into(),
                avatars.to_string(),
                "--clips".into(),
                clips.join(","),
                "--tick-rate".into(),
                tick_rate.to_string(),
                "--protocol".into(),
                protocol.to_string(),
            ]
        })
        .await
    }

    /// Runs `bin` with the arguments `args(port)` gives for a free loopback port.
    async fn launch(
        bin: &Path,
        fd_limit: u64,
        env: &[(&str, &str)],
        args: impl FnOnce(u16) -> Vec<String>,
    ) -> Result<Self> {
        // A port that was free a moment ago; the server binds it right after.
        let port = std::net::TcpListener::bind("127.0.0.1:0")?
            .local_addr()?
            .port();
        // `sh` raises the child's soft limit; no libc here, and it keeps the server unchanged.
        let child = std::process::Command::new("sh")
            .arg("-c")
            .arg(r#"ulimit -n "$1" 2>/dev/null; shift; exec "$@""#)
            .arg("sh")
            .arg(fd_limit.to_string())
            .arg(bin)
            .args(args(port))
            .envs(env.iter().copied())
            .env("RUST_LOG", "warn")
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .spawn()
            .with_context(|| format!("start {}", bin.display()))?;
        let mut spawned = Self { child, port };
        let deadline = Instant::now() + Duration::from_secs(10);
        loop {
            if tokio::net::TcpStream::connect(("127.0.0.1", port))
                .await
                .is_ok()
            {
                break;
            }
            if let Some(status) = spawned.child.try_wait()? {
                bail!("{} exited at start: {status}", bin.display());
            }
            if Instant::now() > deadline {
                spawned.kill();
                bail!(
                    "{} did not listen on port {port} within 10 s",
                    bin.display()
                );
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        eprintln!(
            "started {} (pid {}) on 127.0.0.1:{port}",
            bin.display(),
            spawned.pid()
        );
        Ok(spawned)
    }

    /// Its process id (`sh` execs the server, so it is the server's).
    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    /// Its websocket URL.
    pub fn ws_url(&self) -> String {
        format!("ws://127.0.0.1:{}/ws", self.port)
    }

    fn kill(&mut self) {
        if let Err(e) = self.child.kill() {
            eprintln!("could not kill the server: {e}");
        }
        self.child.wait().ok();
    }

    /// Asks the server to shut down gracefully (SIGTERM), killing it after 5 s.
    pub async fn stop(mut self) {
        let term = std::process::Command::new("kill")
            .arg("-TERM")
            .arg(self.pid().to_string())
            .status();
        if term.is_ok() {
            let deadline = Instant::now() + Duration::from_secs(5);
            while Instant::now() < deadline {
                if matches!(self.child.try_wait(), Ok(Some(_))) {
                    return;
                }
                tokio::time::sleep(Duration::from_millis(50)).await;
            }
        }
        self.kill();
    }
}

impl Drop for Spawned {
    fn drop(&mut self) {
        // After `stop` the child was reaped and this is a no-op; on an early error it ends
        // the server rather than leaving it running.
        if matches!(self.child.try_wait(), Ok(None)) {
            self.kill();
        }
    }
}

fn sibling(name: &str) -> Result<PathBuf> {
    let exe = std::env::current_exe()?;
    let path = exe
        .parent()
        .context("this executable has no folder")?
        .join(name);
    if !path.is_file() {
        bail!(
            "{} not found: build it (`cargo build --release`) or pass --server-bin",
            path.display()
        );
    }
    Ok(path)
}

async fn command(ws: &mut Link, id: u64, command: Command) -> Result<()> {
    client::send(
        ws,
        &ClientMsg::Command {
            id,
            command,
            idempotency_key: None,
        },
    )
    .await?;
    client::expect(
        ws,
        |m| matches!(m, ServerMsg::Ack { id: a, .. } if *a == id),
    )
    .await?;
    Ok(())
}

/// Makes `scene` hold `avatars` built-in avatars, the added ones playing `clips` in turn, over
/// a websocket. The server's `default` scene already holds one (playing `idle`) and is used as
/// it is, so only one scene ticks; any other scene is created.
pub async fn create_scene(
    url: &str,
    token: &str,
    scene: &str,
    avatars: usize,
    clips: &[String],
) -> Result<()> {
    let mut ws = client::connect_control(url, token).await?;
    let scene_id = SceneId(scene.to_owned());
    let existing = if scene == posecast_server::startup::DEFAULT_SCENE {
        1
    } else {
        command(
            &mut ws,
            0,
            Command::CreateScene {
                scene: scene_id.clone(),
            },
        )
        .await
        .with_context(|| format!("create scene {scene}"))?;
        0
    };
    for i in 0..avatars.saturating_sub(existing) {
        let clip = clips.get(i % clips.len().max(1)).cloned();
        command(
            &mut ws,
            i as u64 + 1,
            Command::AddAvatar {
                scene: scene_id.clone(),
                asset: posecast_server::builtin::BUILTIN_ASSET.into(),
                avatar: Some(AvatarId(format!("load-{i}"))),
                clip,
                position: None,
                rotation: None,
            },
        )
        .await
        .with_context(|| format!("add avatar {i}"))?;
    }
    // Done with commands; a failed close leaves nothing behind that matters.
    ws.sink
        .send(tokio_tungstenite::tungstenite::Message::Close(None))
        .await
        .ok();
    eprintln!("scene {scene}: {avatars} avatars");
    Ok(())
}

/// `GET path` at `host:port` (HTTP/1.0, 5 s bound): status and body.
pub async fn http_get(authority: &str, path: &str) -> Result<(u16, String)> {
    let mut stream = tokio::net::TcpStream::connect(authority).await?;
    let request = format!("GET {path} HTTP/1.0\r\nHost: {authority}\r\n\r\n");
    stream.write_all(request.as_bytes()).await?;
    let mut text = String::new();
    tokio::time::timeout(Duration::from_secs(5), stream.read_to_string(&mut text))
        .await
        .with_context(|| format!("{path} did not answer in 5 s"))??;
    let status = text
        .split(' ')
        .nth(1)
        .and_then(|s| s.parse().ok())
        .unwrap_or(0);
    let body = text.split_once("\r\n\r\n").map_or("", |(_, b)| b);
    Ok((status, body.to_owned()))
}

/// The server's `/metrics` counters (`posecast_name value` lines) at `host:port`.
pub async fn scrape_metrics(authority: &str) -> Result<HashMap<String, f64>> {
    let mut stream = tokio::net::TcpStream::connect(authority).await?;
    let request = format!("GET /metrics HTTP/1.0\r\nHost: {authority}\r\n\r\n");
    stream.write_all(request.as_bytes()).await?;
    let mut body = String::new();
    tokio::time::timeout(Duration::from_secs(5), stream.read_to_string(&mut body))
        .await
        .context("/metrics did not answer in 5 s")??;
    Ok(body
        .lines()
        .filter(|l| l.starts_with("posecast_"))
        .filter_map(|l| {
            let (name, value) = l.rsplit_once(' ')?;
            Some((name.to_owned(), value.parse().ok()?))
        })
        .collect())
}

/// Busy-loop processes (`sh -c 'while :; do :; done'`) that load the machine while they live:
/// the outside CPU contention of a busy host.
#[derive(Debug)]
pub struct Busy(Vec<std::process::Child>);

impl Busy {
    /// Starts `n` of them.
    ///
    /// # Errors
    /// One could not be started (those started are stopped).
    pub fn start(n: u64) -> Result<Self> {
        let mut busy = Self(Vec::new());
        for _ in 0..n {
            let child = std::process::Command::new("sh")
                .args(["-c", "while :; do :; done"])
                .stdin(Stdio::null())
                .stdout(Stdio::null())
                .spawn()
                .context("start a busy loop")?;
            busy.0.push(child);
        }
        Ok(busy)
    }
}

impl Drop for Busy {
    fn drop(&mut self) {
        for child in &mut self.0 {
            child.kill().ok();
            child.wait().ok();
        }
    }
}
