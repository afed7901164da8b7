//! Clip playback on one avatar: a clock per clip (speed, loop, pause, seek) and a cross-fade
//! from the previous clip to the next.

use crate::clip::{Clip, Sampler, Wrap};
use posecast_proto::Transform;
use std::sync::Arc;

/// Default cross-fade duration, seconds.
pub const DEFAULT_FADE: f32 = 0.25;

/// One clip being played.
#[derive(Debug, Clone)]
pub struct Layer {
    /// The clip, already bound to the avatar's joints (retargeted when it came from another rig).
    pub clip: Arc<Clip>,
    /// The rig the clip was authored for, when retargeted.
    pub source_asset: Option<String>,
    /// Clip time in seconds from the clip's start, before wrapping.
    pub time: f32,
    /// Seconds of clip time per second of wall time.
    pub speed: f32,
    /// Loop, or hold the pose at the end (or start, playing backwards).
    pub looping: bool,
    /// A paused clock does not advance.
    pub paused: bool,
    sampler: Sampler,
}

impl Layer {
    /// A layer at clip time `start` (seconds from the clip's start).
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
            time: start,
            speed,
            looping,
            paused: false,
            sampler,
        }
    }

    /// The clip time, wrapped or clamped into `[0, duration]`.
    #[must_use]
    pub fn clip_time(&self) -> f32 {
        let wrap = if self.looping {
            Wrap::Loop
        } else {
            Wrap::Clamp
        };
        self.clip.wrap_time(self.clip.start() + self.time, wrap) - self.clip.start()
    }

    fn advance(&mut self, dt: f32) {
        if !self.paused {
            self.time += dt * self.speed;
            // Keep the unwrapped clock small so f32 precision does not decay over hours.
            let d = self.clip.duration();
            if self.looping && d > 0.0 && self.time.abs() > 1000.0 * d {
                self.time = self.time.rem_euclid(d);
            } else if !self.looping {
                self.time = self.time.clamp(0.0, d.max(0.0));
            }
        }
    }

    fn sample(&mut self, rest: &[Transform], out: &mut [Transform]) {
        let t = self.clip.start() + self.clip_time();
        self.sampler.sample(&self.clip, t, rest, out);
    }
}

/// What an avatar plays: the current layer and, during a cross-fade, the one fading out.
#[derive(Debug, Default)]
pub struct Player {
    current: Option<Layer>,
    fading: Option<Fade>,
    scratch: Vec<Transform>,
}

#[derive(Debug)]
struct Fade {
    from: Layer,
    elapsed: f32,
    duration: f32,
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

    /// Starts `layer`, cross-fading from the current one over `fade` seconds (0: cut).
    pub fn play(&mut self, layer: Layer, fade: f32) {
        let from = self.current.replace(layer);
        self.fading = match from {
            Some(from) if fade > 0.0 => Some(Fade {
                from,
                elapsed: 0.0,
                duration: fade,
            }),
            _ => None,
        };
    }

    /// Stops playing: the rest pose from now on.
    pub fn stop(&mut self) {
        self.current = None;
        self.fading = None;
    }

    /// Advances every clock by `dt` seconds of wall time.
    pub fn advance(&mut self, dt: f32) {
        if let Some(layer) = &mut self.current {
            layer.advance(dt);
        }
        if let Some(fade) = &mut self.fading {
            fade.from.advance(dt);
            fade.elapsed += dt;
            if fade.elapsed >= fade.duration {
                self.fading = None;
            }
        }
    }

    /// Writes the pose into `out` (one transform per joint): the current layer, blended with
    /// the fading one by `w = elapsed / duration` (slerp of rotations, lerp of translations and
    /// scales, so the fade is continuous at both ends). No layer: `rest`.
    pub fn sample(&mut self, rest: &[Transform], out: &mut [Transform]) {
        match &mut self.current {
            Some(layer) => layer.sample(rest, out),
            None => {
                let n = out.len().min(rest.len());
                out[..n].copy_from_slice(&rest[..n]);
            }
        }
        if let Some(fade) = &mut self.fading {
            self.scratch.resize(out.len(), Transform::IDENTITY);
            fade.from.sample(rest, &mut self.scratch);
            let w = (fade.elapsed / fade.duration).clamp(0.0, 1.0);
            for (o, f) in out.iter_mut().zip(&self.scratch) {
                *o = blend(f, o, w);
            }
        }
    }
}

/// `a` at `w = 0`, `b` at `w = 1`; rotations along the shortest arc.
#[must_use]
pub fn blend(a: &Transform, b: &Transform, w: f32) -> Transform {
    let rb = if a.rotation.dot(b.rotation) < 0.0 {
        -b.rotation
    } else {
        b.rotation
    };
    Transform {
        translation: a.translation.lerp(b.translation, w),
        rotation: a.rotation.slerp(rb, w).normalize(),
        scale: a.scale.lerp(b.scale, w),
    }
}
