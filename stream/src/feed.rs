//! A scene's publication: who is subscribed, the frames a late joiner starts from, and the
//! encoding and fan-out of each tick's poses.
//!
//! Every tick the [`Feed`] encodes the frame once per encoding in use (binary always; JSON
//! only while a subscriber wants it) — per avatar pieces first, so subscribers limited to some
//! avatars get the same pieces reassembled — and hands the same bytes to every subscriber's
//! [`Outbox`]. It keeps each avatar's delta encoder (the keyframe its deltas refer to) and the
//! scene's last keyframe and delta for joiners. The poses themselves are the scene's (the
//! server's `scene` module): the feed reads them and never changes what an avatar does.

use super::outbox::{OutFrame, Outbox, flush_all, message_len};
use super::pace;
use super::publish::{Piece, Published, Snapshot};
use super::relay::{self, RelayError, RelayFrame};
use super::take;
use super::wire2::{self, DeltaLayout, Ring};
use crate::Counters;
use axum::extract::ws::{Message, Utf8Bytes};
use bytes::Bytes;
use posecast_core::error::Error;
use posecast_proto::description::AvatarDescription;
use posecast_proto::frame::{ChunkEncoder, FrameHeader, FrameKind};
use posecast_proto::frame2::ReferencedKind;
use posecast_proto::msg::{AvatarId, Encoding, SceneId, ServerMsg};
use posecast_proto::precision::{Grid, GridKey, Precision};
use posecast_proto::subset::JointSet;
use posecast_sim::avatar::Avatar;
use std::collections::HashMap;
use std::sync::Arc;

/// Seconds between the keyframes of a wire v2 subscriber whose chain of deltas continues
/// (every frame decoded exactly as the server holds it). Not a repair of drift, which the
/// integer coding does not have, but a bound on how long a receiver that lost its place (a
/// client's own fault) waits for a frame it can decode.
pub const V2_KEY_SECONDS: f64 = 10.0;

/// A connection subscribed to a scene.
#[derive(Debug)]
pub struct Subscriber {
    /// The connection's id (one subscription per connection and scene).
    pub conn: u64,
    /// Where its messages go.
    pub outbox: Arc<Outbox>,
    /// Binary or JSON frames.
    pub encoding: Encoding,
    /// Only these avatars, or all.
    pub filter: Option<Vec<AvatarId>>,
    /// It gets every `every`-th tick (1: all of them), or fewer while its connection's
    /// adaptive rate ([`crate::pace`]) is lower.
    pub every: u32,
    /// Only these joints of every avatar, or all.
    pub joints: Option<JointSet>,
    /// The tick of the last keyframe it was sent: a wire v1 subscriber that skips ticks may
    /// skip a keyframe, and then gets it before its next delta; a wire v2 one gets the next
    /// keyframe [`V2_KEY_SECONDS`] after it.
    key_sent: Option<u64>,
    /// The protocol version of its connection: binary subscribers of version 2 get wire v2
    /// frames ([`wire2`]).
    pub version: u32,
    /// Its connection's token name (presence); `None`: anonymous.
    pub name: Option<Arc<str>>,
    /// Whether it wants morph weights in its frames (`subscribe`'s `morph_weights`).
    pub morph_weights: bool,
    /// The precision its wire v2 frames are coded at (`None`: the finest).
    pub precision: Option<Precision>,
}

impl Subscriber {
    /// A subscription of connection `conn` getting every `every`-th tick (at least 1).
    #[must_use]
    pub fn new(
        conn: u64,
        outbox: Arc<Outbox>,
        encoding: Encoding,
        filter: Option<Vec<AvatarId>>,
        every: u32,
    ) -> Self {
        Self {
            conn,
            outbox,
            encoding,
            filter,
            every: every.max(1),
            joints: None,
            key_sent: None,
            version: 1,
            name: None,
            morph_weights: true,
            precision: None,
        }
    }

    /// The same subscription with its wire v2 frames coded at `precision` (`None`, or one
    /// no coarser than the finest: the finest).
    #[must_use]
    pub fn with_precision(mut self, precision: Option<Precision>) -> Self {
        self.precision = precision.filter(|p| !p.is_finest());
        self
    }

    /// The grid its wire v2 frames are coded on: its precision, with near-axis steps from
    /// protocol version 6 (`None`: the finest).
    fn grid(&self) -> Option<Grid> {
        self.precision
            .map(|precision| Grid::for_version(precision, self.version))
    }

    /// The same subscription with or without morph weights in its frames.
    #[must_use]
    pub fn with_morph_weights(mut self, wanted: bool) -> Self {
        self.morph_weights = wanted;
        self
    }

    /// The same subscription, made by a connection with token name `name` (presence).
    #[must_use]
    pub fn with_name(mut self, name: Option<&str>) -> Self {
        self.name = name.map(Arc::from);
        self
    }

    /// The same subscription, limited to the joints of `joints` (`None`: every joint).
    #[must_use]
    pub fn with_joints(mut self, joints: Option<JointSet>) -> Self {
        self.joints = joints;
        self
    }

    /// The same subscription on a connection of protocol version `version`.
    #[must_use]
    pub fn with_version(mut self, version: u32) -> Self {
        self.version = version;
        self
    }

    /// Whether it gets wire v2 frames: a binary subscriber of version 2 or later, with a joint
    /// subset from version 3 (v2 frames cut to its joints; version 2 got v1 frames cut to them,
    /// and still does).
    fn v2(&self) -> bool {
        self.encoding == Encoding::Binary
            && (!self.outbox.datagrams() || self.version >= 8)
            && (self.version >= 3 || (self.version == 2 && self.joints.is_none()))
    }

