//! Clip playback on one avatar: a clock per clip (speed, loop, pause, seek) and a cross-fade
//! from the previous clip to the next, of the pose and of the morph weights the clips animate.

use posecast_proto::Transform;
use posecast_proto::command::{FadeState, RootMotion};
use posecast_rigs::clip::{Clip, Sampler};
use std::sync::Arc;

/// Default cross-fade duration, seconds.
pub const DEFAULT_FADE: f32 = 0.25;

/// One clip being played.
///
/// Its clock is not accumulated tick by tick (`time += dt · speed` in f32 drifts: −0.39 %
/// after ~2,000 s at 60 Hz, +5.5 % past 16,384 s). It is derived from the scene's tick clock in
/// f64: clip time `= anchor_time + (clock − anchor_clock) · speed`, re-anchored whenever speed,
/// pause or position change. Error stays far below 1 µs of clip time over 10⁷ ticks.
#[derive(Debug, Clone)]
pub struct Layer {
    /// The clip, already bound to the avatar's joints (retargeted when it came from another rig).
    pub clip: Arc<Clip>,
    /// The rig the clip was authored for, when retargeted.
    pub source_asset: Option<String>,
    /// Seconds of clip time per second of wall time.
    speed: f32,
    /// Loop, or hold the pose at the end (or start, playing backwards).
    pub looping: bool,
    /// A paused clock does not advance.
    paused: bool,
    /// What the clip's root translation does (see [`super::placement`]).
    pub root_motion: RootMotion,
    /// Clip time (seconds from the clip's start, unwrapped) at `anchor_clock`.
    anchor_time: f64,
    /// Scene clock (seconds) the anchor refers to.
    anchor_clock: f64,
    /// The scene clock at the last tick or command.
    clock: f64,
    sampler: Sampler,
    /// For each of the clip's morph tracks, the avatar's channel it drives (resolved on first
    /// use: a layer stays on one avatar).
    morph_slots: Option<Vec<Option<usize>>>,
}

impl Layer {
    /// A layer at clip time `start` (seconds from the clip's start); its clock starts when it
    /// is played ([`Player::play`]).
    #[must_use]
    pub fn new(
        clip: Arc<Clip>,
        source_asset: Option<String>,
        start: f32,
        speed: f32,
        looping: bool,
    ) -> Self {
        let sampler = clip.sampler();
        Self {
            clip,
            source_asset,
            speed,
            looping,
            paused: false,
            root_motion: super::placement::default_root_motion(looping),
            anchor_time: f64::from(start),
            anchor_clock: 0.0,
            clock: 0.0,
            sampler,
            morph_slots: None,
        }
    }

    /// Clip time (seconds from the clip's start) before wrapping, in f64.
    #[must_use]
    pub fn time(&self) -> f64 {
        if self.paused {
            self.anchor_time
        } else {
            self.anchor_time + (self.clock - self.anchor_clock) * f64::from(self.speed)
        }
    }

    /// The clip time wrapped (looping) or clamped into `[0, duration]`, in f64.
    #[must_use]
    pub fn clip_time_f64(&self) -> f64 {
        let d = f64::from(self.clip.duration().max(0.0));
        let t = self.time();
        if self.looping {
            if d > 0.0 { t.rem_euclid(d).min(d) } else { 0.0 }
        } else {
            t.clamp(0.0, d)
        }
    }

    /// The clip time wrapped (looping) or clamped into `[0, duration]`.
    #[must_use]
    pub fn clip_time(&self) -> f32 {
        self.clip_time_f64() as f32
    }

    /// Playback speed (clip seconds per second).
    #[must_use]
    pub fn speed(&self) -> f32 {
        self.speed
    }

    /// Whether the clock is stopped.
    #[must_use]
    pub fn paused(&self) -> bool {
        self.paused
    }

    /// Moves the anchor to now (keeping the clip time) so a change of speed or pause applies
    /// from this moment on. A looping clock is wrapped here, so the anchor stays small.
    fn reanchor(&mut self) {
        self.anchor_time = if self.looping {
            self.clip_time_f64()
        } else {
            self.time()
        };
        self.anchor_clock = self.clock;
    }

    /// Changes the speed from the current clock on.
    pub fn set_speed(&mut self, speed: f32) {
        self.reanchor();
        self.speed = speed;
    }

