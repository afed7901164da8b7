//! Scenes driven tick by tick in the test's own thread, and what their subscribers' outboxes
//! hold: for tests of the feed's frames without a websocket in between.

use axum::extract::ws::Message;
use posecast_proto::msg::AvatarId;
use posecast_server::avatar::Avatar;
use posecast_server::avatar::playback::Layer;
use posecast_server::rig::Rig;
use posecast_server::stream::outbox::{Next, Outbox};
use std::sync::Arc;
use std::time::Duration;

/// Every binary message the outbox holds now (after a tick it holds something for a due
/// subscriber; 120 s at most, an event rather than a timing).
pub async fn binary_frames(outbox: &Outbox) -> Vec<Vec<u8>> {
    match tokio::time::timeout(Duration::from_secs(120), outbox.next()).await {
        Ok(Next::Send(messages)) => messages
            .into_iter()
            .filter_map(|m| match m {
                Message::Binary(b) => Some(b.to_vec()),
                _ => None,
            })
            .collect(),
        other => panic!("outbox gave {other:?}"),
    }
}

/// An avatar `id` (number `num`) of `rig` playing its `walk` clip from `start` seconds, looping.
pub fn walking(rig: &Arc<Rig>, id: &str, num: u32, start: f32) -> Avatar {
    let mut avatar = Avatar::new(AvatarId(id.into()), num, rig.clone());
    let walk = rig.clip("walk").unwrap().clone();
    avatar.play(Layer::new(walk, None, start, 1.0, true), 0.0);
    avatar
}
