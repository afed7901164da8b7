//! The browser harness: chromedriver and headless Chromium, page queries, screenshots.

use crate::common::{self, http};
use fantoccini::{Client as Browser, ClientBuilder, Locator};
use posecast_client::net::Client;
use posecast_proto::msg::AvatarId;
use posecast_server::config::Config;
use posecast_server::startup::Server;
use serde_json::{Value, json};
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};
use tokio::io::{AsyncReadExt, AsyncWriteExt};

/// One browser at a time: the tests measure frames and push delays, which several Chromiums
/// sharing two cores would blur.
static ONE_AT_A_TIME: tokio::sync::Mutex<()> = tokio::sync::Mutex::const_new(());

const CHROMIUM: &str = "/usr/bin/chromium";
const CHROMEDRIVER: &str = "/usr/bin/chromedriver";

/// A chromedriver child process in a process group of its own, with the Chromium it starts:
/// the whole group is killed on drop (also when a test panics before closing the session).
pub struct Driver {
    child: Child,
    profile: PathBuf,
    _turn: tokio::sync::MutexGuard<'static, ()>,
}

impl Drop for Driver {
    fn drop(&mut self) {
        let group = format!("-{}", self.child.id());
        let _ = Command::new("kill")
            .args(["-KILL", "--", &group])
            .stderr(Stdio::null())
            .status();
        let _ = self.child.kill();
        let _ = self.child.wait();
        let _ = std::fs::remove_dir_all(&self.profile);
    }
}

/// A free port for chromedriver *below* the kernel's ephemeral range
/// (`ip_local_port_range`): a port taken from that range and let go (bind to port 0, close)
/// can be handed to a test server binding port 0 before chromedriver binds it, and then the
/// session request reached that server (a CI run failed so: "NotW3C", with a test page for
/// an answer). Ports below the range are never handed out that way.
fn driver_port() -> u16 {
    let ephemeral = std::fs::read_to_string("/proc/sys/net/ipv4/ip_local_port_range")
        .ok()
        .and_then(|s| s.split_whitespace().next()?.parse::<u16>().ok())
        .unwrap_or(32768);
    let (low, high) = (10_000u16, ephemeral.max(11_000));
    let seed = u64::from(std::process::id())
        ^ std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| u64::from(d.subsec_nanos()));
    let span = u64::from(high - low);
    (0..span)
        .map(|i| low + ((seed + i * 7919) % span) as u16)
        .find(|&p| std::net::TcpListener::bind(("127.0.0.1", p)).is_ok())
        .expect("a free port below the ephemeral range")
}

