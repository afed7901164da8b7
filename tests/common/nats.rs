//! A `nats-server` child process with JetStream on a free loopback port, for the cluster tests
//! (`scripts/test` installs the Debian package when it is missing).

use std::net::{SocketAddr, TcpListener, TcpStream};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// `nats-server -js` on `127.0.0.1`, killed (and its store folder removed) when dropped.
pub struct Nats {
    child: Child,
    program: &'static str,
    /// More arguments (credentials: `--user`/`--pass`, `--auth`; a configuration file: `-c`).
    extra: Vec<String>,
    /// Its environment's additions (the variables a configuration file refers to).
    env: Vec<(String, String)>,
    /// Its client port.
    pub port: u16,
    store: tempfile::TempDir,
}

fn spawn(
    program: &str,
    port: u16,
    store: &std::path::Path,
    extra: &[String],
    env: &[(String, String)],
) -> Child {
    Command::new(program)
        .args(["-js", "-a", "127.0.0.1", "-p", &port.to_string(), "-sd"])
        .arg(store)
        .args(extra)
        .envs(env.iter().map(|(k, v)| (k, v)))
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .expect("cannot start nats-server")
}

impl Nats {
    /// Starts it and waits until it accepts connections (at most 20 s); `None`, after
    /// [`posecast_proto::testing::skip`] (a failure under `CI=true`), when `nats-server` is
    /// not installed.
    pub fn start() -> Option<Self> {
        Self::start_with(&[])
    }

    /// [`Nats::start`] with more arguments for `nats-server` (e.g. `--user u --pass p`, or
    /// `--auth TOKEN`: clients must then authenticate).
    pub fn start_with(extra: &[&str]) -> Option<Self> {
        Self::start_env(extra, &[])
    }

    /// The repository's sample configuration, `scripts/nats/cluster.conf` (posecast's own
    /// account, users and subject permissions), with the variables it refers to in `env`.
    pub fn start_config(env: &[(&str, &str)]) -> Option<Self> {
        let conf = concat!(env!("CARGO_MANIFEST_DIR"), "/scripts/nats/cluster.conf");
        Self::start_env(&["-c", conf], env)
    }

    /// [`Nats::start_with`] with more environment variables.
    pub fn start_env(extra: &[&str], env: &[(&str, &str)]) -> Option<Self> {
        let extra: Vec<String> = extra.iter().map(|&a| a.to_owned()).collect();
        let env: Vec<(String, String)> = env
            .iter()
            .map(|(k, v)| ((*k).to_owned(), (*v).to_owned()))
            .collect();
        let program = [
            "nats-server",
            "/usr/sbin/nats-server",
            "/usr/bin/nats-server",
        ]
        .into_iter()
        .find(|p| {
            Command::new(p)
                .arg("--version")
                .stdout(Stdio::null())
                .stderr(Stdio::null())
                .status()
                .is_ok()
        });
        let Some(program) = program else {
            posecast_proto::testing::skip(
                "nats-server is not installed (apt-get install nats-server; scripts/test does)",
            );
            return None;
        };
        let store = tempfile::tempdir().unwrap();
        let port = TcpListener::bind("127.0.0.1:0")
            .unwrap()
            .local_addr()
            .unwrap()
            .port();
        let nats = Self {
            child: spawn(program, port, store.path(), &extra, &env),
            program,
            extra,
            env,
            port,
            store,
        };
        nats.wait_listening();
        Some(nats)
    }

    fn wait_listening(&self) {
        let addr = SocketAddr::from(([127, 0, 0, 1], self.port));
        let deadline = Instant::now() + Duration::from_secs(20);
        // A connection is not proof enough: while nothing listens on the port, a connect can
        // pick the same port as its own source and reach itself (TCP simultaneous open), and
        // a CI run then started posecast against a server that was not there yet. nats-server
        // greets every client with `INFO`.
        let greets = || {
            use std::io::Read;
            let Ok(mut s) = TcpStream::connect_timeout(&addr, Duration::from_millis(200)) else {
                return false;
            };
            s.set_read_timeout(Some(Duration::from_secs(1))).ok();
            let mut head = [0u8; 4];
            s.read_exact(&mut head).is_ok() && &head == b"INFO"
        };
        while !greets() {
            assert!(
                Instant::now() < deadline,
                "nats-server did not listen on {addr}"
            );
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    /// Its URL.
    pub fn url(&self) -> String {
        format!("nats://127.0.0.1:{}", self.port)
    }

    /// Kills it (SIGKILL): clients see the connection drop.
    pub fn stop(&mut self) {
        self.child.kill().ok();
        self.child.wait().ok();
    }

    /// Starts it again on the same port with the same store (what JetStream held survives).
    pub fn restart(&mut self) {
        self.stop();
        self.child = spawn(
            self.program,
            self.port,
            self.store.path(),
            &self.extra,
            &self.env,
        );
        self.wait_listening();
    }
}

impl Drop for Nats {
    fn drop(&mut self) {
        self.stop();
    }
}