    /// Stops or restarts the clock.
    pub fn set_paused(&mut self, paused: bool) {
        self.reanchor();
        self.paused = paused;
    }

    /// Jumps to clip time `time` (seconds from the clip's start).
    pub fn seek(&mut self, time: f32) {
        self.anchor_time = f64::from(time);
        self.anchor_clock = self.clock;
    }

    /// Starts the layer's clock at scene clock `clock`.
    fn start_at(&mut self, clock: f64) {
        self.clock = clock;
        self.anchor_clock = clock;
    }

    fn set_clock(&mut self, clock: f64) {
        self.clock = clock;
    }

    fn sample(&mut self, rest: &[Transform], out: &mut [Transform]) {
        let t = self.clip.start() + self.clip_time();
        self.sampler.sample(&self.clip, t, rest, out);
    }

    /// Writes the weight of every channel the clip animates into `out` (one entry per channel
    /// of `channels`); the others are left as they are.
    fn sample_weights(&mut self, channels: &[String], out: &mut [f32]) {
        let clip = &self.clip;
        if clip.morphs().is_empty() {
            return;
        }
        let t = clip.start() + self.clip_time();
        let slots = self.morph_slots.get_or_insert_with(|| {
            clip.morphs()
                .iter()
                .map(|m| channels.iter().position(|c| *c == m.channel))
                .collect()
        });
        for (m, slot) in clip.morphs().iter().zip(slots.iter()) {
            if let Some(o) = slot.and_then(|c| out.get_mut(c)) {
                *o = m.sample(t);
            }
        }
    }
}

/// Fades kept at most under the current layer: a `play` beyond that many overlapping fades
/// freezes the oldest two into one still pose (continuous at that instant; see
/// [`Player::sample`]), so `play` spam cannot grow the stack or the tick's work.
pub const MAX_FADES: usize = 8;

/// What an avatar plays: the current layer and, under it, the layers still fading out.
///
/// **A fade stack.** Each `play … fade` puts the new layer on top of what was playing, at
/// weight 0 rising to 1 over the fade; a `play` during a fade pushes another one instead of
/// dropping the fade in progress (which made the pose jump: 28.6° in the black-box trial). The
/// pose is evaluated bottom up, `P = S₀; P ← blend(P, Sᵢ₊₁, wᵢ)` for each fade `i`, so a
/// new layer changes nothing at the instant it starts (`w = 0`) and every weight moves
/// continuously with the clock. Once a fade's weight reaches 1, it and everything below it
/// contribute nothing and are dropped.
#[derive(Debug, Default)]
pub struct Player {
    current: Option<Layer>,
    /// Fades under `current`, oldest first: `fading[i].from` is what the layer above it
    /// (`fading[i + 1].from`, or `current` for the newest) fades in over.
    fading: Vec<Fade>,
    /// The scene clock (seconds) at the last tick.
    clock: f64,
    scratch: Vec<Transform>,
    /// The avatar's morph channels (its description's `morph_targets`), which the clips'
    /// morph tracks are matched to by name.
    channels: Vec<String>,
    weight_scratch: Vec<f32>,
}

/// What a layer fades in over.
#[derive(Debug)]
enum Under {
    /// A clip that keeps playing while it fades out.
    Layer(Layer),
    /// A still pose and morph weights: the bottom of a stack that grew past [`MAX_FADES`],
    /// frozen at the tick it was collapsed (`name`: the clip it showed most of, for
    /// [`FadeState::from`]).
    Frozen {
        pose: Vec<Transform>,
        weights: Vec<f32>,
        name: String,
    },
}

impl Under {
    fn name(&self) -> &str {
        match self {
            Under::Layer(layer) => layer.clip.name(),
            Under::Frozen { name, .. } => name,
        }
    }

    fn source_asset(&self) -> Option<String> {
        match self {
            Under::Layer(layer) => layer.source_asset.clone(),
            Under::Frozen { .. } => None,
        }
    }

    fn set_clock(&mut self, clock: f64) {
        if let Under::Layer(layer) = self {
            layer.set_clock(clock);
        }
    }

    fn sample_weights(&mut self, channels: &[String], out: &mut [f32]) {
        match self {
            Under::Layer(layer) => layer.sample_weights(channels, out),
            Under::Frozen { weights, .. } => {
                for (o, w) in out.iter_mut().zip(weights.iter()) {
                    *o = *w;
                }
            }
        }
    }

