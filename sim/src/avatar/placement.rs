//! An avatar's world placement and what its clip's root motion does to it.
//!
//! - [`Placing`]: where the avatar stands, and a move in progress (`place_avatar … duration`):
//!   position lerped, rotation slerped, on the scene's f64 tick clock, so the placement at a
//!   tick depends only on that tick's clock.
//! - [`RootMotion`]: in place (the root's horizontal motion removed, its height kept) or
//!   accumulate (as authored, and each loop wrap moves the placement on by the clip's net
//!   horizontal root displacement, turned by the placement's rotation).

use super::playback::Layer;
use glam::Vec3;
use posecast_proto::Transform;
use posecast_proto::command::RootMotion;
use posecast_proto::placement::{MAX_PLACEMENT_METRES, Placement};
use posecast_rigs::clip::Clip;
use std::sync::Arc;

/// A move from one placement to another over a span of scene clock.
#[derive(Debug, Clone, Copy)]
struct Move {
    from: Placement,
    to: Placement,
    /// Scene clock (seconds) when the move started.
    start: f64,
    /// Seconds; > 0.
    duration: f64,
}

impl Move {
    fn at(&self, clock: f64) -> Placement {
        let w = ((clock - self.start) / self.duration).clamp(0.0, 1.0);
        self.from.interpolate(&self.to, w as f32)
    }
}

/// Where an avatar stands, and where it is going.
#[derive(Debug, Clone, Default)]
pub struct Placing {
    current: Placement,
    moving: Option<Move>,
}

impl Placing {
    /// Standing at `placement`.
    #[must_use]
    pub fn new(placement: Placement) -> Self {
        Self {
            current: placement,
            moving: None,
        }
    }

    /// The placement at the last tick or command.
    #[must_use]
    pub fn current(&self) -> Placement {
        self.current
    }

    /// Where the avatar ends up when the move in progress (if any) is over: what is stored.
    #[must_use]
    pub fn target(&self) -> Placement {
        self.moving.map_or(self.current, |m| m.to)
    }

    /// Starts a move to `to` at scene clock `clock`, over `duration` seconds (≤ 0: at once).
    pub fn place(&mut self, to: Placement, duration: f64, clock: f64) {
        if duration > 0.0 {
            self.moving = Some(Move {
                from: self.current,
                to,
                start: clock,
                duration,
            });
        } else {
            self.current = to;
            self.moving = None;
        }
    }

    /// Moves to scene clock `clock`.
    pub fn set_clock(&mut self, clock: f64) {
        if let Some(m) = self.moving {
            self.current = m.at(clock);
            if clock >= m.start + m.duration {
                self.current = m.to;
                self.moving = None;
            }
        }
    }

    /// Shifts the placement (and a move in progress) by `offset` metres, world space, kept
    /// within ±[`MAX_PLACEMENT_METRES`] (an avatar walking for ever stops at the edge rather
    /// than reach a position no command could set).
    pub fn shift(&mut self, offset: Vec3) {
        let bound = Vec3::splat(MAX_PLACEMENT_METRES);
        let shift = |p: &mut Vec3| *p = (*p + offset).clamp(-bound, bound);
        shift(&mut self.current.position);
        if let Some(m) = &mut self.moving {
            shift(&mut m.from.position);
            shift(&mut m.to.position);
        }
    }
}

/// `play`'s default: in place for looping clips, accumulate (as authored) otherwise.
#[must_use]
pub fn default_root_motion(looping: bool) -> RootMotion {
    if looping {
        RootMotion::InPlace
    } else {
        RootMotion::Accumulate
    }
}

/// A clip's root translations at its start and its net horizontal displacement, per root
/// joint; computed once per clip played.
#[derive(Debug, Clone, Default)]
pub struct RootTrack {
    clip: Option<Arc<Clip>>,
    /// `(joint, translation at the clip's start, net horizontal displacement start → end)`.
    roots: Vec<(usize, Vec3, Vec3)>,
}

