//! One avatar in a scene — the simulation, with no networking: its rig, what it plays, a live
//! driver's pose, joint overrides layered on top, and the pose it had at the last tick.
//!
//! - [`playback`]: clip clocks and cross-fades.
//! - [`placement`]: the avatar's world placement, moves, and clip root motion.
//! - [`live`]: a live driver's pose, retargeted from its source rig.
//! - [`trackers`]: a tracker drive: the whole body solved from a headset, controllers and
//!   optional hip and foot trackers.
//! - [`goals`]: IK goals and a gaze, solved after the clip and the live pose.
//! - [`recording`]: what the avatar streams, tick by tick, into a clip on its rig.

pub mod goals;
pub mod layers;
pub mod live;
pub mod placement;
pub mod playback;
pub mod recording;
pub mod trackers;

use crate::avatar::live::LivePose;
use glam::{Mat4, Quat};
use placement::{Placing, RootTrack};
use playback::{Layer, Player};
use posecast_proto::bind::{rotation_about, world_increment_local};
use posecast_proto::command::{AdditiveReference, AvatarState, JointMask, OnRelease};
use posecast_proto::description::AvatarDescription;
use posecast_proto::fk::forward_kinematics;
use posecast_proto::frame::AvatarPose;
use posecast_proto::morph;
use posecast_proto::msg::{AvatarId, SceneId};
use posecast_proto::{DecomposeError, Transform};
use posecast_rigs::rig::Rig;
use recording::Recorder;
use std::sync::Arc;
use std::time::Instant;

/// A value that is not a rotation (non-finite, zero, or overflowing when normalised).
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
#[error("rotation {0:?} is not a finite non-zero quaternion")]
pub struct InvalidRotation(pub [f32; 4]);

