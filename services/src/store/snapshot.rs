//! A scene as stored in `scenes/<scene>.json`: its avatars, what each plays and its joint
//! overrides, by joint *name* so a file stays meaningful if joint order ever changes.

use crate::scene::Scene;
use crate::world::World;
use crate::world::command;
use posecast_proto::command::{Command, JointRef, RootMotion};
use posecast_proto::msg::{AvatarId, SceneId};
use posecast_proto::placement::Placement;
use posecast_sim::avatar::Avatar;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use tracing::warn;

/// The version of the scene file format. A file with another version is refused (moved
/// aside), never half-read.
pub const SCENE_FORMAT: u32 = 1;

/// One scene file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SceneFile {
    /// [`SCENE_FORMAT`].
    pub format: u32,
    /// The scene's id (equals the file's stem).
    pub scene: SceneId,
    /// When the snapshot was taken, microseconds since the Unix epoch: the clocks of playing
    /// clips are extrapolated from here on restore.
    pub saved_us: u64,
    /// Avatars in the order they were added.
    pub avatars: Vec<AvatarRecord>,
    /// The answers of the scene's latest commands that carried an idempotency key, oldest
    /// first ([`crate::scene::answers`]): a retry after a restart, or after a failover in a
    /// cluster, is answered without applying the command again; files without: none.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub recent: Vec<RecentCommand>,
    /// The take the scene replays, when it is a replay (`replay`). Written in a cluster only,
    /// where a server taking the scene over resumes it; a server on its own does not store
    /// replays (a restart ends them).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub replay: Option<ReplayRecord>,
}

pub use crate::scene::answers::RecentCommand;

/// Where a replay was when its scene's snapshot was taken.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ReplayRecord {
    /// The take.
    pub take: String,
    /// Seconds into the take at `saved_us`.
    pub time: f64,
    /// Take seconds per scene second.
    pub speed: f32,
    /// Whether it is paused.
    pub paused: bool,
    /// Whether it loops.
    pub looping: bool,
    /// The avatars on stage it moves (the scene's other avatars were taken over by a clip, or
    /// added).
    pub replayed: Vec<AvatarId>,
}

/// One avatar.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AvatarRecord {
    /// Its id.
    pub id: AvatarId,
    /// Its rig's asset name.
    pub asset: String,
    /// The clip it plays, if any.
    pub playback: Option<PlaybackRecord>,
    /// Joint overrides: joint name → local rotation `[x, y, z, w]` (normalised rig frame).
    pub overrides: BTreeMap<String, [f32; 4]>,
    /// Where it stands (the end of a move in progress); files without one: the origin.
    #[serde(default)]
    pub placement: Placement,
    /// Its IK goals and gaze, as the `set_ik_goal` / `look_at` commands that set them (applied
    /// again once every avatar of the scene is back, so goals relative to others find them).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub goals: Vec<Command>,
    /// Its clip layers, as the `play_layer` commands that start them again at the clip time
    /// they had (applied after the avatar is back).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub layers: Vec<Command>,
    /// Morph weights above 0 by channel name (issue 30); files without: all 0.
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub morph_weights: BTreeMap<String, f32>,
    /// Weights above 0 of the file's own expressions (a VRM's), by name; files without: all 0.
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub expression_weights: BTreeMap<String, f32>,
}

/// The current clip of an avatar. A cross-fade in progress is not stored: it restores as the
/// clip it was fading to.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PlaybackRecord {
    /// The clip's name in its rig.
    pub clip: String,
    /// The rig the clip was retargeted from (`play`'s `from_asset`), if not the avatar's own.
    pub from_asset: Option<String>,
    /// Clip time in seconds from the clip's start, at `saved_us` (wrapped into the clip).
    pub time: f32,
    /// Playback speed.
    pub speed: f32,
    /// Whether it loops.
    pub looping: bool,
    /// Whether its clock is stopped.
    pub paused: bool,
    /// `play`'s root motion; files without one: the default for `looping`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub root_motion: Option<RootMotion>,
}