/// Starts chromedriver and a headless Chromium session at 1280×800.
pub async fn browser() -> (Driver, Browser) {
    let turn = ONE_AT_A_TIME.lock().await;
    assert!(
        Path::new(CHROMEDRIVER).exists() && Path::new(CHROMIUM).exists(),
        "chromium and chromedriver are needed (scripts/test installs them)"
    );
    let port = driver_port();
    let child = Command::new(CHROMEDRIVER)
        .arg(format!("--port={port}"))
        .process_group(0)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .expect("start chromedriver");
    let profile =
        std::env::temp_dir().join(format!("posecast-dashboard-{}-{port}", std::process::id()));
    let driver = Driver {
        child,
        profile,
        _turn: turn,
    };
    let deadline = Instant::now() + Duration::from_secs(60);
    while tokio::net::TcpStream::connect(("127.0.0.1", port))
        .await
        .is_err()
    {
        assert!(Instant::now() < deadline, "chromedriver did not start");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let mut caps = serde_json::Map::new();
    caps.insert(
        "goog:chromeOptions".into(),
        json!({
            "binary": CHROMIUM,
            "args": [
                "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                "--disable-background-networking", "--disable-component-update", "--disable-sync",
                "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
                "--window-size=1280,800", "--force-device-scale-factor=1",
                format!("--user-data-dir={}", driver.profile.display()),
            ],
        }),
    );
    let connector = hyper_util::client::legacy::connect::HttpConnector::new();
    let client = ClientBuilder::new(connector)
        .capabilities(caps)
        .connect(&format!("http://127.0.0.1:{port}"))
        .await
        .expect("start a Chromium session");
    (driver, client)
}

/// Evaluates `expr` in the page until it is truthy, for at most `secs`; returns its value.
pub async fn wait_js(b: &Browser, secs: u64, expr: &str) -> Value {
    let deadline = Instant::now() + Duration::from_secs(secs);
    loop {
        let v = b
            .execute(&format!("return ({expr});"), vec![])
            .await
            .unwrap();
        let truthy =
            !matches!(&v, Value::Null | Value::Bool(false)) && v != json!(0) && v != json!("");
        if truthy {
            return v;
        }
        assert!(Instant::now() < deadline, "timed out waiting for `{expr}`");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

pub async fn find(b: &Browser, css: &str) -> fantoccini::elements::Element {
    b.wait()
        .at_most(Duration::from_secs(60))
        .for_element(Locator::Css(css))
        .await
        .unwrap_or_else(|e| panic!("no element {css}: {e}"))
}

pub async fn errors(b: &Browser) -> Value {
    b.execute("return window.posecast.errors;", vec![])
        .await
        .unwrap()
}

pub async fn command(server: &Server, body: Value) -> (u16, Value) {
    let (status, text) = http(server, "POST", "/api/commands", Some(&body.to_string())).await;
    (status, serde_json::from_str(&text).unwrap_or(Value::Null))
}

pub async fn avatar_state(server: &Server, avatar: &str) -> Value {
    let (status, body) = command(server, json!({"op": "get_avatar", "avatar": avatar})).await;
    assert_eq!(status, 200, "{body}");
    body["result"].clone()
}

/// Largest angle (degrees) of `joint`'s streamed local rotation from identity over `secs`.
pub async fn max_angle(c: &Client, avatar: &AvatarId, joint: usize, secs: f32) -> f32 {
    let end = Instant::now() + Duration::from_secs_f32(secs);
    let mut max = 0.0f32;
    while Instant::now() < end {
        if let Some(p) = c.latest(avatar) {
            max = max.max(
                p.locals[joint]
                    .rotation
                    .angle_between(glam::Quat::IDENTITY)
                    .to_degrees(),
            );
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    max
}

/// Non-background pixels of a screenshot inside the CSS-pixel rectangle `(x, y, w, h)`.
pub fn count_avatar_pixels(png_bytes: &[u8], rect: (f64, f64, f64, f64)) -> (usize, usize) {
    let (pixels, area) = avatar_pixels(png_bytes, rect, GRID_DIFFERENCE);
    (pixels.len(), area)
}

/// Connected runs `(first, last)` of screenshot columns (CSS px) holding an avatar pixel inside
/// `rect`: one per figure drawn apart from the others. Stricter than [`count_avatar_pixels`]:
/// the grid's nearest lines (80 from the background) span the whole preview and would join
/// the figures; the lit mesh and the skeleton overlay are far brighter.
pub fn column_runs(png_bytes: &[u8], rect: (f64, f64, f64, f64)) -> Vec<(usize, usize)> {
    let (pixels, _) = avatar_pixels(png_bytes, rect, 150);
    let mut columns: Vec<usize> = pixels.iter().map(|&(x, _)| x).collect();
    columns.sort_unstable();
    columns.dedup();
    let mut runs: Vec<(usize, usize)> = Vec::new();
    for x in columns {
        match runs.last_mut() {
            Some(run) if run.1 + 1 == x => run.1 = x,
            _ => runs.push((x, x)),
        }
    }
    runs
}

/// Summed RGB difference from the preview's background above which a pixel is no grid.
const GRID_DIFFERENCE: i32 = 60;

/// `(x, y)` of the pixels of a screenshot inside the CSS-pixel rectangle `(x, y, w, h)` whose
/// summed RGB difference from the background exceeds `threshold`, and the rectangle's area.
pub fn avatar_pixels(
    png_bytes: &[u8],
    rect: (f64, f64, f64, f64),
    threshold: i32,
) -> (Vec<(usize, usize)>, usize) {
    let decoder = png::Decoder::new(png_bytes);
    let mut reader = decoder.read_info().unwrap();
    let mut buf = vec![0; reader.output_buffer_size()];
    let info = reader.next_frame(&mut buf).unwrap();
    let channels = info.color_type.samples();
    // The preview's clear colour (viewer.js BACKGROUND); most of the grid is within 60 of it (its nearest lines reach 80).
    let bg = [27i32, 30, 36];
    let (x0, y0) = (rect.0.max(0.0) as usize, rect.1.max(0.0) as usize);
    let x1 = ((rect.0 + rect.2) as usize).min(info.width as usize);
    let y1 = ((rect.1 + rect.3) as usize).min(info.height as usize);
    let mut pixels = Vec::new();
    for y in y0..y1 {
        for x in x0..x1 {
            let i = (y * info.width as usize + x) * channels;
            let d: i32 = (0..3).map(|c| (i32::from(buf[i + c]) - bg[c]).abs()).sum();
            if d > threshold {
                pixels.push((x, y));
            }
        }
    }
    (pixels, (x1 - x0) * (y1 - y0))
}

pub fn artifacts() -> PathBuf {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("target/test-artifacts");
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// A server with the built-in avatar plus the CSE169 `test.skel` rig (DOF limits on `knee_r`).
pub async fn server_with_limited_rig() -> (Server, PathBuf) {
    let dir =
        std::env::temp_dir().join(format!("posecast-dashboard-assets-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let skel = Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/testdata/cse169/test.skel");
    std::fs::copy(&skel, dir.join("test.skel")).expect("../shared/testdata/cse169/test.skel");
    let config = Config {
        listen: "127.0.0.1:0".parse().unwrap(),
        tick_rate: 60.0,
        asset_dirs: vec![dir.clone()],
        access: common::test_access(),
        ..Config::default()
    };
    let server = Server::start(config).await.unwrap();
    server.ready().await.unwrap();
    (server, dir)
}

/// Writes a screenshot for the README and the guide small: RGB without the alpha channel, 6 bits a channel
/// (the lowest two bits of the shading's gradients are what compresses worst; invisible),
/// best compression.
pub fn write_small_png(png_bytes: &[u8], path: &Path) {
    let mut reader = png::Decoder::new(png_bytes).read_info().unwrap();
    let mut buf = vec![0; reader.output_buffer_size()];
    let info = reader.next_frame(&mut buf).unwrap();
    let channels = info.color_type.samples();
    let rgb: Vec<u8> = buf[..info.buffer_size()]
        .chunks_exact(channels)
        .flat_map(|p| [p[0] & 0xfc, p[1] & 0xfc, p[2] & 0xfc])
        .collect();
    let file = std::io::BufWriter::new(std::fs::File::create(path).unwrap());
    let mut encoder = png::Encoder::new(file, info.width, info.height);
    encoder.set_color(png::ColorType::Rgb);
    encoder.set_depth(png::BitDepth::Eight);
    encoder.set_compression(png::Compression::Best);
    encoder.set_adaptive_filter(png::AdaptiveFilterType::Adaptive);
    encoder
        .write_header()
        .unwrap()
        .write_image_data(&rgb)
        .unwrap();
}

/// Serves `html` at `/` (any other path), the files of `modules` under `/node_modules/` and
/// `files` at their paths, until the test ends, on another origin than the posecast server's,
/// as a third party's page, bundle and models would be.
pub async fn serve_origin(
    html: String,
    modules: Option<PathBuf>,
    files: Vec<(&'static str, Vec<u8>)>,
) -> String {
    let files = std::sync::Arc::new(files);
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    tokio::spawn(async move {
        while let Ok((mut stream, _)) = listener.accept().await {
            let (html, modules, files) = (html.clone(), modules.clone(), files.clone());
            tokio::spawn(async move {
                let mut head = Vec::new();
                let mut buf = [0u8; 4096];
                while !head.windows(4).any(|w| w == b"\r\n\r\n") && head.len() < 65536 {
                    match stream.read(&mut buf).await {
                        Ok(0) | Err(_) => return,
                        Ok(n) => head.extend_from_slice(&buf[..n]),
                    }
                }
                let head = String::from_utf8_lossy(&head);
                let path = head.split_whitespace().nth(1).unwrap_or("/").to_owned();
                let file = files.iter().find(|(p, _)| *p == path);
                let (status, content_type, body) = match path.strip_prefix("/node_modules/") {
                    _ if file.is_some() => (
                        "200 OK",
                        "application/octet-stream",
                        file.map(|(_, b)| b.clone()).unwrap_or_default(),
                    ),
                    Some(rest) if !rest.contains("..") => {
                        match modules.as_ref().map(|m| std::fs::read(m.join(rest))) {
                            Some(Ok(bytes)) => ("200 OK", "text/javascript; charset=utf-8", bytes),
                            _ => ("404 Not Found", "text/plain", b"no such file".to_vec()),
                        }
                    }
                    Some(_) => ("404 Not Found", "text/plain", b"no such file".to_vec()),
                    None => ("200 OK", "text/html; charset=utf-8", html.into_bytes()),
                };
                let mut answer = format!(
                    "HTTP/1.1 {status}\r\nContent-Type: {content_type}\r\n\
                     Content-Length: {}\r\nConnection: close\r\n\r\n",
                    body.len()
                )
                .into_bytes();
                answer.extend_from_slice(&body);
                if stream.write_all(&answer).await.is_ok() {
                    stream.shutdown().await.ok();
                }
            });
        }
    });
    format!("http://{addr}/")
}