    /// How its wire v2 deltas are laid out: naming the frames they refer to over datagrams
    /// (protocol version 8; predicted over the ticks between from version 9), packed from
    /// protocol version 7, else byte-aligned chunks.
    fn layout(&self) -> DeltaLayout {
        if self.outbox.datagrams() {
            DeltaLayout::Referenced(ReferencedKind::for_version(self.version))
        } else if self.version >= 7 {
            DeltaLayout::Packed
        } else {
            DeltaLayout::Chunks
        }
    }

    /// The keyframe tick its deltas may refer to: the last one sent, or over datagrams the
    /// last one the client acknowledged.
    fn key_held(&self, scene_num: u32) -> Option<u64> {
        if self.outbox.datagrams() {
            self.outbox.key_acked(scene_num)
        } else {
            self.key_sent
        }
    }

    /// Whether its frames carry morph weights: v2 frames from protocol version 4, JSON ones
    /// always — unless the subscription left them out.
    fn weights(&self) -> bool {
        self.morph_weights && (self.encoding == Encoding::Json || self.version >= 4)
    }

    fn wants(&self, avatar: &AvatarId) -> bool {
        self.filter.as_ref().is_none_or(|f| f.contains(avatar))
    }
}

/// The tick a frame belongs to.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct TickStamp {
    /// The tick number.
    pub seq: u64,
    /// Server time of the tick, µs since the Unix epoch.
    pub server_time_us: u64,
}

/// What the scene's owner hands on to other servers through its tap ([`Feed::set_tap`]), in
/// publication order.
#[derive(Debug, Clone)]
pub enum Relayed {
    /// The scene's avatars, in scene order: sent before the first frame and before the first
    /// frame after they change.
    Avatars(Vec<Arc<AvatarDescription>>),
    /// A tick's frame, as bytes for another server ([`relay`]).
    Frame(Bytes),
    /// News of one avatar (`avatar_changed`) for the subscribers covering it.
    Change {
        /// The avatar.
        avatar: AvatarId,
        /// The message as the owner's subscribers got it.
        message: Message,
    },
}

/// Where a tap hands what it relays (called under the scene's lock: it must not block).
#[derive(Clone)]
pub struct Tap(pub Arc<dyn Fn(Relayed) + Send + Sync>);

impl std::fmt::Debug for Tap {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Tap")
    }
}

/// A relayed frame the feed could not take.
#[derive(Debug, thiserror::Error)]
pub enum RelayRefused {
    /// The bytes are not a relayed frame.
    #[error(transparent)]
    Unreadable(#[from] RelayError),
    /// The feed is not a relay (its scene is ticked here).
    #[error("scene is ticked here, not relayed")]
    NotRelay,
    /// The frame names an avatar whose description has not arrived.
    #[error("frame names avatar {0}, whose description has not arrived")]
    UnknownAvatar(AvatarId),
    /// The frame belongs to another scene number.
    #[error("frame of scene number {got}, this scene is number {expected}")]
    SceneNum {
        /// This scene's number.
        expected: u32,
        /// The frame's.
        got: u32,
    },
}

/// What a frame message is made for: an encoding, an avatar filter and a joint set.
/// (encoding, avatar filter, joint subset, with morph weights)
type Cut<'a> = (Encoding, Option<&'a [AvatarId]>, Option<&'a JointSet>, bool);

/// One scene's subscribers and the frame state they share (kept under the scene's lock, next
/// to the avatars, so a joiner's first frames and the next tick are in order).
#[derive(Debug)]
pub struct Feed {
    scene: SceneId,
    num: u32,
    metrics: Arc<dyn Counters>,
    /// Ticks per second (what a subscription's rate divides).
    tick_rate: f32,
    subscribers: Vec<Subscriber>,
    /// Each avatar's delta encoder, by avatar number.
    encoders: HashMap<u32, ChunkEncoder>,
    last_key_seq: Option<u64>,
    force_key: bool,
    last_key: Option<Published>,
    last_delta: Option<Published>,
    /// Each avatar's description message, serialised once and shared by every subscriber.
    descriptions: HashMap<AvatarId, (Arc<AvatarDescription>, Message)>,
    /// An avatar was placed since the last tick: the cached frames show the old placement.
    placed: bool,
    /// Where each tick is handed on to other servers, if anywhere.
    tap: Option<Tap>,
    /// The descriptions the tap last handed on.
    tapped: Vec<Arc<AvatarDescription>>,
    /// `Some` while the feed relays a scene ticked elsewhere: that scene's avatars.
    relay: Option<Vec<Arc<AvatarDescription>>>,
    /// Recent ticks as levels, while some subscriber gets wire v2.
    ring: Ring,
    /// The take being recorded, if any ([`Feed::record`]).
    take: Option<TakeRecording>,
}

/// Where a take of the scene (`record_scene`) gets its records: each frame as the feed encoded
/// it for binary subscribers, and the avatars' descriptions when they change, already framed
/// as take records ([`crate::take`]). Called under the feed's lock: it must not block (hand
/// the bytes to a writer).
pub trait TakeSink: Send + std::fmt::Debug {
    /// The records of tick `seq`'s frame (after an avatars record when `avatars`, the scene's
    /// avatars now, changed). `false`: stop recording (a limit was reached, or the writer
    /// failed); the feed drops the sink.
    fn append(
        &mut self,
        records: Vec<u8>,
        seq: u64,
        avatars: Option<&[Arc<AvatarDescription>]>,
    ) -> bool;