/// The scene as it is now. Takes the scene's lock briefly.
#[must_use]
pub fn snapshot(scene: &Scene, now_us: u64) -> SceneFile {
    let s = scene.lock();
    let replay = s.replay.as_ref().map(|r| {
        let state = r.state(&scene.id, s.clock());
        ReplayRecord {
            take: state.take,
            time: state.time,
            speed: state.speed,
            paused: state.paused,
            looping: state.looping,
            replayed: s
                .avatars
                .iter()
                .filter(|a| a.replayed.is_some() && r.casts(&a.id))
                .map(|a| a.id.clone())
                .collect(),
        }
    });
    SceneFile {
        format: SCENE_FORMAT,
        scene: scene.id.clone(),
        saved_us: now_us,
        avatars: s.avatars.iter().map(record).collect(),
        recent: scene.answers().iter().cloned().collect(),
        replay,
    }
}

fn record(a: &Avatar) -> AvatarRecord {
    let playback = a.player.current().map(|l| {
        // A retargeted clip is named `<source>:<clip>` (control::retarget).
        let name = l.clip.name();
        let clip = l
            .source_asset
            .as_ref()
            .and_then(|src| name.strip_prefix(src.as_str())?.strip_prefix(':'))
            .unwrap_or(name)
            .to_owned();
        PlaybackRecord {
            clip,
            from_asset: l.source_asset.clone(),
            time: l.clip_time(),
            speed: l.speed(),
            looping: l.looping,
            paused: l.paused(),
            root_motion: Some(l.root_motion),
        }
    });
    let names = a.rig.skeleton().names();
    AvatarRecord {
        id: a.id.clone(),
        asset: a.rig.name.clone(),
        playback,
        overrides: a
            .overrides
            .iter()
            .zip(names)
            .filter_map(|(o, n)| o.map(|q| (n.clone(), q.to_array())))
            .collect(),
        placement: a.placing.target(),
        goals: goal_commands(a),
        layers: layer_commands(a),
        morph_weights: a.set_channel_weights(),
        expression_weights: a.set_expression_weights(),
    }
}

/// The `play_layer` commands that start an avatar's layers again as they are (a layer fading
/// out is not kept).
fn layer_commands(a: &Avatar) -> Vec<Command> {
    a.layers
        .iter()
        // The locomotion layer belongs to its tracker drive, which a restart does not keep.
        .filter(|l| !l.stopping() && l.name != posecast_sim::avatar::LOCOMOTION_LAYER)
        .filter_map(|l| {
            let clip = l.player.current()?;
            Some(Command::PlayLayer {
                avatar: a.id.clone(),
                layer: l.name.clone(),
                clip: clip.clip.name().to_string(),
                from_asset: clip.source_asset.clone(),
                mask: l.mask.clone(),
                additive: l.additive,
                reference: l.reference,
                weight: Some(l.weight),
                speed: Some(clip.speed()),
                looping: Some(clip.looping),
                start: Some(clip.clip_time()),
                fade: Some(0.0),
            })
        })
        .collect()
}

/// The commands that set an avatar's goals and gaze as they are.
fn goal_commands(a: &Avatar) -> Vec<Command> {
    let names = a.rig.skeleton().names();
    let joint_ref = |r: &posecast_sim::avatar::goals::JointRef| JointRef {
        avatar: r.avatar.clone(),
        joint: r.joint.clone(),
    };
    let mut commands: Vec<Command> = a
        .goals
        .goals
        .iter()
        .map(|g| Command::SetIkGoal {
            avatar: a.id.clone(),
            effector: names[g.effector].clone(),
            position: g.position.to_array(),
            rotation: g.rotation.map(|q| q.to_array()),
            weight: Some(g.weight),
            pole: g.pole.map(|p| p.to_array()),
            relative_to: g.relative_to.as_ref().map(joint_ref),
            chain: g.chain.and_then(|n| u8::try_from(n).ok()),
        })
        .collect();
    if let Some(g) = &a.goals.gaze {
        commands.push(Command::LookAt {
            avatar: a.id.clone(),
            target: g.target.to_array(),
            weight: Some(g.weight),
            relative_to: g.relative_to.as_ref().map(joint_ref),
        });
    }
    commands
}

