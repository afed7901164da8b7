//! A take replayed as a scene (`replay`, issue 32): before every tick the replay moves its
//! avatars to the take's frame at the replay's clock, so the scene streams — encoded, fanned
//! out, paced — like any other, and each avatar's pose is the one the recorded scene's
//! subscribers received (the frame's decoded rotations, translations, scales, placement and
//! morph weights; [`posecast_sim::avatar::Avatar::replayed`]).
//!
//! - Time: take seconds `anchor_time + (clock − anchor_clock) · speed` (held while paused),
//!   wrapped when looping, else held at the end; `control_replay` re-anchors at the scene
//!   clock, so a seek, a pause or a new speed never jumps anything but what it asks for.
//! - The cast: every avatar of the take gets an avatar of the same rig in the replay scene,
//!   named `<scene>.<avatar>` (avatar ids are unique on the server, and a take may be replayed
//!   twice at once, or while its scene still runs). Avatars the take added or removed part
//!   way come on and go off with it; those off stage wait in the replay.
//! - Taking over: an avatar given a clip (`play`) leaves the replay for good; a live driver
//!   drives it over the replayed pose (and when the driver goes, the replay has it again). The
//!   others keep replaying.

use bytes::Bytes;
use posecast_core::error::Error;
use posecast_proto::command::ReplayState;
use posecast_proto::msg::{AvatarId, SceneId};
use posecast_sim::avatar::Avatar;
use posecast_stream::feed::Feed;
use posecast_stream::take::{ReadAt, TakeError, TakeIndex, TakeReader};
use std::collections::HashMap;
use std::sync::Arc;

/// Fastest and slowest replay speeds (take seconds per scene second).
pub const SPEEDS: std::ops::RangeInclusive<f32> = 0.01..=100.0;

/// Where a replayed take's bytes are: its file in the data folder, or memory (a server
/// without one).
#[derive(Debug)]
pub enum TakeSource {
    /// The take's file, read at offsets (the page cache keeps what a replay reads again).
    File(std::fs::File),
    /// The take in memory.
    Memory(Bytes),
}

impl ReadAt for TakeSource {
    fn read_at(&self, buf: &mut [u8], offset: u64) -> std::io::Result<()> {
        match self {
            Self::File(f) => f.read_at(buf, offset),
            Self::Memory(b) => b.read_at(buf, offset),
        }
    }
}

/// One avatar of the take in the replay.
#[derive(Debug)]
pub struct CastMember {
    /// Its id in the take.
    pub recorded: AvatarId,
    /// Its avatar in the replay scene (of the same rig, rest pose until its first frame).
    pub avatar: Avatar,
}

/// A take replayed by a scene (see the module doc).
#[derive(Debug)]
pub struct Replay {
    take: String,
    index: Arc<TakeIndex>,
    reader: TakeReader<TakeSource>,
    /// The take's avatar id → the replay's.
    cast: HashMap<AvatarId, AvatarId>,
    /// Avatars of the cast the frame being shown does not have.
    offstage: Vec<Avatar>,
    anchor_clock: f64,
    anchor_time: f64,
    speed: f32,
    paused: bool,
    looping: bool,
    /// The frame last shown.
    shown: Option<usize>,
    /// Why the replay stopped, if it did (a take damaged past its index).
    failed: Option<String>,
}