    /// An event record (who drives which avatar changed), before the next frame's records.
    /// `false`: stop recording, as for [`TakeSink::append`].
    fn append_event(&mut self, record: Vec<u8>) -> bool;
}

/// Who drives an avatar live, as a take notes it: the driver's name and how it drives.
pub type DriverNote = (AvatarId, posecast_proto::command::Driver);

#[derive(Debug)]
struct TakeRecording {
    sink: Box<dyn TakeSink>,
    /// The descriptions last written to it.
    avatars: Vec<Arc<AvatarDescription>>,
    /// The drivers last written to it.
    drivers: Vec<DriverNote>,
}

impl TakeRecording {
    /// Appends `frame` (after the avatars' descriptions, if they changed). Whether to go on.
    fn frame(&mut self, frame: &Published) -> bool {
        let mut records = Vec::with_capacity(
            64 + frame
                .pieces
                .iter()
                .map(|p| 16 + p.chunk.len() + 2 * p.pose.weights.len())
                .sum::<usize>(),
        );
        let same = self.avatars.len() == frame.pieces.len()
            && self
                .avatars
                .iter()
                .zip(&frame.pieces)
                .all(|(a, p)| Arc::ptr_eq(a, p.description()));
        if !same {
            self.avatars = frame
                .pieces
                .iter()
                .map(|p| p.description().clone())
                .collect();
            let list: Vec<&AvatarDescription> = self.avatars.iter().map(|a| &**a).collect();
            take::write_avatars(&list, &mut records);
        }
        let changed = (!same).then_some(self.avatars.as_slice());
        take::write_frame(
            &frame.header,
            frame.pieces.iter().map(|p| {
                (
                    p.pose.avatar_num,
                    p.chunk.as_ref(),
                    p.pose.weights.as_slice(),
                )
            }),
            &mut records,
        );
        self.sink.append(records, frame.header.seq, changed)
    }
}

impl Feed {
    /// The feed of scene `scene` (number `num` in binary frames) ticking at `tick_rate`, with
    /// no subscribers.
    #[must_use]
    pub fn new(scene: SceneId, num: u32, metrics: Arc<dyn Counters>, tick_rate: f32) -> Self {
        Self {
            scene,
            num,
            metrics,
            tick_rate,
            subscribers: Vec::new(),
            encoders: HashMap::new(),
            last_key_seq: None,
            force_key: true,
            last_key: None,
            last_delta: None,
            descriptions: HashMap::new(),
            placed: false,
            tap: None,
            tapped: Vec::new(),
            relay: None,
            ring: Ring::default(),
            take: None,
        }
    }

    /// Starts recording a take into `sink` (`None`: stops, dropping the sink). Its first
    /// frame is a keyframe, so the take decodes from its start. Returns the sink recording
    /// until now, if any.
    pub fn record(&mut self, sink: Option<Box<dyn TakeSink>>) -> Option<Box<dyn TakeSink>> {
        if sink.is_some() {
            self.force_key = true;
        }
        let before = self.take.take().map(|t| t.sink);
        self.take = sink.map(|sink| TakeRecording {
            sink,
            avatars: Vec::new(),
            drivers: Vec::new(),
        });
        before
    }

    /// While a take is recorded: who drives which avatar now (scene order). When that changed
    /// since the take last noted it, the take gets an event
    /// `{"drivers": [{"avatar", "name", "via"}, …]}` before the next frame.
    pub fn note_drivers(&mut self, drivers: Vec<DriverNote>) {
        let Some(take) = &mut self.take else { return };
        if take.drivers == drivers {
            return;
        }
        let list: Vec<serde_json::Value> = drivers
            .iter()
            .map(
                |(avatar, d)| serde_json::json!({ "avatar": avatar, "name": d.name, "via": d.via }),
            )
            .collect();
        let mut record = Vec::new();
        take::write_event(&serde_json::json!({ "drivers": list }), &mut record);
        take.drivers = drivers;
        if !take.sink.append_event(record) {
            self.take = None;
        }
    }

    /// Whether a take is being recorded.
    #[must_use]
    pub fn is_recording(&self) -> bool {
        self.take.is_some()
    }

    /// Hands every tick's frame, and the avatars' descriptions when they change, to `tap`
    /// (`None`: to nobody). A new tap starts with the descriptions and a keyframe: a relay
    /// fed by it has none of the frames before (a scene taken over may tick a while before its
    /// tap is set, and its first keyframe would otherwise reach no relay).
    pub fn set_tap(&mut self, tap: Option<Tap>) {
        if tap.is_some() {
            self.force_key = true;
        }
        self.tap = tap;
        self.tapped.clear();
    }

    /// Hands the tap the avatars' descriptions if they changed since it last had them (called
    /// when avatars come and go, so news of an avatar never reaches a relay before its
    /// description, and before each frame).
    pub fn tap_avatars<'a, I>(&mut self, descriptions: I)
    where
        I: IntoIterator<Item = &'a Arc<AvatarDescription>>,
        I::IntoIter: ExactSizeIterator + Clone,
    {
        let Some(tap) = &self.tap else { return };
        let descriptions = descriptions.into_iter();
        let same = self.tapped.len() == descriptions.len()
            && self
                .tapped
                .iter()
                .zip(descriptions.clone())
                .all(|(t, d)| Arc::ptr_eq(t, d));
        if !same {
            self.tapped = descriptions.cloned().collect();
            (tap.0)(Relayed::Avatars(self.tapped.clone()));
        }
    }

    /// The last keyframe and the newest delta after it, relayed-frame bytes ([`relay`]), for a
    /// server that starts relaying the scene.
    #[must_use]
    pub fn cached_frames(&self) -> Vec<Bytes> {
        self.last_key
            .iter()
            .chain(self.last_delta.iter())
            .map(relay::encode)
            .collect()
    }

    /// Whether the feed relays frames made elsewhere rather than publishing ticks.
    #[must_use]
    pub fn is_relay(&self) -> bool {
        self.relay.is_some()
    }

    /// The relayed avatars' descriptions (empty unless a relay).
    #[must_use]
    pub fn relayed_avatars(&self) -> &[Arc<AvatarDescription>] {
        self.relay.as_deref().unwrap_or(&[])
    }

