//! Clip layers (issue 29 goal 4): clips played over the avatar's clip on a joint mask (the upper
//! body waving over a walk), replacing the rotations of the joints they own or adding to them
//! (a breathing or nodding layer over anything).
//!
//! Each layer has its own [`Player`], so playing another clip on a layer cross-fades there as
//! `play` does for the avatar's clip. A layer's weight at scene clock `t` is
//! `weight · ramp_in(t) · (1 − ramp_out(t))`, the ramps linear over the layer's fades, and for
//! each joint `j` it owns, with `L_j` the layer clip's local rotation and `Q_j` the pose below:
//!
//! - replacing: `Q_j ← slerp(Q_j, L_j, w)` (and a non-root joint's translation lerped);
//! - additive: `Q_j ← Q_j · slerp(1, R_j⁻¹ · L_j, w)` with `R_j` the reference rotation — the
//!   rig's rest rotation by default, or the clip's first frame
//!   ([`AdditiveReference::FirstFrame`]): the rotation the clip turns the joint through from
//!   it (on an H-Anim neutral rig with the rest reference, the clip's own local rotation),
//!   added on top of what is there.
//!
//! Root motion is the avatar's clip's; a layer's clip moves no root.

use super::playback::{DEFAULT_FADE, Layer, Player};
use glam::Quat;
use posecast_proto::Transform;
use posecast_proto::command::{AdditiveReference, JointMask, LayerState};
use posecast_rigs::rig::Rig;

/// One clip layer of an avatar.
#[derive(Debug)]
pub struct ClipLayer {
    /// The layer's name.
    pub name: String,
    /// Its clips, with their own cross-fades.
    pub player: Player,
    /// The mask it was given (kept to report and to restore).
    pub mask: Option<JointMask>,
    /// Which joints it owns.
    owned: Vec<bool>,
    /// Adds to the pose below instead of replacing it.
    pub additive: bool,
    /// What an additive layer's rotations are measured from.
    pub reference: AdditiveReference,
    /// The current clip's first frame (its reference pose when
    /// [`AdditiveReference::FirstFrame`]), sampled on first use.
    first_frame: Option<Vec<Transform>>,
    /// Its weight at full strength, 0 to 1.
    pub weight: f32,
    /// Scene clock and duration of its fade-in.
    fade_in: (f64, f32),
    /// Scene clock and duration of its fade-out, once stopped.
    fade_out: Option<(f64, f32)>,
    scratch: Vec<Transform>,
}

/// Why a mask is refused.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum MaskError {
    /// A name neither the rig's nor one of its H-Anim names.
    #[error("the rig has no joint {0:?} (neither its own name nor an H-Anim name it maps)")]
    UnknownJoint(String),
    /// The mask leaves no joint.
    #[error("the mask leaves no joint to the layer")]
    Empty,
}

/// The joints `mask` gives a layer on `rig` (`None`: all).
///
/// # Errors
/// A name the rig does not have; a mask that leaves nothing.
pub fn owned_joints(rig: &Rig, mask: Option<&JointMask>) -> Result<Vec<bool>, MaskError> {
    let skeleton = rig.skeleton();
    let n = skeleton.len();
    let Some(mask) = mask else {
        return Ok(vec![true; n]);
    };
    let find = |name: &String| {
        skeleton
            .find(name)
            .or_else(|| rig.hanim.iter().position(|h| h.as_deref() == Some(name)))
            .ok_or_else(|| MaskError::UnknownJoint(name.clone()))
    };
    let from: Vec<usize> = mask.joints.iter().map(find).collect::<Result<_, _>>()?;
    let except: Vec<usize> = mask.except.iter().map(find).collect::<Result<_, _>>()?;
    let parents = skeleton.parents();
    // Joints are parent-before-child: a joint is under `set` when it or an ancestor is in it.
    let under = |set: &[usize]| {
        let mut marked = vec![false; n];
        for j in 0..n {
            marked[j] = set.contains(&j) || parents[j].is_some_and(|p| marked[p]);
        }
        marked
    };
    let (inside, outside) = (under(&from), under(&except));
    let owned: Vec<bool> = inside.iter().zip(&outside).map(|(i, o)| *i && !o).collect();
    if owned.iter().any(|&o| o) {
        Ok(owned)
    } else {
        Err(MaskError::Empty)
    }
}

/// How a layer applies: the joints it owns (from [`owned_joints`]), the mask they came from,
/// replacing or adding, and its weight.
#[derive(Debug, Clone)]
pub struct LayerSpec {
    /// Which joints it owns.
    pub owned: Vec<bool>,
    /// The mask given (kept to report and to restore).
    pub mask: Option<JointMask>,
    /// Adds to the pose below instead of replacing it.
    pub additive: bool,
    /// What an additive layer's rotations are measured from.
    pub reference: AdditiveReference,
    /// Its weight at full strength (clamped to 0–1).
    pub weight: f32,
}

