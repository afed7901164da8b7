//! A frame as published: one piece per avatar, so subscribers limited to some avatars get the
//! same bytes reassembled, in either encoding.
//!
//! The binary chunk of every avatar is encoded each tick (every binary subscriber, and the
//! delta encoder's keyframe, need it). The JSON object is not: serialising floats as text costs
//! about a third of a tick, so it is written only while some subscriber uses JSON. Otherwise the
//! piece keeps the pose, and a JSON late joiner served from the cached frames gets its JSON
//! made then ([`Published::ensure_json`]) — the same text the tick would have written.

use axum::extract::ws::{Message, Utf8Bytes};
use bytes::Bytes;
use posecast_proto::description::AvatarDescription;
use posecast_proto::frame::AvatarPose;
use posecast_proto::frame::{
    ChunkEncoder, FrameHeader, FrameKind, HEADER_BYTES, select_chunk, write_header,
};
use posecast_proto::msg::{AvatarId, AvatarPoseJson, Encoding, SceneId};
use posecast_proto::subset::{JointSet, Selection};
use posecast_sim::avatar::Avatar;
use std::borrow::Cow;
use std::collections::HashMap;
use std::sync::Arc;

/// An avatar's pose at a tick, copied under the scene lock (the server's `Scene::tick`):
/// the frame is encoded from it and fanned out after the lock is released, so commands on
/// the scene do not wait for the encoding.
#[derive(Debug, Clone)]
pub struct Snapshot {
    /// The description the pose belongs to (its id, number and hash).
    pub description: Arc<AvatarDescription>,
    /// The pose at the tick.
    pub pose: AvatarPose,
}

impl Snapshot {
    /// The avatar's pose as it is now.
    #[must_use]
    pub fn of(avatar: &Avatar) -> Self {
        Self {
            description: avatar.description.clone(),
            pose: avatar.pose().clone(),
        }
    }

    /// Its avatar's number in binary frames.
    #[must_use]
    pub fn num(&self) -> u32 {
        self.description.num
    }
}

/// One avatar's part of a frame.
#[derive(Debug)]
pub(super) struct Piece {
    /// The description the pose belongs to (its id, number and hash).
    description: Arc<AvatarDescription>,
    pub(super) chunk: Bytes,
    /// The pose the chunk encodes (what its JSON is written from, and what a relay carries).
    pub(super) pose: AvatarPose,
    /// The pose's rotations as the chunk quantised them, when kept for wire v2's levels
    /// (empty: quantise again if needed).
    pub(super) rotation_bits: Vec<u64>,
    /// The pose as JSON, once somebody needed it.
    json: Option<String>,
}

impl Piece {
    /// The avatar's chunk for the frame being ticked, through its own `encoder` (which keeps a
    /// keyframe chunk as the reference for the deltas after it), and its JSON object if `json`.
    /// With `keep_bits` (a wire v2 subscriber will want the tick's levels) the quantised
    /// rotations are kept, so they are not quantised twice.
    pub(super) fn encode(
        snapshot: Snapshot,
        encoder: &mut ChunkEncoder,
        kind: FrameKind,
        json: bool,
        keep_bits: bool,
    ) -> Self {
        let mut chunk = Vec::with_capacity(32 + 6 * snapshot.pose.rotations.len());
        encoder.encode(&snapshot.pose, kind, &mut chunk);
        let mut piece = Self::relayed(
            snapshot.description,
            Bytes::from(chunk),
            snapshot.pose,
            json,
        );
        if keep_bits {
            piece.rotation_bits = encoder.rotation_bits().to_vec();
        }
        piece
    }

    /// A keyframe chunk of the avatar's current pose for one joiner. A fresh encoder, so the
    /// avatar's own — what every other subscriber's deltas refer to — is left alone.
    pub(super) fn fresh_key(a: &mut Avatar, json: bool) -> Self {
        if a.pose().rotations.len() != a.description.joint_names.len() {
            // Added without a clip and not ticked yet: its pose was never evaluated.
            a.evaluate();
        }
        Self::encode(
            Snapshot::of(a),
            &mut ChunkEncoder::new(),
            FrameKind::Key,
            json,
            false,
        )
    }

    /// A piece made elsewhere (by the scene's owner on another server): its description, the
    /// chunk as encoded there and the pose it encodes.
    pub(super) fn relayed(
        description: Arc<AvatarDescription>,
        chunk: Bytes,
        pose: AvatarPose,
        json: bool,
    ) -> Self {
        let json = json.then(|| pose_json(&description, &pose));
        Self {
            description,
            chunk,
            pose,
            rotation_bits: Vec::new(),
            json,
        }
    }

    pub(super) fn id(&self) -> &AvatarId {
        &self.description.id
    }

    /// The rig the pose belongs to.
    pub(super) fn description(&self) -> &Arc<AvatarDescription> {
        &self.description
    }

    fn json(&self) -> Cow<'_, str> {
        match &self.json {
            Some(s) => Cow::Borrowed(s),
            None => Cow::Owned(pose_json(&self.description, &self.pose)),
        }
    }
}

fn pose_json(d: &AvatarDescription, pose: &AvatarPose) -> String {
    pose_json_of(d, pose, None, true)
}

/// The pieces `filter` keeps (all when `None`), each with the part of its rig `joints` selects
/// (`None`: all of it), selected once per rig (its description hash): avatars of one rig
/// share it.
pub(super) fn select<'a>(
    pieces: &'a [Piece],
    filter: Option<&[AvatarId]>,
    joints: Option<&JointSet>,
) -> Vec<(&'a Piece, Option<Arc<Selection>>)> {
    let mut by_rig: HashMap<&str, Option<Arc<Selection>>> = HashMap::new();
    pieces
        .iter()
        .filter(|p| filter.is_none_or(|f| f.contains(p.id())))
        .map(|p| {
            let selection = joints.and_then(|set| {
                by_rig
                    .entry(p.description.hash.as_str())
                    .or_insert_with(|| {
                        Some(set.select(&p.description))
                            .filter(|s| !s.is_all())
                            .map(Arc::new)
                    })
                    .clone()
            });
            (p, selection)
        })
        .collect()
}