    /// Makes the feed a relay of a scene ticked elsewhere, whose subscribers hold the
    /// descriptions of `avatars` (none for a new relay); its cached frames are dropped (they
    /// came from ticks here).
    pub fn begin_relay(&mut self, avatars: Vec<Arc<AvatarDescription>>) {
        self.relay = Some(avatars);
        self.tap = None;
        self.restart_frames();
    }

    /// The scene is ticked here again: the next frame is a keyframe, and joiners wait for it.
    /// Descriptions stay cached, so avatars restored as they were are not described twice.
    pub fn end_relay(&mut self) {
        self.relay = None;
        self.restart_frames();
    }

    /// Forgets every frame: a new source of frames begins (a new owner, or ticks here), whose
    /// first frame is a keyframe. Subscribers keep their subscriptions.
    pub fn restart_frames(&mut self) {
        self.last_key = None;
        self.last_delta = None;
        self.last_key_seq = None;
        self.force_key = true;
        self.encoders.clear();
        self.ring.clear();
        for sub in &mut self.subscribers {
            sub.key_sent = None;
            sub.outbox.clear_scene(self.num);
        }
    }

    /// A relay's avatars are now `avatars` (in scene order): subscribers covering a new or
    /// changed one get its description, those covering a gone one `avatar_removed`. Returns
    /// the avatars gone, each with the connections told.
    pub fn relay_avatars(&mut self, avatars: Vec<AvatarDescription>) -> Vec<(AvatarId, Vec<u64>)> {
        let Some(old) = self.relay.take() else {
            return Vec::new();
        };
        let mut removed = Vec::new();
        let mut new = Vec::with_capacity(avatars.len());
        for d in avatars {
            if let Some(kept) = old.iter().find(|o| o.id == d.id && ***o == d) {
                new.push(kept.clone());
                continue;
            }
            let d = Arc::new(d);
            let msg = description_message(&self.scene, &mut self.descriptions, &d);
            for sub in self.subscribers.iter().filter(|sub| sub.wants(&d.id)) {
                sub.outbox.push_control(msg.clone());
            }
            new.push(d);
        }
        for gone in old.iter().filter(|o| !new.iter().any(|n| n.id == o.id)) {
            self.descriptions.remove(&gone.id);
            let msg = text(&ServerMsg::AvatarRemoved {
                scene: self.scene.clone(),
                avatar: gone.id.clone(),
            });
            let mut told = Vec::new();
            for sub in self.subscribers.iter().filter(|sub| sub.wants(&gone.id)) {
                sub.outbox.push_control(msg.clone());
                told.push(sub.conn);
            }
            removed.push((gone.id.clone(), told));
        }
        self.relay = Some(new);
        removed
    }

    /// Fans out a frame the scene's owner published ([`relay::decode`]), as [`Feed::publish`]
    /// does a tick's: the same bytes, the same outbox rules.
    ///
    /// # Errors
    /// The bytes are unreadable, of another scene, or name an avatar not described yet; or
    /// the feed is not a relay. Nothing is sent then.
    pub fn relay_frame(&mut self, bytes: &[u8]) -> Result<(), RelayRefused> {
        let RelayFrame { header, pieces } = relay::decode(bytes)?;
        let Some(avatars) = &self.relay else {
            return Err(RelayRefused::NotRelay);
        };
        if header.scene_num != self.num {
            return Err(RelayRefused::SceneNum {
                expected: self.num,
                got: header.scene_num,
            });
        }
        let json = self
            .subscribers
            .iter()
            .any(|sub| sub.encoding == Encoding::Json);
        let pieces = pieces
            .into_iter()
            .map(|p| {
                let d = avatars
                    .iter()
                    .find(|d| d.id == p.avatar)
                    .ok_or_else(|| RelayRefused::UnknownAvatar(p.avatar.clone()))?;
                Ok(Piece::relayed(d.clone(), p.chunk, p.pose, json))
            })
            .collect::<Result<Vec<Piece>, RelayRefused>>()?;
        if json {
            self.metrics.json_encoded(pieces.len() as u64);
        }
        let key = header.kind == FrameKind::Key;
        self.fan_out(Published { header, pieces }, key);
        Ok(())
    }

    /// Who is subscribed, by token name (presence): the names with the most connections first,
    /// at most [`posecast_proto::command::MAX_VIEWER_NAMES`]; anonymous connections and the
    /// names beyond the limit count under `name: None`, last.
    #[must_use]
    pub fn viewers(&self) -> Vec<posecast_proto::command::Viewer> {
        use posecast_proto::command::{MAX_VIEWER_NAMES, Viewer};
        let mut by_name: std::collections::BTreeMap<Option<&str>, u32> =
            std::collections::BTreeMap::new();
        for s in &self.subscribers {
            *by_name.entry(s.name.as_deref()).or_default() += 1;
        }
        let anonymous = by_name.remove(&None).unwrap_or(0);
        let mut named: Vec<(&str, u32)> = by_name
            .into_iter()
            .filter_map(|(n, c)| n.map(|n| (n, c)))
            .collect();
        named.sort_by(|a, b| b.1.cmp(&a.1).then(a.0.cmp(b.0)));
        let rest: u32 = named.iter().skip(MAX_VIEWER_NAMES).map(|(_, c)| c).sum();
        let mut viewers: Vec<Viewer> = named
            .into_iter()
            .take(MAX_VIEWER_NAMES)
            .map(|(n, c)| Viewer {
                name: Some(n.to_owned()),
                connections: c,
            })
            .collect();
        if anonymous + rest > 0 {
            viewers.push(Viewer {
                name: None,
                connections: anonymous + rest,
            });
        }
        viewers
    }

    /// Number of subscribers.
    #[must_use]
    pub fn len(&self) -> usize {
        self.subscribers.len()
    }