impl RootTrack {
    /// Samples `clip`'s roots (joints without a parent) at its start and end, unless this
    /// track already holds them.
    pub fn prepare(&mut self, clip: &Arc<Clip>, parents: &[Option<usize>], rest: &[Transform]) {
        if self.clip.as_ref().is_some_and(|c| Arc::ptr_eq(c, clip)) {
            return;
        }
        let mut start = rest.to_vec();
        let mut end = rest.to_vec();
        clip.sample(clip.start(), rest, &mut start);
        clip.sample(clip.end(), rest, &mut end);
        self.roots = parents
            .iter()
            .enumerate()
            .filter(|(_, p)| p.is_none())
            .filter_map(|(j, _)| {
                let a = start.get(j)?.translation;
                let b = end.get(j)?.translation;
                Some((j, a, horizontal(b - a)))
            })
            .collect();
        self.clip = Some(clip.clone());
    }

    /// In place: every root's horizontal translation held at the clip's start value.
    pub fn hold_in_place(&self, locals: &mut [Transform]) {
        for &(j, start, _) in &self.roots {
            if let Some(l) = locals.get_mut(j) {
                l.translation.x = start.x;
                l.translation.z = start.z;
            }
        }
    }

    /// The first root's net horizontal displacement over one cycle (avatar space, metres).
    #[must_use]
    pub fn net(&self) -> Vec3 {
        self.roots.first().map_or(Vec3::ZERO, |r| r.2)
    }
}

fn horizontal(v: Vec3) -> Vec3 {
    Vec3::new(v.x, 0.0, v.z)
}

/// Loop wraps of a looping layer between two unwrapped clip times (negative when playing
/// backwards): `⌊t1/d⌋ − ⌊t0/d⌋`.
#[must_use]
pub fn wraps(layer: &Layer, t0: f64, t1: f64) -> f64 {
    let d = f64::from(layer.clip.duration());
    if !layer.looping || d <= 0.0 || !t0.is_finite() || !t1.is_finite() {
        return 0.0;
    }
    (t1 / d).floor() - (t0 / d).floor()
}

impl super::Avatar {
    /// Moves the placement to scene clock `clock`; with accumulated root motion, adds the
    /// loop wraps since `before` (the current layer's unwrapped clip time before the clock
    /// moved) times the clip's net displacement, turned by the placement's rotation.
    pub(super) fn advance_placement(&mut self, clock: f64, before: Option<f64>) {
        self.placing.set_clock(clock);
        let Some(layer) = self.player.current() else {
            return;
        };
        if layer.root_motion != RootMotion::Accumulate {
            return;
        }
        let n = before.map_or(0.0, |t0| wraps(layer, t0, layer.time()));
        if n == 0.0 {
            return;
        }
        let skeleton = self.rig.skeleton();
        self.root_track
            .prepare(&layer.clip, skeleton.parents(), skeleton.rest());
        let step = self.placing.current().rotation * (self.root_track.net() * n as f32);
        if step.is_finite() {
            self.placing.shift(step);
        }
    }

    /// After sampling: holds the roots in place when the current clip plays in place, and
    /// puts the placement into the pose to stream.
    pub(super) fn apply_root_motion(&mut self) {
        if let Some(layer) = self.player.current()
            && layer.root_motion == RootMotion::InPlace
        {
            let skeleton = self.rig.skeleton();
            self.root_track
                .prepare(&layer.clip, skeleton.parents(), skeleton.rest());
            self.root_track.hold_in_place(&mut self.locals);
        }
        self.pose.placement = self.placing.current();
    }