    fn sample(&mut self, rest: &[Transform], out: &mut [Transform]) {
        match self {
            Under::Layer(layer) => layer.sample(rest, out),
            Under::Frozen { pose, .. } => {
                for (o, p) in out
                    .iter_mut()
                    .zip(pose.iter().chain(rest.iter().skip(pose.len())))
                {
                    *o = *p;
                }
            }
        }
    }
}

#[derive(Debug)]
struct Fade {
    from: Under,
    /// Scene clock at the start of the fade.
    started: f64,
    duration: f32,
}

impl Fade {
    fn weight(&self, clock: f64) -> f32 {
        ((clock - self.started) / f64::from(self.duration)).clamp(0.0, 1.0) as f32
    }
}

impl Player {
    /// Nothing playing: the avatar holds its rest pose.
    #[must_use]
    pub fn new() -> Self {
        Self::default()
    }

    /// The current layer.
    #[must_use]
    pub fn current(&self) -> Option<&Layer> {
        self.current.as_ref()
    }

    /// The current layer, to pause, seek or change speed.
    pub fn current_mut(&mut self) -> Option<&mut Layer> {
        self.current.as_mut()
    }

    /// The scene clock (seconds) at the last tick.
    #[must_use]
    pub fn clock(&self) -> f64 {
        self.clock
    }

    /// The newest cross-fade in progress, as clients see it (`AvatarState::fade`): the layer
    /// the current one fades in over.
    #[must_use]
    pub fn fade(&self) -> Option<FadeState> {
        self.fading.last().map(|f| FadeState {
            from: f.from.name().to_string(),
            from_asset: f.from.source_asset(),
            elapsed: (self.clock - f.started).max(0.0) as f32,
            duration: f.duration,
        })
    }

    /// Starts `layer` at the current clock, cross-fading from what plays now (the current
    /// layer and any fades still in progress under it) over `fade` seconds (0: cut).
    pub fn play(&mut self, mut layer: Layer, fade: f32) {
        layer.start_at(self.clock);
        let from = self.current.replace(layer);
        match from {
            Some(from) if fade > 0.0 => self.fading.push(Fade {
                from: Under::Layer(from),
                started: self.clock,
                duration: fade,
            }),
            _ => self.fading.clear(),
        }
    }

    /// Stops playing: the rest pose from now on.
    pub fn stop(&mut self) {
        self.current = None;
        self.fading.clear();
    }

    /// Moves every clock to scene clock `clock` (seconds; the tick's time, derived from its
    /// sequence number, so it never accumulates rounding).
    pub fn set_clock(&mut self, clock: f64) {
        self.clock = clock;
        if let Some(layer) = &mut self.current {
            layer.set_clock(clock);
        }
        for fade in &mut self.fading {
            fade.from.set_clock(clock);
        }
        // A finished fade hides everything below it, itself included.
        if let Some(done) = self.fading.iter().rposition(|f| f.weight(clock) >= 1.0) {
            self.fading.drain(..=done);
        }
    }

    /// The avatar's morph channels, which [`Player::sample_weights`] fills.
    pub fn set_morph_channels(&mut self, channels: Vec<String>) {
        self.channels = channels;
    }

    /// Writes the morph weights the clips animate into `out` (one per channel set with
    /// [`Player::set_morph_channels`]): the fade stack evaluated bottom up like the pose, each
    /// layer's weights blended linearly over those below by its fade's weight; a channel a clip
    /// does not animate is 0 in it (so fading to a clip without a face relaxes the face). No
    /// layer: all 0.
    pub fn sample_weights(&mut self, out: &mut [f32]) {
        out.fill(0.0);
        if self.channels.is_empty() {
            return;
        }
        let channels = &self.channels;
        let Some(current) = &mut self.current else {
            return;
        };
        let Some((first, _)) = self.fading.split_first_mut() else {
            current.sample_weights(channels, out);
            return;
        };
        first.from.sample_weights(channels, out);
        self.weight_scratch.resize(out.len(), 0.0);
        let clock = self.clock;
        for i in 0..self.fading.len() {
            let w = self.fading[i].weight(clock);
            self.weight_scratch.fill(0.0);
            match self.fading.get_mut(i + 1) {
                Some(next) => next.from.sample_weights(channels, &mut self.weight_scratch),
                None => current.sample_weights(channels, &mut self.weight_scratch),
            }
            for (o, s) in out.iter_mut().zip(&self.weight_scratch) {
                *o += (s - *o) * w;
            }
        }
    }