    /// Whether nobody is subscribed.
    #[must_use]
    pub fn is_empty(&self) -> bool {
        self.subscribers.is_empty()
    }

    /// An avatar joined the scene: subscribers covering it get its description, and the next
    /// frame is a keyframe.
    pub fn avatar_added(&mut self, avatar: &Avatar) {
        // A relay that becomes the owner restores the avatars its subscribers were already
        // told about: the same description is not sent twice.
        let known = self
            .descriptions
            .get(&avatar.id)
            .is_some_and(|(d, _)| **d == *avatar.description);
        let msg = description_message(&self.scene, &mut self.descriptions, &avatar.description);
        if !known {
            for sub in self.subscribers.iter().filter(|sub| sub.wants(&avatar.id)) {
                sub.outbox.push_control(msg.clone());
            }
        }
        self.encoders.insert(avatar.num(), ChunkEncoder::new());
        self.force_key = true;
    }

    /// An avatar left the scene: subscribers covering it are told, and the next frame is a
    /// keyframe.
    pub fn avatar_removed(&mut self, avatar: &Avatar) {
        self.descriptions.remove(&avatar.id);
        self.encoders.remove(&avatar.num());
        let msg = text(&ServerMsg::AvatarRemoved {
            scene: self.scene.clone(),
            avatar: avatar.id.clone(),
        });
        for sub in self.subscribers.iter().filter(|sub| sub.wants(&avatar.id)) {
            sub.outbox.push_control(msg.clone());
        }
        self.force_key = true;
    }

    /// Hands `message` — news of avatar `avatar` (`avatar_changed`) — to every subscriber
    /// covering it. Returns their connections (each told once, whoever else tells others).
    pub fn push_change(&self, avatar: &AvatarId, message: &Message) -> Vec<u64> {
        if let Some(tap) = &self.tap {
            (tap.0)(Relayed::Change {
                avatar: avatar.clone(),
                message: message.clone(),
            });
        }
        self.subscribers
            .iter()
            .filter(|sub| sub.wants(avatar))
            .map(|sub| {
                sub.outbox.push_control(message.clone());
                sub.conn
            })
            .collect()
    }

    /// Sends `message` to every subscriber (a change of the whole scene, such as who watches
    /// it); returns the connections told.
    pub fn push_to_all(&self, message: &Message) -> Vec<u64> {
        self.subscribers
            .iter()
            .map(|sub| {
                sub.outbox.push_control(message.clone());
                sub.conn
            })
            .collect()
    }

    /// The connections whose subscription covers `avatar` (the ones [`Feed::avatar_removed`]
    /// and [`Feed::push_change`] reach).
    #[must_use]
    pub fn covering(&self, avatar: &AvatarId) -> Vec<u64> {
        self.subscribers
            .iter()
            .filter(|sub| sub.wants(avatar))
            .map(|sub| sub.conn)
            .collect()
    }

    /// Notes that an avatar was placed: until the next tick, joiners get a keyframe made from
    /// the current poses rather than the cached one, and the next tick is a keyframe, so the
    /// cached keyframe a later joiner gets first already shows the new placement (not only the
    /// delta after it).
    pub fn placed(&mut self) {
        self.placed = true;
        self.force_key = true;
    }

    /// Subscribes a connection (replacing its previous subscription to this scene). It gets,
    /// in order: `subscribed`, every covered avatar's description, then at once a keyframe
    /// holding every one of them — the current pose, before the next tick: the cached last
    /// keyframe and the newest delta after it, or, when avatars were added, removed or
    /// changed since that keyframe, one made now from their current poses, labelled `last`.
    /// (Before the scene's first tick there is none; that tick is a keyframe of every avatar.)
    ///
    /// # Errors
    /// `unknown_avatar` when the filter names an avatar not in `avatars`.
    pub fn subscribe(
        &mut self,
        avatars: &mut [Avatar],
        last: TickStamp,
        mut sub: Subscriber,
    ) -> Result<(), Error> {
        let described: Vec<Arc<AvatarDescription>> = match &self.relay {
            Some(relayed) => relayed.clone(),
            None => avatars.iter().map(|a| a.description.clone()).collect(),
        };
        if let Some(filter) = &sub.filter
            && let Some(missing) = filter
                .iter()
                .find(|id| !described.iter().any(|d| &d.id == *id))
        {
            return Err(Error::NotInScene {
                scene: self.scene.clone(),
                avatar: (*missing).clone(),
            });
        }
        self.subscribers.retain(|old| old.conn != sub.conn);
        sub.outbox.clear_scene(self.num);
        sub.outbox.push_control(text(&ServerMsg::Subscribed {
            scene: self.scene.clone(),
            scene_num: self.num,
            rate: Some(self.tick_rate / sub.every as f32),
            joints: sub.joints.clone(),
            precision: sub.precision,
        }));
        // Exempt from the outbox's stall bound: a scene of many avatars is not a slow client.
        let descriptions: Vec<Message> = described
            .iter()
            .filter(|d| sub.wants(&d.id))
            .map(|d| description_message(&self.scene, &mut self.descriptions, d))
            .collect();
        sub.outbox.push_snapshot(self.num, descriptions);
        sub.key_sent = self.first_frames(avatars, &described, last, &sub);
        self.subscribers.push(sub);
        Ok(())
    }