/// Why a world-space increment could not be applied.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RotateError {
    /// The increment (or its result) is not a rotation.
    #[error(transparent)]
    Invalid(#[from] InvalidRotation),
    /// The joint's new local transform is not a rotation (a sheared or mirrored rig).
    #[error(transparent)]
    Decompose(#[from] DecomposeError),
}

/// The clip layer a tracker drive's `legs: locomotion` plays on (`@` keeps it apart from the
/// names `play_layer` takes).
pub const LOCOMOTION_LAYER: &str = "@locomotion";
/// How long a locomotion clip takes to cross-fade to another, seconds.
const LOCOMOTION_FADE: f32 = 0.25;

/// An avatar.
#[derive(Debug)]
pub struct Avatar {
    /// Its id.
    pub id: AvatarId,
    /// Its rig.
    pub rig: Arc<Rig>,
    /// Its description (sent to subscribers).
    pub description: Arc<AvatarDescription>,
    /// What it plays.
    pub player: Player,
    /// Local rotation overrides, per joint.
    pub overrides: Vec<Option<Quat>>,
    /// The pose at the last tick (local transforms, one per joint).
    pub locals: Vec<Transform>,
    world: Vec<Mat4>,
    pose: AvatarPose,
    /// Where it stands in the scene ([`placement`]).
    pub placing: Placing,
    pub(super) root_track: RootTrack,
    /// A live driver's pose, applied between the clip and the overrides (the `live` module).
    pub live: Option<LivePose>,
    /// IK goals and a gaze, solved after the live pose and before the overrides ([`goals`]).
    pub goals: goals::Goals,
    /// What it streams, being recorded into a clip ([`recording`]).
    pub recording: Option<Recorder>,
    /// Morph weights, one per channel of the description's `morph_targets` (issue 30), set by
    /// `set_morph_weights`, `set_expression`, a live driver and VMC blend shapes.
    pub morph: Vec<f32>,
    /// The weights the playing clips animate (cross-faded as the pose is), per channel.
    pub morph_clip: Vec<f32>,
    /// The weights shown (streamed, sent over VMC): per channel the larger of the set weight
    /// and the clip's, so an expression set by a command or a tracker shows over a talking
    /// clip, and setting 0 gives the face back to the clip.
    pub morph_shown: Vec<f32>,
    /// Weights of the file's expressions (the description's `expression_binds`), one each,
    /// set like [`Avatar::morph`] through their slots ([`Avatar::morph_channel`]).
    pub expression_weights: Vec<f32>,
    /// Each file expression's binds as `(channel, weight)`.
    expression_binds: Vec<Vec<(usize, f32)>>,
    /// Clip layers over the clip, in the order they apply ([`layers`]).
    pub layers: Vec<layers::ClipLayer>,
    /// A replayed take's pose for this avatar (set by the replay before every tick), which
    /// takes the clip's place: layers, a live driver, goals and overrides still apply over
    /// it. `None` for an avatar that is not replayed, or was taken over by a clip.
    pub replayed: Option<AvatarPose>,
    /// Which joints are roots (a layer leaves their translation alone).
    roots: Vec<bool>,
}

impl Avatar {
    /// The driver is gone (left or silent): return to the clip, or hold the pose.
    pub fn driver_gone(&mut self) {
        match self.live.as_mut() {
            Some(live) if live.on_release == OnRelease::Hold => live.driver = None,
            _ => self.live = None,
        }
        self.evaluate();
    }

    /// `release_drive`: ends live driving (and a held pose); the avatar plays its clip again.
    pub fn release_drive(&mut self) {
        self.live = None;
        self.evaluate();
    }

    /// An avatar of `rig`, holding its rest pose.
    #[must_use]
    pub fn new(id: AvatarId, num: u32, rig: Arc<Rig>) -> Self {
        let skeleton = rig.skeleton();
        let n = skeleton.len();
        let mesh_url =
            (!rig.asset.meshes.is_empty()).then(|| format!("/api/assets/{}/mesh.glb", rig.name));
        let description = AvatarDescription::new(
            id.clone(),
            num,
            rig.name.clone(),
            skeleton,
            &rig.translated,
            &rig.scaled,
            mesh_url,
        );
        let channels = posecast_proto::morph::channels(rig.asset.meshes.iter().map(|m| &m.mesh));
        let mut defs = rig.asset.expressions.clone();
        // A configured mapping replaces the file's expression of that name (as the user's
        // joint map wins over a VRM humanoid's).
        if let Some(c) = &rig.options.expression_map {
            defs.retain(|d| !c.contains_key(&d.name));
        }
        let expressions = expression_map(&channels, &defs, rig.options.expression_map.as_ref());
        let morph = vec![0.0; channels.len()];
        let index: std::collections::HashMap<&str, usize> = channels
            .iter()
            .enumerate()
            .map(|(i, c)| (c.as_str(), i))
            .collect();
        let expression_binds: Vec<Vec<(usize, f32)>> = defs
            .iter()
            .map(|e| {
                e.binds
                    .iter()
                    .filter_map(|b| Some((*index.get(b.channel.as_str())?, b.weight)))
                    .collect()
            })
            .collect();
        let mut player = Player::new();
        player.set_morph_channels(channels.clone());
        let expression_weights = vec![0.0; defs.len()];
        let description = description
            .with_morphs(channels, expressions)
            .with_expression_binds(defs);
        let locals = skeleton.rest().to_vec();
        let roots = skeleton.parents().iter().map(Option::is_none).collect();
        let pose = AvatarPose {
            avatar_num: num,
            hash: description.hash_u64(),
            ..AvatarPose::default()
        };
        Self {
            id,
            description: Arc::new(description),
            player,
            overrides: vec![None; n],
            world: vec![Mat4::IDENTITY; n],
            locals,
            rig,
            pose,
            placing: Placing::default(),
            root_track: RootTrack::default(),
            live: None,
            goals: goals::Goals::default(),
            recording: None,
            morph_clip: morph.clone(),
            morph_shown: morph.clone(),
            morph,
            expression_weights,
            expression_binds,
            layers: Vec::new(),
            replayed: None,
            roots,
        }
    }

    /// The avatar's number in binary frames.
    #[must_use]
    pub fn num(&self) -> u32 {
        self.description.num
    }

    /// Moves playback to scene clock `clock` (seconds) and evaluates the pose: clip (or rest),
    /// then overrides, then DOF limits. Returns whether its live driver went silent past the
    /// drive timeout in this tick (the drive ended: the server tells subscribers).
    pub fn tick(&mut self, clock: f64) -> bool {
        let before = self.player.current().map(Layer::time);
        self.player.set_clock(clock);
        for layer in &mut self.layers {
            layer.player.set_clock(clock);
        }
        self.layers.retain(|l| !l.finished());
        self.advance_placement(clock, before);
        let driver_left = self
            .live
            .as_ref()
            .is_some_and(|l| l.expired(Instant::now()));
        if driver_left {
            self.driver_gone();
        }
        self.evaluate();
        self.follow_gait();
        self.goals.forget_released(clock);
        if let Some(recorder) = &mut self.recording {
            // Only a changed rig or a clock going back can refuse a tick; neither happens to
            // an avatar in a ticking scene, and a refused tick is simply not in the clip.
            recorder.push(clock, &self.pose).ok();
        }
        driver_left
    }

    /// A tracker drive's `legs: locomotion`: plays the clip its solve picked
    /// ([`trackers::Trackers::gait`]) on the [`LOCOMOTION_LAYER`] over the legs, at its rate,
    /// cross-fading when the pick changes; fades the layer out once nothing picks.
    fn follow_gait(&mut self) {
        let gait = self
            .live
            .as_ref()
            .and_then(|l| l.trackers.as_ref())
            .and_then(trackers::Trackers::gait);
        let at = self
            .layers
            .iter()
            .position(|l| l.name == LOCOMOTION_LAYER && !l.stopping());
        let Some((clip, rate)) = gait else {
            if let Some(i) = at {
                self.layers[i].stop(Some(LOCOMOTION_FADE));
            }
            return;
        };
        let Some(clip) = self.rig.clips.get(clip).cloned() else {
            return;
        };
        if let Some(i) = at
            && let Some(playing) = self.layers[i].player.current_mut()
            && playing.clip.name() == clip.name()
        {
            playing.set_speed(rate);
            return;
        }
        let mask = JointMask {
            joints: vec!["l_hip".into(), "r_hip".into()],
            except: Vec::new(),
        };
        let Ok(owned) = layers::owned_joints(&self.rig, Some(&mask)) else {
            return;
        };
        let spec = layers::LayerSpec {
            owned,
            mask: Some(mask),
            additive: false,
            reference: AdditiveReference::Rest,
            weight: 1.0,
        };
        let played = Layer::new(clip, None, 0.0, rate, true);
        match at {
            Some(i) => self.layers[i].replace(played, spec, LOCOMOTION_FADE),
            None => {
                // A layer fading out under the name gives way to the new one.
                self.layers.retain(|l| l.name != LOCOMOTION_LAYER);
                self.layers.push(layers::ClipLayer::new(
                    LOCOMOTION_LAYER.into(),
                    played,
                    spec,
                    self.player.clock(),
                    LOCOMOTION_FADE,
                ));
            }
        }
    }

    /// Re-evaluates the pose at the current clock (after a command), without advancing: the
    /// clip (or rest), a live driver's pose over it, IK goals, the overrides on top, then every joint with DOF limits clamped to them
    /// (seed 002: every value set on a DOF, by a clip or a command, is clamped).
    pub fn evaluate(&mut self) {
        if self.replayed.is_some() {
            self.apply_replayed();
        } else {
            self.player
                .sample(self.rig.skeleton().rest(), &mut self.locals);
            self.apply_root_motion();
        }
        let rest = self.rig.skeleton().rest();
        for layer in &mut self.layers {
            layer.apply(rest, &self.roots, &mut self.locals);
        }
        if let Some(live) = &mut self.live {
            live.apply(
                &self.rig,
                self.placing.current().to_mat4(),
                self.player.clock(),
                &mut self.locals,
                &mut self.world,
            );
        }
        self.goals.solve(
            self.rig.skeleton(),
            self.placing.current().to_mat4(),
            self.player.clock(),
            &mut self.locals,
            &mut self.world,
        );
        for (local, o) in self.locals.iter_mut().zip(&self.overrides) {
            if let Some(q) = o {
                local.rotation = *q;
            }
        }
        // A replayed pose was clamped when it was recorded; clamping its quantised rotations
        // again could move them off what was streamed. What goes over it is clamped.
        let clamp = self.replayed.is_none()
            || self.live.is_some()
            || !self.layers.is_empty()
            || !self.goals.is_empty();
        for (local, limits) in self.locals.iter_mut().zip(&self.rig.limits) {
            if let Some(limits) = limits
                && clamp
            {
                local.rotation = limits.clamp(local.rotation);
            }
        }
        let d = &self.description;
        self.pose.rotations.clear();
        self.pose
            .rotations
            .extend(self.locals.iter().map(|t| t.rotation));
        self.pose.translations.clear();
        self.pose.translations.extend(
            d.translated_joints
                .iter()
                .map(|&j| self.locals[usize::from(j)].translation),
        );
        self.pose.scales.clear();
        self.pose.scales.extend(
            d.scaled_joints
                .iter()
                .map(|&j| self.locals[usize::from(j)].scale),
        );
        match &self.replayed {
            Some(p) if p.weights.len() == self.morph_clip.len() => {
                self.morph_clip.copy_from_slice(&p.weights);
            }
            _ => self.player.sample_weights(&mut self.morph_clip),
        }
        self.morph_shown.copy_from_slice(&self.morph);
        if self.expression_weights.iter().any(|&w| w > 0.0) {
            let shown = posecast_proto::expressions::shown_weights(
                &self.description.expression_binds,
                &self.expression_weights,
            );
            for (binds, e) in self.expression_binds.iter().zip(shown) {
                for &(c, w) in binds {
                    if let Some(slot) = self.morph_shown.get_mut(c) {
                        *slot += e * w;
                    }
                }
            }
        }
        for (shown, clip) in self.morph_shown.iter_mut().zip(&self.morph_clip) {
            *shown = shown.min(1.0).max(*clip);
        }
        // As streamed: quantised, so JSON and binary subscribers see the same weights.
        self.pose.weights.clear();
        self.pose.weights.extend(
            self.morph_shown
                .iter()
                .map(|&w| morph::weight_value(morph::weight_level(w))),
        );
    }

    /// The replayed pose ([`Avatar::replayed`]) as the locals: every rotation, the streamed
    /// translations and scales (the others at rest), and its placement.
    fn apply_replayed(&mut self) {
        let Some(p) = &self.replayed else { return };
        let rest = self.rig.skeleton().rest();
        self.locals.copy_from_slice(rest);
        for (local, q) in self.locals.iter_mut().zip(&p.rotations) {
            local.rotation = *q;
        }
        let d = &self.description;
        for (&j, t) in d.translated_joints.iter().zip(&p.translations) {
            if let Some(local) = self.locals.get_mut(usize::from(j)) {
                local.translation = *t;
            }
        }
        for (&j, s) in d.scaled_joints.iter().zip(&p.scales) {
            if let Some(local) = self.locals.get_mut(usize::from(j)) {
                local.scale = *s;
            }
        }
        self.placing = Placing::new(p.placement);
        self.pose.placement = p.placement;
    }

    /// The slot a morph weight's `name` sets: an expression the file defines (its
    /// description's `expression_binds`, by name or VRM 0.x preset name: slot
    /// `channels + k` for the `k`th), else one of the avatar's morph channels (its index), else
    /// a standard expression name its description maps onto one (`proto::expressions`).
    #[must_use]
    pub fn morph_channel(&self, name: &str) -> Option<usize> {
        let d = &self.description;
        posecast_proto::expressions::find_expression(&d.expression_binds, name)
            .map(|k| d.morph_targets.len() + k)
            .or_else(|| {
                posecast_proto::expressions::resolve(name, &d.morph_targets, &d.expressions)
            })
    }

    /// Sets morph weights by slot ([`Avatar::morph_channel`]; `reset`: every other channel
    /// and expression to 0 first) and re-evaluates the pose. Slots past the channels and
    /// expressions are ignored; weights are clamped to `[0, 1]` (callers check them first:
    /// `morph::check_weight`).
    pub fn set_morph(&mut self, weights: &[(usize, f32)], reset: bool) {
        if reset {
            self.morph.iter_mut().for_each(|w| *w = 0.0);
            self.expression_weights.iter_mut().for_each(|w| *w = 0.0);
        }
        self.store_morph(weights);
        self.evaluate();
    }

    /// Sets morph weights by slot without evaluating the pose (the next tick does): for
    /// live drivers and VMC, whose packets come faster than ticks. Clamped like
    /// [`Avatar::set_morph`].
    pub fn store_morph(&mut self, weights: &[(usize, f32)]) {
        let channels = self.morph.len();
        for &(c, w) in weights {
            let slot = if c < channels {
                self.morph.get_mut(c)
            } else {
                self.expression_weights.get_mut(c - channels)
            };
            if let Some(slot) = slot {
                *slot = if w.is_nan() { 0.0 } else { w.clamp(0.0, 1.0) };
            }
        }
    }

    /// Morph weights above 0 by channel name (for `get_avatar`).
    #[must_use]
    pub fn morph_weights(&self) -> std::collections::BTreeMap<String, f32> {
        self.description
            .morph_targets
            .iter()
            .zip(&self.pose.weights)
            .filter(|(_, w)| **w > 0.0)
            .map(|(n, w)| (n.clone(), *w))
            .collect()
    }

    /// The weights set on channels (not the clip's, not the expressions'), above 0, by
    /// channel name: what a snapshot keeps.
    #[must_use]
    pub fn set_channel_weights(&self) -> std::collections::BTreeMap<String, f32> {
        self.description
            .morph_targets
            .iter()
            .zip(&self.morph)
            .filter(|(_, w)| **w > 0.0)
            .map(|(n, w)| (n.clone(), *w))
            .collect()
    }

    /// The weights set on the file's expressions, above 0, by expression name.
    #[must_use]
    pub fn set_expression_weights(&self) -> std::collections::BTreeMap<String, f32> {
        self.description
            .expression_binds
            .iter()
            .zip(&self.expression_weights)
            .filter(|(_, w)| **w > 0.0)
            .map(|(e, w)| (e.name.clone(), *w))
            .collect()
    }

    /// The pose to stream.
    #[must_use]
    pub fn pose(&self) -> &AvatarPose {
        &self.pose
    }

    /// Starts a clip (an avatar being replayed leaves the replay: the clip takes over).
    pub fn play(&mut self, layer: Layer, fade: f32) {
        self.replayed = None;
        self.player.play(layer, fade);
        self.evaluate();
    }

    /// The joint's rotation normalised and clamped to its DOF limits (if the rig has any), or
    /// `None` when that is not a finite unit quaternion.
    fn limited(&self, joint: usize, q: Quat) -> Option<Quat> {
        let q = posecast_proto::unit_quat(q.to_array())?;
        let q = match self.rig.limits.get(joint) {
            Some(Some(limits)) => limits.clamp(q),
            _ => q,
        };
        posecast_proto::unit_quat(q.to_array())
    }

    /// Overrides a joint's local rotation (clamped to its limits). Returns what was set.
    ///
    /// # Errors
    /// [`InvalidRotation`] (nothing changed) when `q` is not a rotation: a non-finite
    /// component, a zero quaternion, or one whose normalisation overflows.
    pub fn set_rotation(&mut self, joint: usize, q: Quat) -> Result<Quat, InvalidRotation> {
        let q = self
            .limited(joint, q)
            .ok_or(InvalidRotation(q.to_array()))?;
        self.overrides[joint] = Some(q);
        self.evaluate();
        Ok(q)
    }

    /// Local increment `Ul' = incr · Ul` on the joint's current rotation.
    ///
    /// # Errors
    /// As [`Avatar::set_rotation`].
    pub fn rotate_local(&mut self, joint: usize, incr: Quat) -> Result<Quat, InvalidRotation> {
        let current = self.locals[joint].rotation;
        self.set_rotation(joint, incr * current)
    }

    /// World-space increment: the joint's world frame turns by `u` about the joint's own world
    /// position, `W' = U W` with `U = T(p) R(u) T(−p)`; its local transform becomes
    /// `D' = W_parent⁻¹ U W` (seed 001), whose rotation is kept (its translation equals the old
    /// one because the pivot is the joint's origin).
    ///
    /// # Errors
    /// When `D'` is not a rotation (a sheared or mirrored rig), or `u` is not one.
    pub fn rotate_world(&mut self, joint: usize, u: Quat) -> Result<Quat, RotateError> {
        let skeleton = self.rig.skeleton();
        forward_kinematics(skeleton, &self.locals, &mut self.world);
        let w = self.world[joint];
        let parent = skeleton.parents()[joint].map_or(Mat4::IDENTITY, |p| self.world[p]);
        let pivot = w.w_axis.truncate();
        let u = posecast_proto::unit_quat(u.to_array()).ok_or(InvalidRotation(u.to_array()))?;
        let d = world_increment_local(parent, rotation_about(pivot, u), w);
        let t = Transform::try_from_mat4(&d)?;
        Ok(self.set_rotation(joint, t.rotation)?)
    }

    /// Releases one joint's override, or all.
    pub fn release(&mut self, joint: Option<usize>) {
        match joint {
            Some(j) => self.overrides[j] = None,
            None => self.overrides.iter_mut().for_each(|o| *o = None),
        }
        self.evaluate();
    }

    /// The world matrices of the current pose.
    #[must_use]
    pub fn world(&mut self) -> &[Mat4] {
        forward_kinematics(self.rig.skeleton(), &self.locals, &mut self.world);
        &self.world
    }

    /// Joint `joint`'s matrix in the scene's space: its world matrix with the avatar's
    /// placement, `P · W_j` (what a goal relative to the joint is given in).
    #[must_use]
    pub fn scene_matrix(&mut self, joint: usize) -> Mat4 {
        let placement = self.placing.current().to_mat4();
        placement * self.world()[joint]
    }

    /// The state shown to clients.
    #[must_use]
    pub fn state(&self, scene: &SceneId) -> AvatarState {
        let layer = self.player.current();
        AvatarState {
            avatar: self.id.clone(),
            scene: scene.clone(),
            asset: self.rig.name.clone(),
            clip: layer.map(|l| l.clip.name().to_string()),
            clip_asset: layer.and_then(|l| l.source_asset.clone()),
            time: layer.map_or(0.0, Layer::clip_time),
            speed: layer.map_or(1.0, Layer::speed),
            looping: layer.is_none_or(|l| l.looping),
            paused: layer.is_some_and(Layer::paused),
            overrides: self
                .overrides
                .iter()
                .enumerate()
                .filter(|(_, o)| o.is_some())
                .map(|(j, _)| self.rig.skeleton().names()[j].clone())
                .collect(),
            placement: self.placing.current(),
            root_motion: layer.map(|l| l.root_motion),
            driven: self.live.is_some(),
            driver: self
                .live
                .as_ref()
                .filter(|l| l.driver.is_some())
                .and_then(|l| l.by.clone()),
            recording: self.recording.as_ref().map(|r| r.name().to_owned()),
            blend_shapes: self
                .live
                .as_ref()
                .map(|l| l.blend_shapes.clone())
                .unwrap_or_default(),
            fade: self.player.fade(),
            ik_goals: self
                .goals
                .goals
                .iter()
                .map(|g| self.rig.skeleton().names()[g.effector].clone())
                .collect(),
            looking: self.goals.gaze.is_some(),
            morph_weights: self.morph_weights(),
            layers: self.layers.iter().map(layers::ClipLayer::state).collect(),
        }
    }
}

/// The description's standard-name map: found by name ([`auto_map`]), the configured
/// corrections applied, and the names the file's own expressions define left out (those
/// resolve to the file's expressions first).
///
/// [`auto_map`]: posecast_proto::expressions::auto_map
fn expression_map(
    channels: &[String],
    defs: &[posecast_proto::expressions::Expression],
    corrections: Option<&std::collections::BTreeMap<String, String>>,
) -> std::collections::BTreeMap<String, String> {
    use posecast_proto::expressions::{auto_map, corrected, find_expression};
    let mut map = auto_map(channels);
    if let Some(c) = corrections {
        // Checked when the rig was normalised; a stale option keeps the guesses.
        map = corrected(map.clone(), c, channels).unwrap_or(map);
    }
    map.retain(|name, _| find_expression(defs, name).is_none());
    map
}