impl Replay {
    /// A replay of `take` (its index and bytes) by a scene whose clock is `clock` now, from
    /// `from` seconds into the take, with `cast` (every avatar of the take, made by the world
    /// — [`crate::world::World::start_replay`]); they all start off stage and come on at the
    /// first tick.
    ///
    /// # Errors
    /// `invalid_value` for a speed outside [`SPEEDS`] or a start that is not finite.
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        take: String,
        index: Arc<TakeIndex>,
        source: TakeSource,
        cast: Vec<CastMember>,
        clock: f64,
        from: f64,
        speed: f32,
        looping: bool,
    ) -> Result<Self, Error> {
        check_speed(speed)?;
        if !from.is_finite() {
            return Err(Error::invalid_field(
                "from",
                "from must be a finite number of seconds",
            ));
        }
        let reader = TakeReader::new(source, index.clone());
        let mut replay = Self {
            take,
            index,
            reader,
            cast: cast
                .iter()
                .map(|c| (c.recorded.clone(), c.avatar.id.clone()))
                .collect(),
            offstage: cast
                .into_iter()
                .map(|c| {
                    let mut a = c.avatar;
                    a.replayed = Some(a.pose().clone());
                    a
                })
                .collect(),
            anchor_clock: clock,
            anchor_time: 0.0,
            speed,
            paused: false,
            looping,
            shown: None,
            failed: None,
        };
        replay.anchor_time = replay.wrap(from);
        Ok(replay)
    }

    /// The take replayed.
    #[must_use]
    pub fn take(&self) -> &str {
        &self.take
    }

    /// Whether avatar `id` is one the replay moves (on stage or off).
    #[must_use]
    pub fn casts(&self, id: &AvatarId) -> bool {
        self.cast.values().any(|c| c == id)
    }

    /// Whether avatar `id` of the replay is off stage now.
    #[must_use]
    pub fn has_offstage(&self, id: &AvatarId) -> bool {
        self.offstage.iter().any(|a| &a.id == id)
    }

    /// Take seconds at scene clock `clock`.
    #[must_use]
    pub fn time_at(&self, clock: f64) -> f64 {
        let t = if self.paused {
            self.anchor_time
        } else {
            self.anchor_time + (clock - self.anchor_clock) * f64::from(self.speed)
        };
        self.wrap(t)
    }

    /// `t` within the take: wrapped when looping, else clamped.
    fn wrap(&self, t: f64) -> f64 {
        let d = self.index.duration();
        if d.is_nan() || d <= 0.0 || !t.is_finite() {
            return 0.0;
        }
        if self.looping {
            t.rem_euclid(d)
        } else {
            t.clamp(0.0, d)
        }
    }

    /// Where the replay is at scene clock `clock`.
    #[must_use]
    pub fn state(&self, scene: &SceneId, clock: f64) -> ReplayState {
        ReplayState {
            scene: scene.clone(),
            take: self.take.clone(),
            time: self.time_at(clock),
            duration: self.index.duration(),
            paused: self.paused,
            speed: self.speed,
            looping: self.looping,
        }
    }

    /// `control_replay` at scene clock `clock`: seek to `time`, pause or resume, a new speed,
    /// looping or not; absent ones stay. Checked whole before anything changes.
    ///
    /// # Errors
    /// `invalid_value` for a time that is not finite or a speed outside [`SPEEDS`].
    pub fn control(
        &mut self,
        clock: f64,
        time: Option<f64>,
        paused: Option<bool>,
        speed: Option<f32>,
        looping: Option<bool>,
    ) -> Result<(), Error> {
        if let Some(s) = speed {
            check_speed(s)?;
        }
        if time.is_some_and(|t| !t.is_finite()) {
            return Err(Error::invalid_field(
                "time",
                "time must be a finite number of seconds",
            ));
        }
        let now = self.time_at(clock);
        self.anchor_clock = clock;
        self.anchor_time = now;
        if let Some(l) = looping {
            self.looping = l;
        }
        if let Some(t) = time {
            self.anchor_time = t;
        }
        self.anchor_time = self.wrap(self.anchor_time);
        if let Some(p) = paused {
            self.paused = p;
        }
        if let Some(s) = speed {
            self.speed = s;
        }
        Ok(())
    }

    /// Before the avatars tick at scene clock `clock`: the take's frame at the replay's time
    /// becomes the replayed avatars' pose; avatars the frame has come on stage, those it has
    /// not go off (subscribers are told through `feed`; the ids of those that came or went are
    /// added to `moved`, for the scene list's watchers). Avatars taken over stay where they
    /// are. A frame that cannot be read stops the replay where it is (logged once).
    pub fn step(
        &mut self,
        clock: f64,
        avatars: &mut Vec<Avatar>,
        feed: &mut Feed,
        moved: &mut Vec<AvatarId>,
    ) {
        if self.failed.is_some() {
            return;
        }
        let Some(i) = self.index.frame_at(self.time_at(clock)) else {
            return;
        };
        if self.shown == Some(i) {
            return;
        }
        if let Err(e) = self.show(i, clock, avatars, feed, moved) {
            tracing::warn!(take = %self.take, error = %e, "replay stopped: the take cannot be read on");
            self.failed = Some(e.to_string());
        }
    }

    fn show(
        &mut self,
        i: usize,
        clock: f64,
        avatars: &mut Vec<Avatar>,
        feed: &mut Feed,
        moved: &mut Vec<AvatarId>,
    ) -> Result<(), TakeError> {
        let poses = self.reader.poses(i)?;
        self.shown = Some(i);
        // Off stage: replayed avatars this frame does not have.
        let on: Vec<&AvatarId> = poses
            .iter()
            .filter_map(|p| self.cast.get(&p.description.id))
            .collect();
        let mut k = 0;
        while k < avatars.len() {
            let a = &avatars[k];
            let ours = self.cast.values().any(|id| id == &a.id);
            if ours && a.replayed.is_some() && !on.contains(&&a.id) {
                let a = avatars.remove(k);
                feed.avatar_removed(&a);
                moved.push(a.id.clone());
                self.offstage.push(a);
            } else {
                k += 1;
            }
        }
        for p in poses {
            let Some(id) = self.cast.get(&p.description.id) else {
                continue;
            };
            if let Some(at) = self.offstage.iter().position(|a| &a.id == id) {
                let mut a = self.offstage.remove(at);
                a.player.set_clock(clock);
                a.replayed = Some(p.pose.clone());
                a.evaluate();
                feed.avatar_added(&a);
                moved.push(a.id.clone());
                avatars.push(a);
            } else if let Some(a) = avatars.iter_mut().find(|a| &a.id == id)
                && let Some(replayed) = &mut a.replayed
            {
                replayed.clone_from(&p.pose);
            }
        }
        Ok(())
    }
}

fn check_speed(speed: f32) -> Result<(), Error> {
    if SPEEDS.contains(&speed) {
        Ok(())
    } else {
        Err(Error::invalid(format!(
            "speed {speed} is outside {}–{}",
            SPEEDS.start(),
            SPEEDS.end()
        )))
    }
}