    /// Hands a new subscriber its first frames (see [`Feed::subscribe`]). Returns the tick of
    /// the scene's keyframe when the subscriber got it (its later deltas can refer to it).
    fn first_frames(
        &mut self,
        avatars: &mut [Avatar],
        described: &[Arc<AvatarDescription>],
        last: TickStamp,
        sub: &Subscriber,
    ) -> Option<u64> {
        let filter = sub.filter.as_deref();
        let joints = sub.joints.as_ref();
        if sub.v2() {
            return self.first_frames_v2(avatars, described, last, sub);
        }
        let json = sub.encoding == Encoding::Json;
        let key = self.last_key.as_mut()?;
        let wanted = described.iter().filter(|d| sub.wants(&d.id));
        if !self.placed && key.covers(wanted, |id| sub.wants(id)) {
            if json {
                let mut made = key.ensure_json();
                made += self.last_delta.as_mut().map_or(0, Published::ensure_json);
                self.metrics.json_encoded(made);
            }
            let message = key.message(&self.scene, sub.encoding, filter, joints, sub.weights());
            sub.outbox
                .push_frame(self.num, OutFrame { message, key: true });
            if let Some(delta) = &self.last_delta {
                let message =
                    delta.message(&self.scene, sub.encoding, filter, joints, sub.weights());
                sub.outbox.push_frame(
                    self.num,
                    OutFrame {
                        message,
                        key: false,
                    },
                );
            }
            return self.last_key_seq;
        }
        if self.relay.is_some() {
            // No poses here to make a keyframe from: the owner's next frame is one (it forces
            // a keyframe whenever its avatars change).
            return None;
        }
        // The cached keyframe predates a change of avatars: a keyframe of the current poses, for
        // this subscriber only, labelled with the last tick.
        let pieces: Vec<Piece> = avatars
            .iter_mut()
            .filter(|a| sub.wants(&a.id))
            .map(|a| Piece::fresh_key(a, json))
            .collect();
        if json {
            self.metrics.json_encoded(pieces.len() as u64);
        } else {
            // The next tick's deltas would refer to the scene's keyframe, which this subscriber
            // never got: make the next tick a keyframe. (A change of avatars already forces one;
            // this keeps it so whatever the reason the cache was stale.)
            self.force_key = true;
        }
        let fresh = Published {
            header: FrameHeader {
                kind: FrameKind::Key,
                scene_num: self.num,
                seq: last.seq,
                server_time_us: last.server_time_us,
                base_seq: last.seq,
            },
            pieces,
        };
        let message = fresh.message(&self.scene, sub.encoding, filter, joints, sub.weights());
        sub.outbox
            .push_frame(self.num, OutFrame { message, key: true });
        // A keyframe of its own: the scene's next deltas do not refer to it (and a full-rate
        // binary subscriber's next tick is a keyframe, forced above).
        None
    }

    /// [`Feed::first_frames`] for a wire v2 subscriber: a v2 keyframe of the newest cached
    /// frame, which starts its chain (later deltas refer to it), or, when the cache predates a
    /// change of avatars, of the current poses, labelled `last`, after which its next frame is
    /// a keyframe (the scene's frames do not continue from those poses). Returns the tick of
    /// the keyframe that starts its chain, if one does.
    fn first_frames_v2(
        &mut self,
        avatars: &mut [Avatar],
        described: &[Arc<AvatarDescription>],
        last: TickStamp,
        sub: &Subscriber,
    ) -> Option<u64> {
        let filter = sub.filter.as_deref();
        let joints = sub.joints.as_ref();
        let wanted = described.iter().filter(|d| sub.wants(&d.id));
        let covered = !self.placed
            && self
                .last_key
                .as_ref()
                .is_some_and(|k| k.covers(wanted, |id| sub.wants(id)));
        if covered {
            let newest = self.last_delta.as_ref().or(self.last_key.as_ref())?;
            let now = self.ring.record(newest);
            if let Some(message) = self.ring.message(
                newest,
                &now,
                None,
                filter,
                joints,
                sub.weights(),
                sub.grid().as_ref(),
                sub.layout(),
            ) {
                sub.outbox.push_chained(
                    self.num,
                    OutFrame { message, key: true },
                    newest.header.seq,
                    None,
                );
                return Some(newest.header.seq);
            }
            return None;
        }
        if self.relay.is_some() || sub.outbox.datagrams() {
            // The owner's next frame is a keyframe; until then there are no poses here. Over
            // datagrams the next tick's keyframe is the first frame: a fresh one, labelled
            // with a tick whose levels it does not have, would be acknowledged, and a delta
            // naming it would not decode to the scene's poses.
            sub.outbox.break_chain(self.num);
            return None;
        }
        let pieces: Vec<Piece> = avatars
            .iter_mut()
            .filter(|a| sub.wants(&a.id))
            .map(|a| Piece::fresh_key(a, false))
            .collect();
        let fresh = Published {
            header: FrameHeader {
                kind: FrameKind::Key,
                scene_num: self.num,
                seq: last.seq,
                server_time_us: last.server_time_us,
                base_seq: last.seq,
            },
            pieces,
        };
        let now = wire2::levels(&fresh);
        if let Some(message) = self.ring.message(
            &fresh,
            &now,
            None,
            filter,
            joints,
            sub.weights(),
            sub.grid().as_ref(),
            DeltaLayout::Chunks,
        ) {
            sub.outbox
                .push_frame(self.num, OutFrame { message, key: true });
        }
        sub.outbox.break_chain(self.num);
        None
    }

    /// Ends a connection's subscription. Returns whether it had one.
    pub fn unsubscribe(&mut self, conn: u64) -> bool {
        let before = self.subscribers.len();
        let num = self.num;
        self.subscribers.retain(|sub| {
            if sub.conn == conn {
                sub.outbox.clear_scene(num);
            }
            sub.conn != conn
        });
        before != self.subscribers.len()
    }

    /// Ends every subscription (the scene is deleted or the server stops).
    pub fn close(&mut self) {
        let msg = text(&ServerMsg::Unsubscribed {
            scene: self.scene.clone(),
        });
        for sub in self.subscribers.drain(..) {
            sub.outbox.clear_scene(self.num);
            sub.outbox.push_control(msg.clone());
        }
    }