/// Reads a scene file's JSON leniently: one bad value never costs the whole scene. The
/// scene's own fields (format, id, time) must be right; an avatar record without a usable id
/// or asset is dropped alone, a playback record that does not parse (or holds a non-finite
/// time or speed) is dropped from its avatar, and an override that is not a rotation (e.g.
/// `null` components written by an older server) is dropped from its joint. Returns the file
/// and what was dropped, each naming the avatar and joint.
///
/// # Errors
/// The scene's own fields are missing or wrong.
pub fn parse_lenient(value: &serde_json::Value) -> Result<(SceneFile, Vec<String>), String> {
    use serde_json::Value;
    let field = |name: &str| value.get(name).cloned().unwrap_or(Value::Null);
    let format: u32 =
        serde_json::from_value(field("format")).map_err(|e| format!("format: {e}"))?;
    let scene: SceneId =
        serde_json::from_value(field("scene")).map_err(|e| format!("scene: {e}"))?;
    let saved_us: u64 =
        serde_json::from_value(field("saved_us")).map_err(|e| format!("saved_us: {e}"))?;
    let records = match field("avatars") {
        Value::Array(a) => a,
        other => return Err(format!("avatars is not a list: {other}")),
    };
    let mut dropped = Vec::new();
    let mut avatars = Vec::with_capacity(records.len());
    for (i, rec) in records.iter().enumerate() {
        let get = |name: &str| rec.get(name).cloned().unwrap_or(Value::Null);
        let (id, asset) = match (
            serde_json::from_value::<AvatarId>(get("id")),
            serde_json::from_value::<String>(get("asset")),
        ) {
            (Ok(id), Ok(asset)) => (id, asset),
            (id, asset) => {
                let name = id.map_or_else(|_| format!("#{i}"), |id| id.0);
                dropped.push(format!(
                    "avatar {name}: no usable id or asset ({})",
                    asset
                        .err()
                        .map_or_else(|| "bad id".into(), |e| e.to_string())
                ));
                continue;
            }
        };
        let playback = match get("playback") {
            Value::Null => None,
            p => match serde_json::from_value::<PlaybackRecord>(p) {
                Ok(p) if p.time.is_finite() && p.speed.is_finite() => Some(p),
                Ok(p) => {
                    dropped.push(format!(
                        "avatar {id}: playback of {} (time {}, speed {} not finite)",
                        p.clip, p.time, p.speed
                    ));
                    None
                }
                Err(e) => {
                    dropped.push(format!("avatar {id}: playback ({e})"));
                    None
                }
            },
        };
        let mut overrides = BTreeMap::new();
        if let Value::Object(map) = get("overrides") {
            for (joint, q) in map {
                match serde_json::from_value::<[f32; 4]>(q.clone())
                    .ok()
                    .filter(|q| posecast_proto::unit_quat(*q).is_some())
                {
                    Some(q) => {
                        overrides.insert(joint, q);
                    }
                    None => dropped.push(format!(
                        "avatar {id}: override of joint {joint} ({q} is not a rotation)"
                    )),
                }
            }
        }
        let placement = match get("placement") {
            Value::Null => Placement::IDENTITY,
            p => match serde_json::from_value::<Placement>(p.clone())
                .ok()
                .and_then(|v| Placement::try_new(v.position.to_array(), v.rotation.to_array()).ok())
            {
                Some(v) => v,
                None => {
                    dropped.push(format!("avatar {id}: placement ({p} is not a placement)"));
                    Placement::IDENTITY
                }
            },
        };
        let mut goals = Vec::new();
        if let Value::Array(list) = get("goals") {
            for g in list {
                match serde_json::from_value::<Command>(g.clone()) {
                    Ok(c @ (Command::SetIkGoal { .. } | Command::LookAt { .. }))
                        if c.avatar() == Some(&id) =>
                    {
                        goals.push(c);
                    }
                    _ => dropped.push(format!("avatar {id}: goal {g} (not a goal of it)")),
                }
            }
        }
        let mut layers = Vec::new();
        if let Value::Array(list) = get("layers") {
            for l in list {
                match serde_json::from_value::<Command>(l.clone()) {
                    Ok(c @ Command::PlayLayer { .. }) if c.avatar() == Some(&id) => layers.push(c),
                    _ => dropped.push(format!("avatar {id}: layer {l} (not a layer of it)")),
                }
            }
        }
        // Weights: each finite one in [0, 1] of a channel name kept; anything else dropped
        // alone (and a channel the rig lost is dropped on restore).
        let mut weights = |field: &str, what: &str| {
            let mut out = BTreeMap::new();
            if let Value::Object(map) = get(field) {
                for (name, w) in map {
                    match w
                        .as_f64()
                        .map(|w| w as f32)
                        .filter(|w| (0.0..=1.0).contains(w))
                    {
                        Some(w) => {
                            out.insert(name, w);
                        }
                        None => dropped.push(format!("avatar {id}: {what} {name} ({w})")),
                    }
                }
            }
            out
        };
        let morph_weights = weights("morph_weights", "morph weight");
        let expression_weights = weights("expression_weights", "expression weight");
        avatars.push(AvatarRecord {
            id,
            asset,
            playback,
            overrides,
            placement,
            goals,
            layers,
            morph_weights,
            expression_weights,
        });
    }
    // A table that does not parse costs the retries' answers only, never the scene.
    let recent = match field("recent") {
        Value::Null => Vec::new(),
        r => serde_json::from_value::<Vec<RecentCommand>>(r).unwrap_or_else(|e| {
            dropped.push(format!("the answers of recent commands ({e})"));
            Vec::new()
        }),
    };
    let replay = match field("replay") {
        Value::Null => None,
        r => serde_json::from_value::<ReplayRecord>(r)
            .map_err(|e| dropped.push(format!("the replay ({e})")))
            .ok(),
    };
    Ok((
        SceneFile {
            format,
            scene,
            saved_us,
            avatars,
            recent,
            replay,
        },
        dropped,
    ))
}