    /// Writes the pose into `out` (one transform per joint): the fade stack evaluated bottom
    /// up, each layer blended over the pose below it by its fade's `w = elapsed / duration`
    /// (slerp of rotations, lerp of translations and scales, so each fade is continuous at both
    /// ends). No layer: `rest`.
    pub fn sample(&mut self, rest: &[Transform], out: &mut [Transform]) {
        if self.fading.len() > MAX_FADES {
            self.collapse_bottom(rest, out.len());
        }
        self.sample_stack(rest, out);
    }

    /// The stack's pose, bottom up (no collapsing).
    fn sample_stack(&mut self, rest: &[Transform], out: &mut [Transform]) {
        let Some(current) = &mut self.current else {
            let n = out.len().min(rest.len());
            out[..n].copy_from_slice(&rest[..n]);
            return;
        };
        let Some((first, _)) = self.fading.split_first_mut() else {
            current.sample(rest, out);
            return;
        };
        first.from.sample(rest, out);
        self.scratch.resize(out.len(), Transform::IDENTITY);
        let clock = self.clock;
        for i in 0..self.fading.len() {
            let w = self.fading[i].weight(clock);
            match self.fading.get_mut(i + 1) {
                Some(next) => next.from.sample(rest, &mut self.scratch),
                None => current.sample(rest, &mut self.scratch),
            }
            for (o, s) in out.iter_mut().zip(&self.scratch) {
                *o = o.blend(s, w);
            }
        }
    }

