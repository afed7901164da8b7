//! The real `posecast` binary as a child process (for persistence and start-up tests).

use std::io::{BufRead, BufReader};
use std::net::SocketAddr;
use std::process::{Command, ExitStatus, Stdio};
use std::sync::{Arc, Mutex};
use std::time::Duration;

/// The `posecast` binary running as a child process on a free port.
pub struct Posecast {
    child: std::process::Child,
    /// Where it listens.
    pub addr: SocketAddr,
    output: Arc<Mutex<Vec<String>>>,
}

impl Posecast {
    /// The binary at 30 Hz on data folder `data`, holding the tests' control token (for
    /// tests that kill it and start it again on the same folder).
    #[allow(dead_code)]
    pub fn on_data(data: &std::path::Path) -> Self {
        let dir = data.to_str().expect("a UTF-8 temporary path");
        Self::start(
            &["--tick-rate", "30", "--data", dir],
            &[("POSECAST_CONTROL_TOKEN", super::CONTROL)],
        )
    }

    /// Starts the binary on `127.0.0.1:0` with `args` and `env` (which may override the
    /// defaults `RUST_LOG=info`, `NO_COLOR=1`), and waits until it is ready: every stored
    /// scene restored (`/healthz` answers 200).
    pub fn start(args: &[&str], env: &[(&str, &str)]) -> Self {
        let server = Self::launch(args, env);
        server.wait_ready(Duration::from_secs(60));
        server
    }

    /// [`Posecast::start`] with `dir` as the working folder (where the default data folder,
    /// `./posecast-data`, goes).
    pub fn start_in(dir: &std::path::Path, args: &[&str], env: &[(&str, &str)]) -> Self {
        let server = Self::spawn(binary(args, env).current_dir(dir));
        server.wait_ready(Duration::from_secs(60));
        server
    }

    /// [`Posecast::start`] up to the URL it prints: listening, maybe still loading.
    pub fn launch(args: &[&str], env: &[(&str, &str)]) -> Self {
        Self::spawn(&mut binary(args, env))
    }

    fn spawn(command: &mut Command) -> Self {
        let mut child = command.spawn().expect("cannot start the posecast binary");
        let output = Arc::new(Mutex::new(Vec::new()));
        let (tx, rx) = std::sync::mpsc::channel();
        let out = child.stdout.take().unwrap();
        let err = child.stderr.take().unwrap();
        for (stream, tx) in [
            (Box::new(out) as Box<dyn std::io::Read + Send>, Some(tx)),
            (Box::new(err), None),
        ] {
            let output = output.clone();
            std::thread::spawn(move || {
                for line in BufReader::new(stream).lines().map_while(Result::ok) {
                    if let (Some(tx), Some(url)) =
                        (&tx, line.strip_prefix("posecast listening on http://"))
                    {
                        tx.send(url.trim().parse::<SocketAddr>().unwrap()).ok();
                    }
                    output.lock().unwrap().push(line);
                }
            });
        }
        let addr = rx
            .recv_timeout(Duration::from_secs(60))
            .unwrap_or_else(|_| panic!("no URL printed: {:?}", output.lock().unwrap()));
        Self {
            child,
            addr,
            output,
        }
    }

    /// `GET /healthz`: status and body, or `None` when nothing answered.
    pub fn health(&self) -> Option<(u16, String)> {
        health(self.addr)
    }

    /// Polls `/healthz` until it answers 200 `ok`; panics after `timeout`.
    pub fn wait_ready(&self, timeout: Duration) {
        let deadline = std::time::Instant::now() + timeout;
        loop {
            match self.health() {
                Some((200, body)) if body == "ok" => return,
                last if std::time::Instant::now() >= deadline => panic!(
                    "not ready within {timeout:?}: /healthz gave {last:?}; output {:?}",
                    self.output()
                ),
                _ => std::thread::sleep(Duration::from_millis(20)),
            }
        }
    }

    /// The process id (to read its `/proc` entries).
    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    /// SIGKILL: no graceful shutdown, nothing flushed that was not already on disk.
    pub fn kill(mut self) {
        self.child.kill().unwrap();
        self.child.wait().unwrap();
    }

    /// Sends signal `name` (`STOP`, `CONT`…) to the process.
    pub fn signal(&self, name: &str) {
        let status = Command::new("kill")
            .args([&format!("-{name}"), &self.child.id().to_string()])
            .status()
            .expect("cannot run kill");
        assert!(status.success(), "kill -{name} failed");
    }

    /// SIGTERM: a graceful shutdown.
    pub fn terminate(&self) {
        let status = Command::new("kill")
            .args(["-TERM", &self.child.id().to_string()])
            .status()
            .expect("cannot run kill");
        assert!(status.success(), "kill -TERM failed");
    }

    /// Waits up to `timeout` for the process to exit.
    pub fn wait_exit(&mut self, timeout: Duration) -> Option<ExitStatus> {
        let deadline = std::time::Instant::now() + timeout;
        loop {
            if let Some(status) = self.child.try_wait().unwrap() {
                return Some(status);
            }
            if std::time::Instant::now() >= deadline {
                return None;
            }
            std::thread::sleep(Duration::from_millis(5));
        }
    }

    /// Every line it printed so far (stdout and stderr).
    pub fn output(&self) -> Vec<String> {
        self.output.lock().unwrap().clone()
    }
}

impl Drop for Posecast {
    fn drop(&mut self) {
        self.child.kill().ok();
        self.child.wait().ok();
    }
}

/// Runs the binary with `args` (on `127.0.0.1:0`) and `env` until it exits, for at most 60 s;
/// returns its exit status and everything it printed (stdout, then stderr).
pub fn run_to_exit(args: &[&str], env: &[(&str, &str)]) -> (ExitStatus, String) {
    let mut child = binary(args, env)
        .spawn()
        .expect("cannot start the posecast binary");
    let deadline = std::time::Instant::now() + Duration::from_secs(60);
    while child.try_wait().unwrap().is_none() {
        if std::time::Instant::now() >= deadline {
            child.kill().ok();
            panic!("the binary did not exit within 60 s");
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    let output = child.wait_with_output().unwrap();
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&output.stdout),
        String::from_utf8_lossy(&output.stderr)
    );
    (output.status, text)
}

/// `GET /healthz` on `addr` (HTTP/1.1, `Connection: close`, blocking, 5 s bound): status and
/// body, or `None` when nothing answered.
pub fn health(addr: SocketAddr) -> Option<(u16, String)> {
    use std::io::{Read, Write};
    let bound = Duration::from_secs(5);
    let mut stream = std::net::TcpStream::connect_timeout(&addr, bound).ok()?;
    stream.set_read_timeout(Some(bound)).ok()?;
    write!(
        stream,
        "GET /healthz HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n"
    )
    .ok()?;
    let mut response = String::new();
    stream.read_to_string(&mut response).ok()?;
    let status = response.split(' ').nth(1)?.parse().ok()?;
    let body = response.split_once("\r\n\r\n")?.1.to_owned();
    Some((status, body))
}

/// The `posecast` binary on `127.0.0.1:0` with `args` and `env`, output captured.
fn binary(args: &[&str], env: &[(&str, &str)]) -> Command {
    let mut command = Command::new(env!("CARGO_BIN_EXE_posecast"));
    command
        .args(["--listen", "127.0.0.1:0"])
        .args(args)
        .env("NO_COLOR", "1")
        .env("RUST_LOG", "info")
        .envs(env.iter().copied())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped());
    command
}