/// The JSON object of `pose`, or of the joints `selection` names (listed in it as `joints`),
/// with its morph weights by channel name or (`weights` false) without.
fn pose_json_of(
    d: &AvatarDescription,
    pose: &AvatarPose,
    selection: Option<&Selection>,
    weights: bool,
) -> String {
    let mut json = AvatarPoseJson {
        avatar: d.id.clone(),
        hash: d.hash.clone(),
        rotations: pose.rotations.iter().map(|q| q.to_array()).collect(),
        translations: pose.translations.iter().map(|t| t.to_array()).collect(),
        scales: pose.scales.iter().map(|t| t.to_array()).collect(),
        placement: pose.placement,
        joints: None,
        weights: if weights {
            d.morph_targets
                .iter()
                .cloned()
                .zip(pose.weights.iter().copied())
                .collect()
        } else {
            Default::default()
        },
    };
    if let Some(sel) = selection {
        json.rotations = Selection::pick(&json.rotations, sel.joint_indices());
        json.translations = Selection::pick(&json.translations, sel.translations.iter().copied());
        json.scales = Selection::pick(&json.scales, sel.scales.iter().copied());
        json.joints = Some(sel.joints.clone());
    }
    // Serialising this type cannot fail (strings and float arrays; non-finite floats become
    // null); an empty object keeps the frame valid JSON if that ever changes.
    serde_json::to_string(&json).unwrap_or_else(|_| "{}".into())
}

/// A frame as published.
#[derive(Debug)]
pub(super) struct Published {
    pub(super) header: FrameHeader,
    pub(super) pieces: Vec<Piece>,
}

impl Published {
    /// Writes the JSON objects not written yet (kept for later joiners). Returns how many.
    pub(super) fn ensure_json(&mut self) -> u64 {
        let mut n = 0;
        for p in &mut self.pieces {
            if p.json.is_none() {
                p.json = Some(pose_json(&p.description, &p.pose));
                n += 1;
            }
        }
        n
    }

    /// Whether the frame holds a piece for exactly these avatars (in scene order, the order
    /// pieces are made in) with their current descriptions — and so may be sent to a joiner
    /// who has just received those descriptions. Pieces of avatars `wants` rejects are ignored.
    pub(super) fn covers<'a>(
        &self,
        mut avatars: impl Iterator<Item = &'a Arc<AvatarDescription>>,
        wants: impl Fn(&AvatarId) -> bool,
    ) -> bool {
        let mut pieces = self.pieces.iter().filter(|p| wants(p.id()));
        loop {
            match (avatars.next(), pieces.next()) {
                (None, None) => return true,
                (Some(a), Some(p)) if Arc::ptr_eq(a, &p.description) => {}
                _ => return false,
            }
        }
    }

    /// The frame as one websocket message, with only the avatars `filter` names (all when
    /// `None`) and of each only the joints of `joints` (all when `None`); with `weights`, each
    /// avatar's morph weights too (a binary frame: the v1 chunks flagged as carrying them,
    /// which only WebTransport sessions of protocol version 4 and later get).
    pub(super) fn message(
        &self,
        scene: &SceneId,
        encoding: Encoding,
        filter: Option<&[AvatarId]>,
        joints: Option<&JointSet>,
        weights: bool,
    ) -> Message {
        let selected = select(&self.pieces, filter, joints);
        match encoding {
            Encoding::Binary => {
                let mut body = Vec::new();
                let mut count = 0usize;
                for (p, selection) in &selected {
                    match selection {
                        None => body.extend_from_slice(&p.chunk),
                        // The chunk was made from this description by this server (or the
                        // owner): it fits. Should it not, the avatar is left out of the frame
                        // rather than sent as something the client cannot decode.
                        Some(sel) => {
                            if select_chunk(&p.chunk, self.header.kind, sel, &mut body).is_err() {
                                continue;
                            }
                        }
                    }
                    if weights {
                        posecast_proto::frame::write_weights(&p.pose.weights, &mut body);
                    }
                    count += 1;
                }
                let mut out = Vec::with_capacity(HEADER_BYTES + body.len());
                write_header(
                    &self.header,
                    count.min(usize::from(u16::MAX)) as u16,
                    &mut out,
                );
                if weights {
                    posecast_proto::frame::flag_weights(&mut out);
                }
                out.extend_from_slice(&body);
                Message::Binary(Bytes::from(out))
            }
            Encoding::Json => {
                // Written by hand around pre-serialised avatar objects: the same text as
                // serde_json gives for `ServerMsg::Frame`.
                let scene = serde_json::to_string(scene).unwrap_or_else(|_| "\"\"".into());
                let mut out = format!(
                    r#"{{"type":"frame","scene":{scene},"seq":{},"server_time_us":{},"avatars":["#,
                    self.header.seq, self.header.server_time_us
                );
                for (i, (p, selection)) in selected.iter().enumerate() {
                    if i > 0 {
                        out.push(',');
                    }
                    // Without weights only where there are any to leave out.
                    let bare = !weights && !p.pose.weights.is_empty();
                    match selection {
                        None if !bare => out.push_str(&p.json()),
                        _ => out.push_str(&pose_json_of(
                            &p.description,
                            &p.pose,
                            selection.as_deref(),
                            weights,
                        )),
                    }
                }
                out.push_str("]}");
                Message::Text(Utf8Bytes::from(out))
            }
        }
    }
}