    /// `place_avatar`: moves to `to` over `duration` seconds of scene clock from now.
    pub fn place(&mut self, to: Placement, duration: f64) {
        self.placing.place(to, duration, self.player.clock());
        self.pose.placement = self.placing.current();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::avatar::Avatar;
    use glam::Quat;
    use posecast_proto::msg::AvatarId;
    use posecast_rigs::clip::{Interpolation, JointChannels, Track, VectorChannel};

    /// The built-in avatar playing a 1 s looping clip whose root walks 1 m along +Z (its
    /// height and the rest of the rig as at rest), in `mode`, standing at `placement`.
    fn walker(mode: RootMotion, placement: Placement) -> Avatar {
        let rig = Arc::new(posecast_rigs::builtin::rig().unwrap());
        let root = rig.skeleton().rest()[0].translation;
        let mut joints = vec![JointChannels::default(); rig.skeleton().len()];
        joints[0].translation = Some(VectorChannel::Keys(
            Track::new(
                Interpolation::Linear,
                vec![0.0, 1.0],
                vec![root, root + Vec3::Z],
            )
            .unwrap(),
        ));
        let clip = Arc::new(Clip::new("stride", joints, None).unwrap());
        let mut a = Avatar::new(AvatarId("w".into()), 0, rig);
        a.place(placement, 0.0);
        let mut layer = Layer::new(clip, None, 0.0, 1.0, true);
        layer.root_motion = mode;
        a.play(layer, 0.0);
        a
    }

    /// Ticks at 60 Hz to `seconds`; the root's world position (`placement · root`).
    fn run(a: &mut Avatar, seconds: f64) -> Vec3 {
        for seq in 0..=(seconds * 60.0).round() as u64 {
            a.tick(seq as f64 / 60.0);
        }
        let p = a.placing.current();
        p.position + p.rotation * a.locals[0].translation
    }

    #[test]
    fn accumulate_moves_the_placement_one_net_displacement_per_loop() {
        let mut a = walker(RootMotion::Accumulate, Placement::IDENTITY);
        let start = a.locals[0].translation;
        let world = run(&mut a, 3.5);
        // Three wraps: 3 m; and half a cycle into the fourth on top.
        assert!((a.placing.current().position - Vec3::new(0.0, 0.0, 3.0)).length() < 1e-4);
        assert!((world - (start + Vec3::new(0.0, 0.0, 3.5))).length() < 1e-3);
        // Turned by the placement: a walker facing +X walks along +X.
        let facing_x = Placement {
            position: Vec3::new(10.0, 0.0, 0.0),
            rotation: Quat::from_rotation_y(std::f32::consts::FRAC_PI_2),
        };
        let mut b = walker(RootMotion::Accumulate, facing_x);
        run(&mut b, 2.5);
        assert!((b.placing.current().position - Vec3::new(12.0, 0.0, 0.0)).length() < 1e-4);
    }

    #[test]
    fn in_place_keeps_the_root_over_the_placement_and_its_height() {
        let mut a = walker(RootMotion::InPlace, Placement::IDENTITY);
        let start = a.locals[0].translation;
        for t in [0.25, 1.5, 3.75] {
            let world = run(&mut a, t);
            assert!((world - start).length() < 1e-5, "{t}: {world}");
        }
        assert_eq!(a.placing.current(), Placement::IDENTITY);
        assert_eq!(default_root_motion(true), RootMotion::InPlace);
    }

    #[test]
    fn a_move_interpolates_on_the_clock_and_ends_at_its_target() {
        let to = Placement {
            position: Vec3::new(2.0, 0.0, 0.0),
            rotation: Quat::from_rotation_y(1.0),
        };
        let mut p = Placing::default();
        p.place(to, 2.0, 10.0);
        p.set_clock(11.0);
        assert!((p.current().position.x - 1.0).abs() < 1e-6);
        assert!((p.current().rotation.angle_between(Quat::IDENTITY) - 0.5).abs() < 1e-5);
        assert_eq!(p.target(), to);
        p.set_clock(12.5);
        assert_eq!(p.current(), to);
        p.place(Placement::IDENTITY, 0.0, 13.0);
        assert_eq!(p.current(), Placement::IDENTITY);
    }
}
