//! Pose in → pose out, shared by the live-driving benches (`live_drive`, `cluster_latency`):
//! a driver sends 120 poses a second, each a distinct `l_elbow` angle, while library clients
//! record when each pose first shows in their stream; latency = seen − sent (one machine, one
//! clock).

use glam::Quat;
use posecast_client::net::{Client, ClientOptions, Driver, Event};
use posecast_proto::msg::{AvatarId, Encoding};
use posecast_server::startup::Server;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// Radians between consecutive poses' elbow angles (far above the quantisation step).
pub const STEP: f32 = 0.004;

/// What to measure: who watches, who drives, what.
pub struct Run<'a> {
    /// The server the watching clients subscribe on (and whose built-in rig names the elbow).
    pub watch: &'a Server,
    /// Their scene.
    pub scene: &'a str,
    /// The websocket URL the driver connects to.
    pub drive_url: String,
    /// Its control token.
    pub token: &'a str,
    /// The avatar driven (of the built-in rig).
    pub avatar: AvatarId,
    /// Watching clients.
    pub clients: usize,
    /// Poses sent (at 120 a second).
    pub poses: usize,
}

/// The latency of every pose some client saw, in the order seen.
///
/// # Errors
/// A client or the driver cannot connect, or the driver is refused.
pub async fn pose_latencies(run: Run<'_>) -> anyhow::Result<Vec<Duration>> {
    let Run {
        watch,
        scene,
        drive_url,
        token,
        avatar,
        clients: count,
        poses,
    } = run;
    let elbow = watch
        .state
        .world
        .library
        .get("avatar")
        .and_then(|r| r.skeleton().find("l_elbow"))
        .ok_or_else(|| anyhow::anyhow!("no l_elbow"))?;
    let sent: Arc<Mutex<Vec<Option<Instant>>>> = Arc::new(Mutex::new(vec![None; poses]));
    let latencies = Arc::new(Mutex::new(Vec::new()));
    let mut clients = Vec::new();
    for _ in 0..count {
        let mut options = ClientOptions::new(watch.ws_url(), scene);
        options.encoding = Encoding::Binary;
        options.reconnect = false;
        let client = Arc::new(Client::connect(options).await?);
        let (sent, latencies, avatar) = (sent.clone(), latencies.clone(), avatar.clone());
        let c = client.clone();
        let mut events = client.events();
        tokio::spawn(async move {
            let mut last = None;
            while let Ok(e) = events.recv().await {
                let Event::Frame { .. } = e else { continue };
                let Some(s) = c.latest(&avatar) else { continue };
                let (axis, angle) = s.locals[elbow].rotation.to_axis_angle();
                let k = (angle * axis.z.signum() / STEP).round();
                if !(k >= 1.0 && (k as usize) < poses) || last == Some(k as usize) {
                    continue;
                }
                last = Some(k as usize);
                let t = sent.lock().map(|s| s[k as usize]).unwrap_or(None);
                if let (Some(t), Ok(mut l)) = (t, latencies.lock()) {
                    l.push(t.elapsed());
                }
            }
        });
        clients.push(client);
    }
    let driver = Driver::connect(&drive_url, Some(token.into())).await?;
    driver.drive(&avatar, None, None).await?;
    let mut interval = tokio::time::interval(Duration::from_secs_f64(1.0 / 120.0));
    for k in 1..poses {
        interval.tick().await;
        let q = Quat::from_rotation_z(k as f32 * STEP);
        if let Ok(mut s) = sent.lock() {
            s[k] = Some(Instant::now());
        }
        driver
            .send_pose(&avatar, [("l_elbow".to_string(), q.to_array())], None, None)
            .await?;
    }
    tokio::time::sleep(Duration::from_millis(300)).await;
    if let Some(e) = driver.next_error(Duration::from_millis(10)).await {
        anyhow::bail!("the driver got an error: {e}");
    }
    // Its drive ends with its connection, before another driver's.
    drop(driver);
    tokio::time::sleep(Duration::from_millis(300)).await;
    drop(clients);
    Ok(latencies.lock().map(|l| l.clone()).unwrap_or_default())
}