/// The clip time a clock shows `elapsed_s` seconds after it showed `p.time`: paused clocks
/// stand still, looping ones wrap (done here in f64 so days of downtime keep precision),
/// others hold at an end like a running clock does.
#[must_use]
pub fn extrapolate(p: &PlaybackRecord, duration: f32, elapsed_s: f64) -> f32 {
    if p.paused {
        return p.time;
    }
    let t = f64::from(p.time) + elapsed_s * f64::from(p.speed);
    let d = f64::from(duration.max(0.0));
    let t = if p.looping {
        if d > 0.0 { t.rem_euclid(d) } else { 0.0 }
    } else {
        t.clamp(0.0, d)
    };
    t as f32
}

/// Recreates a stored scene: the scene, then each avatar with its id, clip (clock extrapolated
/// to `now_us`) and overrides. An avatar whose asset is gone, or a clip or joint its rig lacks,
/// is warned about and skipped alone.
///
/// # Errors
/// The scene itself cannot be created (bad id, already exists).
pub fn restore(
    world: &World,
    file: &SceneFile,
    now_us: u64,
) -> Result<(), posecast_core::error::Error> {
    world.restore_scene(file.scene.clone())?;
    restore_into(world, file, now_us);
    Ok(())
}

/// [`restore`] into the scene of that id, which exists already (a server of a cluster taking
/// a scene over keeps the scene its subscribers are on).
pub fn restore_into(world: &World, file: &SceneFile, now_us: u64) {
    let elapsed_s = now_us.saturating_sub(file.saved_us) as f64 / 1e6;
    if let Ok(scene) = world.scene(&file.scene) {
        *scene.answers() = file.recent.iter().cloned().collect();
    }
    for rec in &file.avatars {
        let placement = Placement::try_new(
            rec.placement.position.to_array(),
            rec.placement.rotation.to_array(),
        )
        .unwrap_or_default();
        let (scene, id) = match world.add_avatar_at(
            &file.scene,
            &rec.asset,
            Some(rec.id.clone()),
            placement,
            false,
        ) {
            Ok(added) => added,
            Err(e) => {
                warn!(scene = %file.scene, avatar = %rec.id, error = %e, "avatar not restored");
                continue;
            }
        };
        if let Some(p) = &rec.playback {
            restore_playback(world, &id, p, elapsed_s);
        }
        let mut s = scene.lock();
        let Some(a) = s.avatar_mut(&id) else { continue };
        for (joint, q) in &rec.overrides {
            let q = glam::Quat::from_array(*q);
            match a.rig.skeleton().find(joint) {
                Some(j) if q.is_finite() && q.length() > 1e-6 => {
                    a.overrides[j] = Some(q.normalize())
                }
                _ => {
                    warn!(scene = %file.scene, avatar = %id, joint, "override not restored: no such joint or not a rotation")
                }
            }
        }
        let channels = &a.description.morph_targets;
        let weights: Vec<(usize, f32)> = rec
            .morph_weights
            .iter()
            .filter_map(|(name, w)| match channels.iter().position(|c| c == name) {
                Some(c) => Some((c, *w)),
                None => {
                    warn!(scene = %file.scene, avatar = %id, name, "morph weight not restored: no such channel");
                    None
                }
            })
            .collect();
        let channels = channels.len();
        let expressions: Vec<(usize, f32)> = rec
            .expression_weights
            .iter()
            .filter_map(|(name, w)| {
                match a.description.expression_binds.iter().position(|e| e.name == *name) {
                    Some(k) => Some((channels + k, *w)),
                    None => {
                        warn!(scene = %file.scene, avatar = %id, name, "expression weight not restored: the rig has no such expression");
                        None
                    }
                }
            })
            .collect();
        a.set_morph(&weights, true);
        a.set_morph(&expressions, false);
        a.evaluate();
    }
    // Goals once every avatar is back: one relative to another avatar needs it there.
    for goal in file.avatars.iter().flat_map(|rec| &rec.goals) {
        if let Err(e) = command::apply(world, goal) {
            warn!(scene = %file.scene, avatar = ?goal.avatar(), error = %e, "IK goal not restored");
        }
    }
    for layer in file.avatars.iter().flat_map(|rec| &rec.layers) {
        if let Err(e) = command::apply(world, layer) {
            warn!(scene = %file.scene, avatar = ?layer.avatar(), error = %e, "clip layer not restored");
        }
    }
}