impl ClipLayer {
    /// A layer named `name` starting to play `clip` at scene clock `clock`, fading in over
    /// `fade` seconds.
    #[must_use]
    pub fn new(name: String, clip: Layer, spec: LayerSpec, clock: f64, fade: f32) -> Self {
        let mut player = Player::new();
        player.set_clock(clock);
        player.play(clip, 0.0);
        Self {
            name,
            player,
            mask: spec.mask,
            owned: spec.owned,
            additive: spec.additive,
            reference: spec.reference,
            first_frame: None,
            weight: spec.weight.clamp(0.0, 1.0),
            fade_in: (clock, fade.max(0.0)),
            fade_out: None,
            scratch: Vec::new(),
        }
    }

    /// Plays `clip` on the layer, cross-fading from what it played over `fade` seconds; the
    /// mask, mode and weight change at once, and a layer fading out comes back.
    pub fn replace(&mut self, clip: Layer, spec: LayerSpec, fade: f32) {
        self.first_frame = None;
        self.player.play(clip, fade);
        self.owned = spec.owned;
        self.mask = spec.mask;
        self.additive = spec.additive;
        self.reference = spec.reference;
        self.weight = spec.weight.clamp(0.0, 1.0);
        if self.fade_out.take().is_some() {
            self.fade_in = (self.player.clock(), fade.max(0.0));
        }
    }

    /// Starts fading the layer out over `fade` seconds (default [`DEFAULT_FADE`]).
    pub fn stop(&mut self, fade: Option<f32>) {
        let clock = self.player.clock();
        self.fade_out = Some((clock, fade.unwrap_or(DEFAULT_FADE).max(0.0)));
    }

    /// Whether it is fading out (after [`ClipLayer::stop`]).
    #[must_use]
    pub fn stopping(&self) -> bool {
        self.fade_out.is_some()
    }

    /// Whether it has faded out completely (and can be dropped).
    #[must_use]
    pub fn finished(&self) -> bool {
        self.fade_out
            .is_some_and(|(started, d)| ramp(self.player.clock(), started, d) >= 1.0)
    }

    /// Its weight now, fades included.
    #[must_use]
    pub fn current_weight(&self) -> f32 {
        let clock = self.player.clock();
        let up = ramp(clock, self.fade_in.0, self.fade_in.1);
        let down = self
            .fade_out
            .map_or(0.0, |(started, d)| ramp(clock, started, d));
        self.weight * up * (1.0 - down)
    }

    /// Applies the layer to `locals` (the pose below it), as the module docs say. `rest`: the
    /// rig's rest pose; `roots`: which joints are roots (their translation is left alone).
    pub fn apply(&mut self, rest: &[Transform], roots: &[bool], locals: &mut [Transform]) {
        let w = self.current_weight();
        if w <= 0.0 {
            return;
        }
        self.scratch.resize(rest.len(), Transform::IDENTITY);
        self.player.sample(rest, &mut self.scratch);
        if self.additive
            && self.reference == AdditiveReference::FirstFrame
            && self.first_frame.is_none()
        {
            let mut first = rest.to_vec();
            if let Some(layer) = self.player.current() {
                layer.clip.sample(layer.clip.start(), rest, &mut first);
            }
            self.first_frame = Some(first);
        }
        for (j, local) in locals.iter_mut().enumerate() {
            if !self.owned.get(j).copied().unwrap_or(false) {
                continue;
            }
            let clip = self.scratch[j];
            if self.additive {
                let reference = match self.reference {
                    AdditiveReference::Rest => rest[j],
                    AdditiveReference::FirstFrame => self
                        .first_frame
                        .as_ref()
                        .and_then(|f| f.get(j).copied())
                        .unwrap_or(rest[j]),
                };
                let delta = reference.rotation.inverse() * clip.rotation;
                local.rotation = (local.rotation * Quat::IDENTITY.slerp(delta, w)).normalize();
                if !roots[j] {
                    local.translation += w * (clip.translation - reference.translation);
                }
            } else {
                local.rotation = local.rotation.slerp(clip.rotation, w).normalize();
                if !roots[j] {
                    local.translation = local.translation.lerp(clip.translation, w);
                }
            }
        }
    }

    /// What `get_avatar` reports.
    #[must_use]
    pub fn state(&self) -> LayerState {
        let clip = self.player.current();
        LayerState {
            layer: self.name.clone(),
            clip: clip.map(|c| c.clip.name().to_string()).unwrap_or_default(),
            time: clip.map_or(0.0, Layer::clip_time),
            speed: clip.map_or(1.0, Layer::speed),
            additive: self.additive,
            weight: self.current_weight(),
            joints: self.owned.iter().filter(|&&o| o).count(),
        }
    }
}