    /// Replaces the two oldest entries of the stack by the pose they make now, held still: the
    /// stack's pose at this clock is unchanged (the same blend, computed once).
    fn collapse_bottom(&mut self, rest: &[Transform], joints: usize) {
        let (Some(bottom), Some(next)) = (self.fading.first(), self.fading.get(1)) else {
            return;
        };
        let w = bottom.weight(self.clock);
        let name = if w < 0.5 {
            bottom.from.name()
        } else {
            next.from.name()
        }
        .to_string();
        let mut pose = vec![Transform::IDENTITY; joints];
        let mut above = vec![Transform::IDENTITY; joints];
        self.fading[0].from.sample(rest, &mut pose);
        self.fading[1].from.sample(rest, &mut above);
        for (p, a) in pose.iter_mut().zip(&above) {
            *p = p.blend(a, w);
        }
        let mut weights = vec![0.0; self.channels.len()];
        let mut weights_above = vec![0.0; self.channels.len()];
        self.fading[0]
            .from
            .sample_weights(&self.channels, &mut weights);
        self.fading[1]
            .from
            .sample_weights(&self.channels, &mut weights_above);
        for (o, a) in weights.iter_mut().zip(&weights_above) {
            *o += (a - *o) * w;
        }
        self.fading.remove(0);
        self.fading[0].from = Under::Frozen {
            pose,
            weights,
            name,
        };
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::{Quat, Vec3};
    use posecast_rigs::clip::{Interpolation, JointChannels, RotationChannel, Track};
    use proptest::prelude::*;

    /// A one-joint clip swinging about `axis` by `amplitude · sin(2π t / duration)` radians: a
    /// seamless loop whose angular speed is at most `amplitude · 2π / duration` (keys every
    /// ~0.05 s, interpolated).
    fn swinging(name: &str, axis: Vec3, amplitude: f32, duration: f32) -> Arc<Clip> {
        let n = (duration / 0.05).ceil() as usize;
        let times: Vec<f32> = (0..=n).map(|k| k as f32 * duration / n as f32).collect();
        let values: Vec<Quat> = times
            .iter()
            .map(|t| {
                let phase = std::f32::consts::TAU * t / duration;
                Quat::from_axis_angle(axis.normalize(), amplitude * phase.sin())
            })
            .collect();
        let track = Track::new(Interpolation::Linear, times, values).unwrap();
        let joint = JointChannels {
            rotation: Some(RotationChannel::Keys(track)),
            ..JointChannels::default()
        };
        Arc::new(Clip::new(name, vec![joint], Some((0.0, duration))).unwrap())
    }

    /// The angle (radians) between the joint's rotations in two poses.
    fn angle(a: &[Transform], b: &[Transform]) -> f32 {
        // atan2 of the relative rotation's parts, not acos of a dot: exact near zero in f32.
        let d = a[0].rotation.inverse() * b[0].rotation;
        2.0 * d.xyz().length().atan2(d.w.abs())
    }

    fn pose(player: &mut Player) -> Vec<Transform> {
        let rest = [Transform::IDENTITY];
        let mut out = [Transform::IDENTITY];
        player.sample(&rest, &mut out);
        out.to_vec()
    }

    /// The black-box case: `play` while a fade is in progress. The fade in progress goes on
    /// under the new one, so the pose at the instant of the second `play` is unchanged (it
    /// jumped by the in-progress fade's share before: 45° here).
    #[test]
    fn play_during_a_fade_is_continuous() {
        let mut player = Player::new();
        player.play(Layer::new(still("a", 0.0), None, 0.0, 1.0, true), 0.0);
        player.play(Layer::new(still("b", 90.0), None, 0.0, 1.0, true), 1.0);
        player.set_clock(0.5);
        let before = pose(&mut player);
        assert!((angle(&before, &[Transform::IDENTITY]).to_degrees() - 45.0).abs() < 0.01);
        player.play(Layer::new(still("c", -90.0), None, 0.0, 1.0, true), 1.0);
        let after = pose(&mut player);
        assert!(
            angle(&before, &after) < 1e-5,
            "jumped {}°",
            angle(&before, &after).to_degrees()
        );
        // Both fades finish: the pose is c's alone, and the stack is empty again.
        player.set_clock(1.6);
        let end = pose(&mut player);
        let c = Quat::from_rotation_y((-90f32).to_radians());
        assert!(
            angle(
                &end,
                &[Transform {
                    rotation: c,
                    ..Transform::IDENTITY
                }]
            ) < 1e-4
        );
        assert!(player.fading.is_empty());
    }

    /// A one-joint clip holding a rotation of `deg` about Y.
    /// Morph weights cross-fade as the pose does: a clip holding `smile` at 1, faded over 1 s
    /// into one that animates no face, gives `1 − w`; tracks find their channel by name; nothing
    /// playing, and channels no clip animates, give 0; a stack collapsed past [`MAX_FADES`]
    /// keeps the weights it showed.
    #[test]
    fn morph_weights_cross_fade_with_the_clips() {
        let face = |w: f32| {
            let clip = Clip::new("face", vec![JointChannels::default()], Some((0.0, 1.0)))
                .unwrap()
                .with_morphs(vec![posecast_rigs::clip::MorphTrack {
                    channel: "smile".into(),
                    track: Track::constant(w),
                }]);
            Arc::new(clip)
        };
        let mut player = Player::new();
        player.set_morph_channels(vec!["blink".into(), "smile".into()]);
        let mut out = vec![9.0; 2];
        player.sample_weights(&mut out);
        assert_eq!(out, [0.0, 0.0]);
        player.play(Layer::new(face(1.0), None, 0.0, 1.0, true), 0.0);
        player.set_clock(0.1);
        player.sample_weights(&mut out);
        assert_eq!(out, [0.0, 1.0]);
        player.play(Layer::new(still("b", 10.0), None, 0.0, 1.0, true), 1.0);
        player.set_clock(0.35);
        player.sample_weights(&mut out);
        assert!((out[1] - 0.75).abs() < 1e-6, "{out:?}");
        assert_eq!(out[0], 0.0);
        player.set_clock(1.2);
        player.sample_weights(&mut out);
        assert_eq!(out, [0.0, 0.0]);
        // Many overlapping fades (the bottom collapses into a frozen pose and weights): the
        // weights stay continuous across the collapse.
        let mut before = vec![0.0; 2];
        let mut clock = 1.2;
        for k in 0..(MAX_FADES + 3) {
            let clip = if k % 2 == 0 {
                face(0.8)
            } else {
                still("b", 5.0)
            };
            player.play(Layer::new(clip, None, 0.0, 1.0, true), 1.0);
            player.sample_weights(&mut before);
            clock += 0.01;
            player.set_clock(clock);
            let mut pose = vec![Transform::IDENTITY; 1];
            player.sample(&[Transform::IDENTITY], &mut pose);
            player.sample_weights(&mut out);
            assert!(
                (out[1] - before[1]).abs() < 0.05,
                "fade {k}: {before:?} → {out:?}"
            );
        }
    }

    fn still(name: &str, deg: f32) -> Arc<Clip> {
        let q = Quat::from_rotation_y(deg.to_radians());
        let track = Track::new(Interpolation::Step, vec![0.0], vec![q]).unwrap();
        let joint = JointChannels {
            rotation: Some(RotationChannel::Keys(track)),
            ..JointChannels::default()
        };
        Arc::new(Clip::new(name, vec![joint], Some((0.0, 1.0))).unwrap())
    }

    #[derive(Debug, Clone)]
    enum Op {
        Tick,
        Play {
            clip: usize,
            fade: f32,
            start: f32,
            speed: f32,
        },
        Speed(f32),
        Pause(bool),
    }

    fn op() -> impl Strategy<Value = Op> {
        prop_oneof![
            6 => Just(Op::Tick),
            3 => (0..4usize, 0.0f32..1.5, 0.0f32..2.0, -2.0f32..2.0)
                .prop_map(|(clip, fade, start, speed)| Op::Play { clip, fade, start, speed }),
            1 => (-2.0f32..2.0).prop_map(Op::Speed),
            1 => any::<bool>().prop_map(Op::Pause),
        ]
    }

    proptest! {
        /// Random play / speed / pause sequences on looping clips moving at up to 2π rad/s, ticked at
        /// 60 Hz: a command never changes the pose at its instant (every `play` here fades,
        /// except those with fade 0, which cut by definition), and a tick moves the joint by at
        /// most what the layers' speeds and the fades' weights can move it in 1/60 s.
        #[test]
        fn the_pose_never_jumps(ops in proptest::collection::vec(op(), 1..200)) {
            // Seamless loops, so wrapping is no jump of the clip's own, swinging at most 1 rad
            // each: two poses are never near 180° apart, where a slerp blend flips its arc.
            let tau = std::f32::consts::TAU;
            let clips = [
                swinging("x", Vec3::X, 1.0, 2.0),
                swinging("y", Vec3::Y, 1.0, 1.5),
                swinging("z", Vec3::Z, 0.8, 3.0),
                swinging("d", Vec3::new(1.0, 1.0, 0.0), 1.0, 1.0),
            ];
            let fastest = tau * 2.0; // rad/s: the fastest clip (1 rad · 2π / 1 s) at |speed| ≤ 2
            let rate = 60.0;
            let mut player = Player::new();
            player.play(Layer::new(clips[0].clone(), None, 0.0, 1.0, true), 0.0);
            let mut tick = 0u64;
            let mut last = pose(&mut player);
            for op in ops {
                match op {
                    Op::Tick => {
                        // Worst case per tick: every layer turning at the fastest clip's
                        // speed and every fade's weight moving by dt / duration over an angle
                        // of at most π, composed over the stack.
                        let dt = 1.0 / rate;
                        let fades: f32 = player.fading.iter()
                            .map(|f| std::f32::consts::PI * dt as f32 / f.duration).sum();
                        let bound = fastest * dt as f32 * (player.fading.len() + 1) as f32 + fades;
                        tick += 1;
                        player.set_clock(tick as f64 / rate);
                        let now = pose(&mut player);
                        prop_assert!(angle(&last, &now) <= bound + 1e-4,
                            "tick moved {}° (bound {}°)", angle(&last, &now).to_degrees(), bound.to_degrees());
                        last = now;
                    }
                    Op::Play { clip, fade, start, speed } => {
                        let fade = if fade < 0.05 { 0.0 } else { fade };
                        player.play(Layer::new(clips[clip].clone(), None, start, speed, true), fade);
                        let now = pose(&mut player);
                        if fade > 0.0 {
                            prop_assert!(angle(&last, &now) < 1e-4,
                                "play jumped {}°", angle(&last, &now).to_degrees());
                        }
                        last = now;
                    }
                    Op::Speed(s) => {
                        if let Some(layer) = player.current_mut() { layer.set_speed(s); }
                        let now = pose(&mut player);
                        prop_assert!(angle(&last, &now) < 1e-4);
                        last = now;
                    }
                    Op::Pause(p) => {
                        if let Some(layer) = player.current_mut() { layer.set_paused(p); }
                        let now = pose(&mut player);
                        prop_assert!(angle(&last, &now) < 1e-4);
                        last = now;
                    }
                }
                prop_assert!(player.fading.len() <= MAX_FADES + 1);
            }
        }
    }

    /// Past [`MAX_FADES`] overlapping fades the two oldest become one still pose; the pose at
    /// that tick is the one the whole stack made.
    #[test]
    fn a_full_stack_collapses_without_a_jump() {
        let mut player = Player::new();
        let clips = [
            swinging("x", Vec3::X, 1.0, 2.0),
            swinging("y", Vec3::Y, 1.0, 1.5),
        ];
        player.play(Layer::new(clips[0].clone(), None, 0.0, 1.0, true), 0.0);
        let mut tick = 0u64;
        for k in 0..(MAX_FADES + 3) {
            player.play(
                Layer::new(clips[k % 2].clone(), None, 0.3 * k as f32, 1.0, true),
                5.0,
            );
            tick += 1;
            player.set_clock(tick as f64 / 60.0);
            // The pose an uncollapsed stack gives, then the (possibly collapsing) sample.
            let mut full = [Transform::IDENTITY];
            player.sample_stack(&[Transform::IDENTITY], &mut full);
            let got = pose(&mut player);
            assert!(
                angle(&full, &got) < 1e-4,
                "collapse moved {}°",
                angle(&full, &got).to_degrees()
            );
            assert!(player.fading.len() <= MAX_FADES);
        }
    }

    /// A one-joint clip of `duration` seconds whose rotation is irrelevant here.
    fn clip(duration: f32) -> Arc<Clip> {
        Arc::new(Clip::new("c", vec![JointChannels::default()], Some((0.0, duration))).unwrap())
    }

    /// 10⁷ ticks at 60 Hz with speed changes, a pause and a seek: the clip time equals the
    /// exact value computed from the schedule in f64 to within 1 µs.
    #[test]
    fn clock_does_not_drift_over_ten_million_ticks() {
        let rate = 60.0f64;
        let duration = 7.3f32;
        let mut player = Player::new();
        player.play(Layer::new(clip(duration), None, 0.25, 1.0, true), 0.0);
        let mut exact = 0.25f64; // unwrapped clip time, advanced in exact steps
        let mut speed = 1.0f64;
        let ticks: u64 = 10_000_000;
        for n in 1..=ticks {
            let clock = n as f64 / rate;
            player.set_clock(clock);
            exact += speed / rate;
            match n {
                2_000_000 => {
                    player.current_mut().unwrap().set_speed(1.7);
                    speed = f64::from(1.7f32);
                }
                5_000_000 => {
                    player.current_mut().unwrap().set_speed(-0.45);
                    speed = f64::from(-0.45f32);
                }
                8_000_000 => {
                    player.current_mut().unwrap().seek(3.0);
                    exact = 3.0;
                }
                _ => {}
            }
        }
        let got = player.current().unwrap().clip_time_f64();
        let want = exact.rem_euclid(f64::from(duration));
        // `exact` itself accumulates ~1e7 f64 roundings (~1e-9 s); 1 µs is the promise.
        assert!((got - want).abs() < 1e-6, "clip time {got} vs {want}");
    }

    #[test]
    fn pause_holds_and_resume_continues() {
        let mut player = Player::new();
        player.play(Layer::new(clip(10.0), None, 1.0, 2.0, false), 0.0);
        player.set_clock(1.0);
        assert!((player.current().unwrap().time() - 3.0).abs() < 1e-12);
        player.current_mut().unwrap().set_paused(true);
        player.set_clock(5.0);
        assert!((player.current().unwrap().time() - 3.0).abs() < 1e-12);
        player.current_mut().unwrap().set_paused(false);
        player.set_clock(6.0);
        assert!((player.current().unwrap().time() - 5.0).abs() < 1e-12);
        // Not looping: held at the end.
        player.set_clock(100.0);
        assert_eq!(player.current().unwrap().clip_time(), 10.0);
    }

    #[test]
    fn fade_weight_follows_the_clock() {
        let mut player = Player::new();
        player.set_clock(2.0);
        player.play(Layer::new(clip(1.0), None, 0.0, 1.0, true), 0.0);
        player.play(Layer::new(clip(1.0), None, 0.0, 1.0, true), 0.5);
        player.set_clock(2.25);
        let w = player.fading.last().unwrap().weight(player.clock);
        assert!((w - 0.5).abs() < 1e-6, "{w}");
        player.set_clock(2.5);
        assert!(player.fading.is_empty());
    }
}
