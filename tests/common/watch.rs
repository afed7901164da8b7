//! A binary (v1) subscriber that keeps every frame it decodes, by avatar id, and comparisons
//! of the poses it saw (the take suites: a replay against what live subscribers received).

use futures_util::StreamExt;
use posecast_proto::frame::{AvatarPose, FrameDecoder};
use posecast_proto::msg::{Encoding, ServerMsg};
use std::collections::{BTreeMap, HashMap};
use std::net::SocketAddr;
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tokio_tungstenite::tungstenite::Message;

/// Bound on every wait (a busy machine): the tests wait for events, never for a duration.
pub const PATIENCE: Duration = Duration::from_secs(120);

/// One decoded frame as a subscriber saw it: its tick, and each avatar's pose by id.
#[derive(Debug, Clone)]
pub struct Seen {
    pub seq: u64,
    pub poses: BTreeMap<String, AvatarPose>,
}

/// A binary (v1) subscriber of a scene, keeping every frame it decodes.
pub struct Watcher {
    frames: Arc<Mutex<Vec<Seen>>>,
    task: tokio::task::JoinHandle<()>,
}

impl Watcher {
    pub async fn start(addr: SocketAddr, scene: &str) -> Self {
        let (mut ws, _) = tokio_tungstenite::connect_async(format!("ws://{addr}/ws"))
            .await
            .unwrap();
        super::hello_and_subscribe(&mut ws, Encoding::Binary, scene, None).await;
        let frames = Arc::new(Mutex::new(Vec::new()));
        let out = frames.clone();
        let task = tokio::spawn(async move {
            let mut ids: HashMap<u32, String> = HashMap::new();
            let mut decoder = FrameDecoder::new();
            while let Some(Ok(msg)) = ws.next().await {
                match msg {
                    Message::Binary(bytes) => {
                        let frame = decoder.decode(&bytes).unwrap();
                        let poses = frame
                            .avatars
                            .into_iter()
                            .map(|p| (ids[&p.avatar_num].clone(), p))
                            .collect();
                        out.lock().unwrap().push(Seen {
                            seq: frame.header.seq,
                            poses,
                        });
                    }
                    Message::Text(t) => {
                        if let Ok(ServerMsg::Description { avatar, .. }) =
                            serde_json::from_str::<ServerMsg>(t.as_str())
                        {
                            ids.insert(avatar.num, avatar.id.0.clone());
                        }
                    }
                    _ => {}
                }
            }
        });
        Self { frames, task }
    }

    /// Stops watching (the frames seen so far stay).
    pub fn stop(&self) {
        self.task.abort();
    }

    pub fn frames(&self) -> Vec<Seen> {
        self.frames.lock().unwrap().clone()
    }

    /// Waits until `done` holds for the frames seen.
    pub async fn until(&self, what: &str, done: impl Fn(&[Seen]) -> bool) {
        let waited = tokio::time::timeout(PATIENCE, async {
            loop {
                if done(&self.frames()) {
                    return;
                }
                tokio::time::sleep(Duration::from_millis(20)).await;
            }
        })
        .await;
        assert!(waited.is_ok(), "waited {PATIENCE:?} for {what}");
    }
}

impl Drop for Watcher {
    fn drop(&mut self) {
        self.task.abort();
    }
}

/// `poses` with the replay's avatar ids (`<scene>.<id>`) back to the take's.
pub fn unprefixed(
    poses: &BTreeMap<String, AvatarPose>,
    scene: &str,
) -> BTreeMap<String, AvatarPose> {
    poses
        .iter()
        .map(|(id, p)| {
            let id = id
                .strip_prefix(&format!("{scene}."))
                .unwrap_or_else(|| panic!("replay avatar {id} is not named after scene {scene}"));
            (id.to_owned(), p.clone())
        })
        .collect()
}

/// The same poses, avatar for avatar: rotations, translations, scales and placement bit for
/// bit (what the frames carried), numbers and hashes aside (the replay's avatars are its own).
pub fn same(a: &BTreeMap<String, AvatarPose>, b: &BTreeMap<String, AvatarPose>) -> bool {
    a.len() == b.len()
        && a.iter().zip(b).all(|((ia, pa), (ib, pb))| {
            ia == ib
                && pa.rotations == pb.rotations
                && pa.translations == pb.translations
                && pa.scales == pb.scales
                && pa.placement == pb.placement
                && pa.weights == pb.weights
        })
}

/// Where in `live` (from `from` on) the poses `poses` are, if they are.
pub fn find(live: &[Seen], from: usize, poses: &BTreeMap<String, AvatarPose>) -> Option<usize> {
    (from..live.len()).find(|&i| same(&live[i].poses, poses))
}
