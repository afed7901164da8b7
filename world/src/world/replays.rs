//! Starting and steering replays of takes (`replay`, `control_replay`): the scene and its
//! cast are made here; the replay itself is [`crate::scene::replay`].

use super::World;
use crate::scene::replay::{CastMember, Replay, TakeSource};
use posecast_core::error::Error;
use posecast_proto::command::ReplayState;
use posecast_proto::msg::{AvatarId, SceneId, check_id};
use posecast_sim::avatar::Avatar;
use posecast_stream::take::TakeIndex;
use std::sync::Arc;
use std::sync::atomic::Ordering;

/// How a replay starts (`replay`'s options).
#[derive(Debug, Clone, Copy)]
pub struct ReplayStart {
    /// Seconds into the take.
    pub from: f64,
    /// Take seconds per scene second.
    pub speed: f32,
    /// Loop at the end.
    pub looping: bool,
}

impl World {
    /// `replay`: a new scene `scene` replaying take `take` (its index and bytes). Every
    /// avatar of the take gets one of the same rig, `<scene>.<avatar>`; the rigs must be
    /// loaded and still have the joints, streamed translations and scales they were recorded
    /// with. Nothing is left behind when it fails.
    ///
    /// # Errors
    /// `unknown_asset` (a rig the take needs is gone), `conflict` (the scene or an avatar id
    /// exists, or a rig changed since the take), `invalid_value` (a bad option, an id too
    /// long), `quota_exceeded` (scenes, avatars per scene).
    pub fn start_replay(
        &self,
        scene: &SceneId,
        take: &str,
        index: Arc<TakeIndex>,
        source: TakeSource,
        start: ReplayStart,
    ) -> Result<(Arc<crate::scene::Scene>, ReplayState), Error> {
        let cast = self.cast_of(scene, take, &index, |_| false)?;
        let _adding = self.ids_free(&cast)?;
        let created = self.create_scene(scene.clone())?;
        match attach(&created, take, index, source, cast, start, false) {
            Ok(state) => Ok((created, state)),
            Err(e) => {
                self.delete_scene(scene).ok();
                Err(e)
            }
        }
    }

    /// A replay resumed in scene `scene`, which exists (a server of a cluster taking a replay
    /// scene over, its avatars restored from its snapshot but for the replayed ones): every
    /// avatar of the take the scene does not have joins the cast; those it has (taken over by
    /// a clip) stay as they are.
    ///
    /// # Errors
    /// As [`Self::start_replay`].
    pub fn resume_replay(
        &self,
        scene: &Arc<crate::scene::Scene>,
        take: &str,
        index: Arc<TakeIndex>,
        source: TakeSource,
        start: ReplayStart,
        paused: bool,
    ) -> Result<ReplayState, Error> {
        let here = |id: &AvatarId| scene.lock().avatars.iter().any(|a| &a.id == id);
        let cast = self.cast_of(&scene.id, take, &index, here)?;
        let _adding = self.ids_free(&cast)?;
        attach(scene, take, index, source, cast, start, paused)
    }