fn restore_playback(world: &World, avatar: &AvatarId, p: &PlaybackRecord, elapsed_s: f64) {
    let source = p.from_asset.as_deref().map(|n| world.library.get(n));
    let duration = match source {
        Some(Some(rig)) => rig.clip(&p.clip).map(|c| c.duration()),
        Some(None) => None,
        None => world.find_avatar(avatar).ok().and_then(|s| {
            let s = s.lock();
            let a = s.avatars.iter().find(|a| &a.id == avatar)?;
            a.rig.clip(&p.clip).map(|c| c.duration())
        }),
    };
    let Some(duration) = duration else {
        warn!(%avatar, clip = %p.clip, from_asset = ?p.from_asset, "clip not restored: it no longer exists");
        return;
    };
    let play = Command::Play {
        avatar: avatar.clone(),
        clip: p.clip.clone(),
        from_asset: p.from_asset.clone(),
        speed: Some(p.speed),
        looping: Some(p.looping),
        start: Some(extrapolate(p, duration, elapsed_s)),
        fade: Some(0.0),
        root_motion: p.root_motion,
    };
    let result = command::apply(world, &play).and_then(|_| {
        if p.paused {
            command::apply(
                world,
                &Command::Pause {
                    avatar: avatar.clone(),
                },
            )
        } else {
            Ok(posecast_proto::command::CommandResult::Done)
        }
    });
    if let Err(e) = result {
        warn!(%avatar, clip = %p.clip, error = %e, "clip not restored");
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::Config;
    use crate::state::Services;
    use posecast_rigs::builtin::BUILTIN_ASSET;

    fn cmd(state: &Services, json: &str) -> serde_json::Value {
        crate::control::execute(state, &serde_json::from_str(json).unwrap())
            .unwrap()
            .to_value()
    }

    #[tokio::test]
    async fn snapshot_round_trips_through_json_and_restore() {
        let state = Services::new(Config::default());
        state
            .world
            .library
            .insert(posecast_rigs::builtin::rig().unwrap());
        cmd(&state, r#"{"op":"create_scene","scene":"s"}"#);
        cmd(
            &state,
            &format!(r#"{{"op":"add_avatar","scene":"s","asset":"{BUILTIN_ASSET}","avatar":"a"}}"#),
        );
        cmd(
            &state,
            &format!(r#"{{"op":"add_avatar","scene":"s","asset":"{BUILTIN_ASSET}","avatar":"b"}}"#),
        );
        cmd(
            &state,
            r#"{"op":"play","avatar":"a","clip":"idle","speed":0.5,"looping":false,"start":0.2}"#,
        );
        cmd(
            &state,
            r#"{"op":"play","avatar":"b","clip":"idle","start":0.7}"#,
        );
        cmd(&state, r#"{"op":"pause","avatar":"b"}"#);
        let set = cmd(
            &state,
            r#"{"op":"set_joint_rotation","avatar":"a","joint":"l_knee","rotation":[0.3826834,0,0,0.9238795]}"#,
        );

        // A goal relative to b, which is restored after a; a gaze.
        cmd(
            &state,
            r#"{"op":"set_ik_goal","avatar":"a","effector":"r_wrist","position":[0,0.1,0],"pole":[0,0,-1],"weight":0.75,"relative_to":{"avatar":"b","joint":"l_shoulder"}}"#,
        );
        cmd(
            &state,
            r#"{"op":"look_at","avatar":"a","target":[1,1.6,2]}"#,
        );

        let scene = state.world.scene(&SceneId("s".into())).unwrap();
        let file = snapshot(&scene, 1_000_000);
        let text = serde_json::to_string_pretty(&file).unwrap();
        let back: SceneFile = serde_json::from_str(&text).unwrap();
        assert_eq!(back, file);
        assert_eq!(back.avatars.len(), 2);
        let a = &back.avatars[0];
        let p = a.playback.as_ref().unwrap();
        assert_eq!(
            (p.clip.as_str(), p.time, p.speed, p.looping, p.paused),
            ("idle", 0.2, 0.5, false, false)
        );
        let knee: Vec<f32> = set["rotation"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_f64().unwrap() as f32)
            .collect();
        assert_eq!(a.overrides["l_knee"].to_vec(), knee);

        // Restore into a fresh state 2 s later: a's clock moved 1 s (speed 0.5), b's did not.
        let fresh = Services::new(Config::default());
        fresh
            .world
            .library
            .insert(posecast_rigs::builtin::rig().unwrap());
        restore(&fresh.world, &back, 3_000_000).unwrap();
        let again = snapshot(&fresh.world.scene(&SceneId("s".into())).unwrap(), 3_000_000);
        let (ra, rb) = (&again.avatars[0], &again.avatars[1]);
        let pa = ra.playback.as_ref().unwrap();
        let duration = fresh
            .world
            .library
            .get(BUILTIN_ASSET)
            .unwrap()
            .clip("idle")
            .unwrap()
            .duration();
        assert!((pa.time - 1.2f32.min(duration)).abs() < 1e-4, "{pa:?}");
        assert_eq!(ra.overrides, a.overrides);
        assert_eq!(ra.goals, a.goals);
        assert_eq!(a.goals.len(), 2, "{:?}", a.goals);
        let restored = fresh.world.scene(&SceneId("s".into())).unwrap();
        let state_a = restored.lock().avatars[0].state(&restored.id);
        assert_eq!(
            (state_a.ik_goals, state_a.looking),
            (vec!["r_wrist".to_owned()], true)
        );
        let pb = rb.playback.as_ref().unwrap();
        assert!(pb.paused && (pb.time - 0.7).abs() < 1e-6, "{pb:?}");
        assert_eq!(rb.id, AvatarId("b".into()));
    }

    #[tokio::test]
    async fn restore_skips_what_no_longer_exists() {
        let state = Services::new(Config::default());
        state
            .world
            .library
            .insert(posecast_rigs::builtin::rig().unwrap());
        let file: SceneFile = serde_json::from_value(serde_json::json!({
            "format": 1, "scene": "s", "saved_us": 0,
            "avatars": [
                {"id": "gone", "asset": "no-such-rig", "playback": null, "overrides": {}},
                {"id": "a", "asset": BUILTIN_ASSET,
                 "playback": {"clip": "no-such-clip", "from_asset": null, "time": 0.0, "speed": 1.0, "looping": true, "paused": false},
                 "overrides": {"tail": [0.0, 0.0, 0.0, 1.0], "l_knee": [0.0, 0.0, 0.0, 2.0]}}
            ]
        }))
        .unwrap();
        restore(&state.world, &file, 0).unwrap();
        let info = state.world.scene(&SceneId("s".into())).unwrap().info();
        assert_eq!(info.avatars.len(), 1);
        assert_eq!(info.avatars[0].clip, None);
        assert_eq!(info.avatars[0].overrides, vec!["l_knee".to_string()]);
    }

    /// A tracker drive's locomotion layer belongs to the drive (a restart does not keep
    /// drives): a snapshot keeps the avatar's own layers, not it.
    #[tokio::test]
    async fn snapshots_leave_out_the_locomotion_layer() {
        let state = Services::new(Config::default());
        state
            .world
            .library
            .insert(posecast_rigs::builtin::rig().unwrap());
        cmd(&state, r#"{"op":"create_scene","scene":"s"}"#);
        cmd(
            &state,
            &format!(r#"{{"op":"add_avatar","scene":"s","asset":"{BUILTIN_ASSET}","avatar":"a"}}"#),
        );
        cmd(
            &state,
            r#"{"op":"play_layer","avatar":"a","layer":"wave","clip":"wave","mask":{"joints":["r_shoulder"]}}"#,
        );
        let scene = state.world.scene(&SceneId("s".into())).unwrap();
        {
            let mut s = scene.lock();
            let a = s.avatar_mut(&AvatarId("a".into())).unwrap();
            let clip = a.rig.clips[0].clone();
            let spec = posecast_sim::avatar::layers::LayerSpec {
                owned: vec![true; a.rig.skeleton().len()],
                mask: None,
                additive: false,
                reference: posecast_proto::command::AdditiveReference::Rest,
                weight: 1.0,
            };
            let played = posecast_sim::avatar::playback::Layer::new(clip, None, 0.0, 1.0, true);
            a.layers.push(posecast_sim::avatar::layers::ClipLayer::new(
                posecast_sim::avatar::LOCOMOTION_LAYER.into(),
                played,
                spec,
                0.0,
                0.0,
            ));
        }
        let file = snapshot(&scene, 1_000_000);
        let names: Vec<&Command> = file.avatars[0].layers.iter().collect();
        assert_eq!(names.len(), 1, "{names:?}");
        assert!(matches!(names[0], Command::PlayLayer { layer, .. } if layer == "wave"));
    }

    #[test]
    fn extrapolation_wraps_clamps_and_holds() {
        let p = |looping, paused| PlaybackRecord {
            clip: "c".into(),
            from_asset: None,
            time: 1.0,
            speed: 2.0,
            looping,
            paused,
            root_motion: None,
        };
        assert!((extrapolate(&p(true, false), 3.0, 2.5) - 0.0).abs() < 1e-6);
        assert!((extrapolate(&p(true, false), 3.0, 86_400.25) - 1.5).abs() < 1e-4);
        assert_eq!(extrapolate(&p(false, false), 3.0, 10.0), 3.0);
        assert_eq!(extrapolate(&p(true, true), 3.0, 10.0), 1.0);
    }
}