    /// Publishes tick `at`: the avatars' poses at it, copied under the scene lock
    /// ([`Snapshot::of`]). Encodes the frame once per encoding and offers it to every
    /// subscriber. A keyframe when forced (an avatar added or removed, a joiner who missed the
    /// keyframe) or when `key_interval` ticks have passed since the last one.
    pub fn publish(&mut self, snapshots: Vec<Snapshot>, at: TickStamp, key_interval: u64) {
        self.placed = false;
        let key = self.force_key
            || self
                .last_key_seq
                .is_none_or(|k| at.seq.saturating_sub(k) >= key_interval)
            || snapshots.iter().any(|a| {
                !self
                    .encoders
                    .get(&a.num())
                    .is_some_and(|e| e.has_key(a.pose.rotations.len()))
            });
        let kind = if key {
            FrameKind::Key
        } else {
            FrameKind::Delta
        };
        let header = FrameHeader {
            kind,
            scene_num: self.num,
            seq: at.seq,
            server_time_us: at.server_time_us,
            base_seq: if key {
                at.seq
            } else {
                self.last_key_seq.unwrap_or(at.seq)
            },
        };
        // JSON only while someone reads it; a JSON late joiner gets it made from the cached
        // poses (`first_frames`).
        let json = self
            .subscribers
            .iter()
            .any(|sub| sub.encoding == Encoding::Json);
        self.tap_avatars(snapshots.iter().map(|a| &a.description));
        let v2 = self.subscribers.iter().any(Subscriber::v2);
        let pieces: Vec<Piece> = snapshots
            .into_iter()
            .map(|a| {
                let encoder = self.encoders.entry(a.num()).or_default();
                Piece::encode(a, encoder, kind, json, v2)
            })
            .collect();
        if json {
            self.metrics.json_encoded(pieces.len() as u64);
        }
        let published = Published { header, pieces };
        if let Some(take) = &mut self.take
            && !take.frame(&published)
        {
            self.take = None;
        }
        if let Some(tap) = &self.tap {
            (tap.0)(Relayed::Frame(relay::encode(&published)));
        }
        self.fan_out(published, key);
    }