/// 0 at `started`, rising linearly to 1 over `duration` seconds (1 at once for 0).
fn ramp(clock: f64, started: f64, duration: f32) -> f32 {
    if duration <= 0.0 {
        return 1.0;
    }
    ((clock - started) / f64::from(duration)).clamp(0.0, 1.0) as f32
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;
    use posecast_rigs::clip::{Clip, JointChannels, RotationChannel, Track};
    use std::sync::Arc;

    /// A two-joint clip holding joint 1 at `q` (joint 0 not animated).
    fn holding(q: Quat) -> Layer {
        let channels = vec![
            JointChannels::default(),
            JointChannels {
                rotation: Some(RotationChannel::Keys(Track::constant(q))),
                ..Default::default()
            },
        ];
        Layer::new(
            Arc::new(Clip::new("hold", channels, None).unwrap()),
            None,
            0.0,
            1.0,
            true,
        )
    }

    /// Replacing and adding, on a rig whose rest rotation is not the identity, derived by hand.
    #[test]
    fn replace_and_add_against_the_rest_pose() {
        let rest_q = Quat::from_rotation_z(0.4);
        let rest = [
            Transform::IDENTITY,
            Transform {
                rotation: rest_q,
                translation: Vec3::Y,
                ..Transform::IDENTITY
            },
        ];
        let roots = [true, false];
        let below = Quat::from_rotation_x(0.3);
        let clip_q = Quat::from_rotation_z(0.4) * Quat::from_rotation_y(0.5);
        let start = |additive| {
            let spec = LayerSpec {
                owned: vec![false, true],
                mask: None,
                additive,
                reference: AdditiveReference::Rest,
                weight: 0.5,
            };
            let mut l = ClipLayer::new("l".into(), holding(clip_q), spec, 0.0, 0.0);
            let mut locals = rest;
            locals[1].rotation = below;
            l.apply(&rest, &roots, &mut locals);
            locals
        };
        let close = |a: Quat, b: Quat| a.dot(b).abs() > 1.0 - 1e-6;
        // Replacing at weight 0.5: halfway from the pose below to the clip's rotation.
        let replaced = start(false);
        assert!(
            close(replaced[1].rotation, below.slerp(clip_q, 0.5)),
            "{:?}",
            replaced[1]
        );
        assert_eq!(replaced[0], rest[0], "joint 0 is not owned");
        // Adding: the clip turns the joint 0.5 rad about Y from its rest; half of that on top.
        let added = start(true);
        let want = below * Quat::from_rotation_y(0.25);
        assert!(
            close(added[1].rotation, want),
            "{:?} against {want:?}",
            added[1].rotation
        );
    }

    /// A first-frame reference adds only the clip's motion: at clip time 1 of a clip turning
    /// joint 1 from `q0` to `q1`, the joint gets `below · q0⁻¹ · q1`.
    #[test]
    fn a_first_frame_reference_adds_only_the_motion() {
        use posecast_rigs::clip::Interpolation;
        let (q0, q1) = (
            Quat::from_rotation_x(1.0),
            Quat::from_rotation_x(1.0) * Quat::from_rotation_z(0.3),
        );
        let track = Track::new(Interpolation::Linear, vec![0.0, 1.0], vec![q0, q1]).unwrap();
        let channels = vec![
            JointChannels::default(),
            JointChannels {
                rotation: Some(RotationChannel::Keys(track)),
                ..Default::default()
            },
        ];
        let clip = Arc::new(Clip::new("turn", channels, None).unwrap());
        let rest = [Transform::IDENTITY; 2];
        let below = Quat::from_rotation_y(0.2);
        let run = |reference| {
            let spec = LayerSpec {
                owned: vec![false, true],
                mask: None,
                additive: true,
                reference,
                weight: 1.0,
            };
            let played = Layer::new(clip.clone(), None, 1.0, 0.0, false);
            let mut l = ClipLayer::new("l".into(), played, spec, 0.0, 0.0);
            let mut locals = rest;
            locals[1].rotation = below;
            l.apply(&rest, &[true, false], &mut locals);
            locals[1].rotation
        };
        let close = |a: Quat, b: Quat| a.dot(b).abs() > 1.0 - 1e-6;
        let first = run(AdditiveReference::FirstFrame);
        assert!(
            close(first, below * Quat::from_rotation_z(0.3)),
            "{first:?}"
        );
        let from_rest = run(AdditiveReference::Rest);
        assert!(close(from_rest, below * q1), "{from_rest:?}");
    }

    #[test]
    fn fades_ramp_the_weight_in_and_out() {
        let spec = LayerSpec {
            owned: vec![true, true],
            mask: None,
            additive: false,
            reference: AdditiveReference::Rest,
            weight: 0.8,
        };
        let mut l = ClipLayer::new("l".into(), holding(Quat::IDENTITY), spec, 10.0, 0.5);
        assert_eq!(l.current_weight(), 0.0);
        l.player.set_clock(10.25);
        assert!((l.current_weight() - 0.4).abs() < 1e-6);
        l.player.set_clock(11.0);
        assert!((l.current_weight() - 0.8).abs() < 1e-6);
        l.stop(Some(1.0));
        l.player.set_clock(11.5);
        assert!((l.current_weight() - 0.4).abs() < 1e-6);
        assert!(!l.finished());
        l.player.set_clock(12.0);
        assert!(l.finished());
    }
}