    /// Checks that no avatar has an id of `cast`, and returns the lock avatar adds hold (ids
    /// are unique across scenes: checked and taken under it).
    ///
    /// # Errors
    /// `conflict` naming the avatar that exists.
    fn ids_free(&self, cast: &[CastMember]) -> Result<std::sync::MutexGuard<'_, ()>, Error> {
        let adding = self
            .avatar_ids
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        if let Some(c) = cast.iter().find(|c| self.find_avatar(&c.avatar.id).is_ok()) {
            return Err(Error::Conflict(format!("avatar {} exists", c.avatar.id)));
        }
        Ok(adding)
    }

    /// The cast of a replay of `take` in scene `scene`: an avatar of the same rig for every
    /// avatar of the take but those `skip` names (by their id in the replay).
    fn cast_of(
        &self,
        scene: &SceneId,
        take: &str,
        index: &TakeIndex,
        skip: impl Fn(&AvatarId) -> bool,
    ) -> Result<Vec<CastMember>, Error> {
        let mut recorded: Vec<&posecast_proto::description::AvatarDescription> = Vec::new();
        for list in &index.avatar_lists {
            for d in list {
                if !recorded.iter().any(|r| r.id == d.id) {
                    recorded.push(d);
                }
            }
        }
        let max = self.quotas.max_avatars_per_scene;
        if recorded.len() > max {
            return Err(self.metrics.refuse_quota(
                posecast_core::quota::Quota::AvatarsPerScene,
                format!("take {take} has {} avatars", recorded.len()),
                max,
            ));
        }
        let mut cast = Vec::with_capacity(recorded.len());
        let by_id = self.numbers_from_ids.load(Ordering::SeqCst);
        for d in &recorded {
            let id = AvatarId(format!("{scene}.{}", d.id));
            if skip(&id) {
                continue;
            }
            let rig = self
                .library
                .get(&d.name)
                .ok_or_else(|| Error::UnknownAsset {
                    asset: d.name.clone(),
                    needed_by: Some(format!("avatar {} of take {take}", d.id)),
                })?;
            check_id("avatar", &id.0).map_err(|e| {
                Error::invalid(format!(
                    "replay avatar {id}: {} (choose a shorter scene id)",
                    e.message
                ))
            })?;
            let seq = self.next_avatar_num.fetch_add(1, Ordering::Relaxed);
            let num = if by_id { super::number_of(&id.0) } else { seq };
            let avatar = Avatar::new(id, num, rig);
            let now = &avatar.description;
            if now.joint_names != d.joint_names
                || now.translated_joints != d.translated_joints
                || now.scaled_joints != d.scaled_joints
                || now.morph_targets.len() != d.morph_targets.len()
            {
                return Err(Error::Conflict(format!(
                    "rig {} is not the one avatar {} of take {take} was recorded with \
                     (its joints or channels changed)",
                    d.name, d.id
                )));
            }
            cast.push(CastMember {
                recorded: d.id.clone(),
                avatar,
            });
        }
        Ok(cast)
    }

    /// `control_replay` on scene `scene`.
    ///
    /// # Errors
    /// `unknown_scene`; `not_allowed_now` when the scene is not a replay; `invalid_value`.
    pub fn control_replay(
        &self,
        scene: &SceneId,
        time: Option<f64>,
        paused: Option<bool>,
        speed: Option<f32>,
        looping: Option<bool>,
    ) -> Result<ReplayState, Error> {
        let scene = self.scene(scene)?;
        let mut s = scene.lock();
        let clock = s.clock();
        let replay = s
            .replay
            .as_mut()
            .ok_or_else(|| Error::NotAllowedNow(format!("scene {} is not a replay", scene.id)))?;
        replay.control(clock, time, paused, speed, looping)?;
        Ok(replay.state(&scene.id, clock))
    }

    /// The takes being replayed now, one entry per replay.
    #[must_use]
    pub fn replayed_takes(&self) -> Vec<String> {
        self.scenes()
            .iter()
            .filter_map(|s| s.lock().replay.as_ref().map(|r| r.take().to_owned()))
            .collect()
    }
}

/// Starts a replay in `scene` with `cast`; its first frame's avatars come on stage at once,
/// so the answer's announcements (`changes`) and the first subscribers find them.
fn attach(
    scene: &Arc<crate::scene::Scene>,
    take: &str,
    index: Arc<TakeIndex>,
    source: TakeSource,
    cast: Vec<CastMember>,
    start: ReplayStart,
    paused: bool,
) -> Result<ReplayState, Error> {
    let mut s = scene.lock();
    let clock = s.clock();
    let mut replay = Replay::new(
        take.to_owned(),
        index,
        source,
        cast,
        clock,
        start.from,
        start.speed,
        start.looping,
    )?;
    if paused {
        replay.control(clock, None, Some(true), None, None)?;
    }
    let state = replay.state(&scene.id, clock);
    let s = &mut *s;
    // Announced with the answer (`changes`), not as tick changes.
    replay.step(clock, &mut s.avatars, &mut scene.feed(), &mut Vec::new());
    s.replay = Some(replay);
    Ok(state)
}