    /// Offers a frame to every subscriber due for it (a subscriber that skipped the keyframe
    /// its deltas refer to gets that first), then keeps it for joiners.
    fn fan_out(&mut self, published: Published, key: bool) {
        let at = TickStamp {
            seq: published.header.seq,
            server_time_us: published.header.server_time_us,
        };
        // Encode once per (encoding, filter, joint set); with no filters and no joint sets
        // that is once per encoding.
        let mut cache: HashMap<Cut<'_>, Message> = HashMap::new();
        // The scene's keyframe, for subscribers at a lower rate that skipped its tick.
        let mut key_cache: HashMap<Cut<'_>, Message> = HashMap::new();
        let mut bytes_out = 0u64;
        let mut offered = 0u64;
        let mut pushed: Vec<Arc<Outbox>> = Vec::with_capacity(self.subscribers.len());
        // Wire v2: the tick's levels, and its frames by the chain they continue (`None`: the
        // keyframe), filter and joint set — each made at most once.
        let levels = if self.subscribers.iter().any(Subscriber::v2) {
            Some(self.ring.record(&published))
        } else {
            self.ring.clear();
            None
        };
        // (chain, avatar filter, joint subset, with morph weights, precision, delta layout)
        type V2Key<'a> = (
            Option<Vec<u64>>,
            Option<&'a [AvatarId]>,
            Option<&'a JointSet>,
            bool,
            Option<GridKey>,
            DeltaLayout,
        );
        let mut v2_cache: HashMap<V2Key<'_>, Option<Message>> = HashMap::new();
        // Ticks between a wire v2 chain's keyframes.
        let v2_refresh = (f64::from(self.tick_rate) * V2_KEY_SECONDS).ceil().max(1.0) as u64;
        let v2_late = f64::from(self.tick_rate).ceil().max(1.0) as u64;
        for sub in &mut self.subscribers {
            // The connection's adaptive rate may be lower than the subscription's; paced
            // connections are staggered by their id, so they do not all send on one tick.
            let paced = sub.outbox.pace().rate();
            let due = if u64::from(paced) * u64::from(sub.every) < 60 {
                pace::sends(paced, at.seq, sub.conn)
            } else {
                at.seq.is_multiple_of(u64::from(sub.every))
            };
            if !due {
                continue;
            }
            let filter = sub.filter.as_deref();
            let joints = sub.joints.as_ref();
            let weights = sub.weights();
            if sub.v2() {
                let on = sub.grid();
                let precision = on.as_ref();
                let grid = precision.map(Grid::key);
                let layout = sub.layout();
                let Some(levels) = &levels else { continue };
                let ring = &self.ring;
                if matches!(layout, DeltaLayout::Referenced(_)) {
                    // Over datagrams (protocol version 8) a delta names the newest frames the
                    // client acknowledged whole, so a lost datagram costs its own tick; with
                    // none (it just joined, nothing came back for a while, a new avatar or
                    // rig) the tick's keyframe goes — unless one is on its way.
                    let refs = sub.outbox.datagram_refs(self.num, at.seq);
                    let delta = (!refs.is_empty())
                        .then(|| {
                            v2_cache
                                .entry((Some(refs.clone()), filter, joints, weights, grid, layout))
                                .or_insert_with(|| {
                                    ring.message(
                                        &published,
                                        levels,
                                        Some(&refs),
                                        filter,
                                        joints,
                                        weights,
                                        precision,
                                        layout,
                                    )
                                })
                                .clone()
                        })
                        .flatten();
                    let frame = match delta {
                        Some(message) => OutFrame {
                            message,
                            key: false,
                        },
                        None if sub.outbox.datagram_key_due(self.num) => {
                            let Some(message) = v2_cache
                                .entry((None, filter, joints, weights, grid, DeltaLayout::Chunks))
                                .or_insert_with(|| {
                                    ring.message(
                                        &published,
                                        levels,
                                        None,
                                        filter,
                                        joints,
                                        weights,
                                        precision,
                                        DeltaLayout::Chunks,
                                    )
                                })
                                .clone()
                            else {
                                continue;
                            };
                            sub.key_sent = Some(at.seq);
                            OutFrame { message, key: true }
                        }
                        None => continue,
                    };
                    bytes_out += message_len(&frame.message) as u64;
                    sub.outbox.push_frame_later(self.num, frame);
                    pushed.push(sub.outbox.clone());
                    offered += 1;
                    continue;
                }
                // A delta continues the frames the subscriber will hold (without the pending
                // delta it replaces, for a client that does not keep up); none (it just
                // joined, the rate changed the ticks it got: anything not in the ring, a new
                // avatar or rig) or a keyframe tick [`V2_KEY_SECONDS`] after its last
                // keyframe: the tick's shared keyframe. The scene's other keyframes (once a
                // second, for wire v1 and joiners) are not sent to a chain that continues:
                // its receiver decodes exactly the levels the server holds, so a keyframe
                // would repair nothing and cost 5 % of the stream.
                // (A reader at a lower rate whose ticks miss the scene's keyframe ticks gets
                // its own a second later.)
                let age = sub.key_sent.map_or(u64::MAX, |k| at.seq.saturating_sub(k));
                let refresh = (key && age >= v2_refresh) || age >= v2_refresh + v2_late;
                let chain = (!refresh).then(|| sub.outbox.chain(self.num)).flatten();
                let replacing = chain.as_ref().and_then(|c| c.replacing);
                let delta = chain.and_then(|chain| {
                    v2_cache
                        .entry((
                            Some(chain.ticks.clone()),
                            filter,
                            joints,
                            weights,
                            grid,
                            layout,
                        ))
                        .or_insert_with(|| {
                            ring.message(
                                &published,
                                levels,
                                Some(&chain.ticks),
                                filter,
                                joints,
                                weights,
                                precision,
                                layout,
                            )
                        })
                        .clone()
                });
                let (frame, replacing) = match delta {
                    Some(message) => (
                        OutFrame {
                            message,
                            key: false,
                        },
                        replacing,
                    ),
                    None => {
                        let Some(message) = v2_cache
                            // A keyframe is the same whatever the deltas' layout.
                            .entry((None, filter, joints, weights, grid, DeltaLayout::Chunks))
                            .or_insert_with(|| {
                                ring.message(
                                    &published,
                                    levels,
                                    None,
                                    filter,
                                    joints,
                                    weights,
                                    precision,
                                    DeltaLayout::Chunks,
                                )
                            })
                            .clone()
                        else {
                            continue;
                        };
                        sub.key_sent = Some(at.seq);
                        (OutFrame { message, key: true }, None)
                    }
                };
                bytes_out += message_len(&frame.message) as u64;
                sub.outbox
                    .push_chained_later(self.num, frame, at.seq, replacing);
                pushed.push(sub.outbox.clone());
                offered += 1;
                continue;
            }
            if !key && sub.key_held(self.num) != self.last_key_seq {
                let Some(last_key) = &mut self.last_key else {
                    continue;
                };
                if sub.encoding == Encoding::Json {
                    self.metrics.json_encoded(last_key.ensure_json());
                }
                let message = key_cache
                    .entry((sub.encoding, filter, joints, weights))
                    .or_insert_with(|| {
                        last_key.message(&self.scene, sub.encoding, filter, joints, weights)
                    })
                    .clone();
                bytes_out += message_len(&message) as u64;
                sub.outbox
                    .push_frame_later(self.num, OutFrame { message, key: true });
                sub.key_sent = self.last_key_seq;
            }
            let message = cache
                .entry((sub.encoding, filter, joints, weights))
                .or_insert_with(|| {
                    published.message(&self.scene, sub.encoding, filter, joints, weights)
                })
                .clone();
            bytes_out += message_len(&message) as u64;
            sub.outbox
                .push_frame_later(self.num, OutFrame { message, key });
            pushed.push(sub.outbox.clone());
            if key {
                sub.key_sent = Some(at.seq);
            }
            offered += 1;
        }
        self.metrics.frames_offered(offered, bytes_out);
        // The tick's writes into sockets the outboxes write themselves, over the runtime's
        // threads (queued above, so no connection's write waits for another's encoding).
        flush_all(pushed);
        if key {
            self.last_key = Some(published);
            self.last_delta = None;
            self.last_key_seq = Some(at.seq);
            self.force_key = false;
        } else {
            self.last_delta = Some(published);
        }
    }
}

/// An avatar's description message, from the cache while the description is the same one.
fn description_message(
    scene: &SceneId,
    cache: &mut HashMap<AvatarId, (Arc<AvatarDescription>, Message)>,
    description: &Arc<AvatarDescription>,
) -> Message {
    if let Some((d, m)) = cache.get(&description.id)
        && Arc::ptr_eq(d, description)
    {
        return m.clone();
    }
    let message = text(&ServerMsg::Description {
        scene: scene.clone(),
        avatar: Box::new((**description).clone()),
    });
    cache.insert(
        description.id.clone(),
        (description.clone(), message.clone()),
    );
    message
}

/// A server message as a websocket text message.
#[must_use]
pub fn text(msg: &ServerMsg) -> Message {
    // Serialising these types cannot fail (no maps with non-string keys, no failing Serialize
    // impls); an empty object is sent rather than panicking if that ever changes.
    Message::Text(Utf8Bytes::from(
        serde_json::to_string(msg).unwrap_or_else(|_| "{}".into()),
    ))
}
