//! A clip sampler that remembers where it last was in every track, for forward playback.

use posecast_proto::Transform;

use super::{Clip, sample_joint};

/// Per-track key cursors for one clip. [`Sampler::sample`] gives exactly what
/// [`Clip::sample`] gives (the same evaluation, only the key search starts at the cursor), and
/// costs O(1) per track when time moves forwards by less than a key interval.
#[derive(Clone, Debug)]
pub struct Sampler {
    /// Nine cursors per joint: rotation, translation and scale, three curves each.
    cursors: Vec<[usize; 9]>,
}

impl Sampler {
    /// A sampler with every cursor at the first key.
    #[must_use]
    pub fn new(clip: &Clip) -> Self {
        Self {
            cursors: vec![[0; 9]; clip.joint_count()],
        }
    }

    /// Samples `clip` at `time` into `out`, like [`Clip::sample`]. A sampler made for another
    /// clip still gives exact results (cursors are only hints; missing ones are added).
    pub fn sample(&mut self, clip: &Clip, time: f32, rest: &[Transform], out: &mut [Transform]) {
        let needed = clip.joint_count().max(out.len().min(rest.len()));
        if self.cursors.len() < needed {
            self.cursors.resize(needed, [0; 9]);
        }
        for (j, ((o, r), cursors)) in out
            .iter_mut()
            .zip(rest)
            .zip(self.cursors.iter_mut())
            .enumerate()
        {
            *o = match clip.channels().get(j) {
                Some(ch) => sample_joint(ch, time, r, cursors),
                None => *r,
            };
        }
    }
}

#[cfg(test)]
mod tests {
    use super::super::{Interpolation, JointChannels, RotationChannel, Track, VectorChannel};
    use super::*;
    use glam::{Quat, Vec3};

    #[test]
    fn forward_and_backward_match_random_access() {
        let times: Vec<f32> = (0..40).map(|i| i as f32 / 30.0).collect();
        let rots = (0..40)
            .map(|i| Quat::from_rotation_y(i as f32 * 0.2) * Quat::from_rotation_x(i as f32 * 0.05))
            .collect();
        let trans = (0..40).map(|i| Vec3::new(i as f32, 0.0, 0.0)).collect();
        let joints = vec![
            JointChannels {
                rotation: Some(RotationChannel::Keys(
                    Track::new(Interpolation::Linear, times.clone(), rots).unwrap(),
                )),
                translation: Some(VectorChannel::Keys(
                    Track::new(Interpolation::Step, times, trans).unwrap(),
                )),
                ..Default::default()
            };
            3
        ];
        let clip = Clip::new("c", joints, None).unwrap();
        let rest = [Transform::IDENTITY; 3];
        let mut s = clip.sampler();
        let (mut a, mut b) = ([Transform::IDENTITY; 3], [Transform::IDENTITY; 3]);
        let mut t = -0.1;
        while t < 1.6 {
            s.sample(&clip, t, &rest, &mut a);
            clip.sample(t, &rest, &mut b);
            assert_eq!(a, b, "t = {t}");
            t += 1.0 / 120.0;
        }
        for t in [1.2f32, 0.1, 0.9, 0.0, 1.3] {
            s.sample(&clip, t, &rest, &mut a);
            clip.sample(t, &rest, &mut b);
            assert_eq!(a, b, "t = {t}");
        }
    }
}
