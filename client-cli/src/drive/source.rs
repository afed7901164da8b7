//! The live source: a BVH clip imported and normalised locally by the server's own pipeline,
//! sampled at playback time into binary poses addressed by the server's joint order.

use anyhow::{Context, bail};
use glam::{Quat, Vec3};
use posecast_proto::Transform;
use posecast_proto::live::BinaryPose;
use posecast_server::clip::{Clip, Sampler, Wrap};
use posecast_server::import::bvh;
use posecast_server::rig::{PipelineOptions, Rig};
use std::path::Path;
use std::sync::Arc;

/// A normalised rig and its clip, what the server makes of the same file on upload.
#[derive(Debug)]
pub struct ClipSource {
    rig: Rig,
    clip: Arc<Clip>,
    sampler: Sampler,
    locals: Vec<Transform>,
}

impl ClipSource {
    /// Imports BVH `bytes` (read from `path`) and normalises the rig with the default pipeline,
    /// as the server does on an upload, so the rotations sampled here are in the frame the
    /// server's copy of the rig expects: `R' = pre · R · post` applied to every key.
    ///
    /// # Errors
    /// The file is not UTF-8 BVH, the pipeline refuses the rig, or it has no frames.
    pub fn from_bvh(path: &Path, bytes: &[u8]) -> anyhow::Result<Self> {
        let name = path.display().to_string();
        let text = std::str::from_utf8(bytes).with_context(|| format!("{name}: not UTF-8"))?;
        let asset = bvh::parse(&name, text)?;
        let rig = Rig::from_asset(asset, &PipelineOptions::default())
            .with_context(|| format!("{name}: the rig cannot be normalised"))?;
        let Some(clip) = rig.clips.first().cloned() else {
            bail!("{name} has no motion frames to stream");
        };
        let sampler = clip.sampler();
        let locals = rig.skeleton().rest().to_vec();
        Ok(Self {
            rig,
            clip,
            sampler,
            locals,
        })
    }

    /// The normalised rig.
    #[must_use]
    pub fn rig(&self) -> &Rig {
        &self.rig
    }

    /// The clip's length, seconds.
    #[must_use]
    pub fn duration(&self) -> f32 {
        self.clip.duration()
    }

    /// The clip time (seconds from the clip's start) of playback time `played` (seconds of
    /// clip played, wall-clock time × speed): looped, or held at the end.
    #[must_use]
    pub fn clip_time(&self, played: f32, looping: bool) -> f32 {
        let wrap = if looping { Wrap::Loop } else { Wrap::Clamp };
        self.clip.wrap_time(self.clip.start() + played, wrap) - self.clip.start()
    }

    /// Samples the clip at `time` (seconds from its start): every joint's local rotation and
    /// the root's local translation, in the normalised rig's frames.
    pub fn sample(&mut self, time: f32) -> (&[Transform], Vec3) {
        let rest = self.rig.skeleton().rest();
        self.sampler
            .sample(&self.clip, self.clip.start() + time, rest, &mut self.locals);
        let root = self.rig.skeleton().roots().next().unwrap_or(0);
        let root_position = self.locals.get(root).map_or(Vec3::ZERO, |t| t.translation);
        (&self.locals, root_position)
    }
}

/// Where each local joint goes in the server's order (the `joints` of the `drive` answer).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct JointMap {
    indices: Vec<u16>,
}

impl JointMap {
    /// Maps `local` joint names to their index in `server`; the two must hold the same names.
    ///
    /// # Errors
    /// A local joint the server's rig lacks, or a server joint the local rig lacks (another
    /// skeleton under the same asset name).
    pub fn new(local: &[String], server: &[String]) -> anyhow::Result<Self> {
        let indices = local
            .iter()
            .map(|name| {
                let i = server.iter().position(|s| s == name).with_context(|| {
                    format!("the server's source rig has no joint {name:?}: another skeleton")
                })?;
                u16::try_from(i).context("more than 65536 joints")
            })
            .collect::<anyhow::Result<Vec<_>>>()?;
        if server.len() != local.len() {
            bail!(
                "the server's source rig has {} joints, the file {}: another skeleton",
                server.len(),
                local.len()
            );
        }
        Ok(Self { indices })
    }

    /// A binary pose of every joint's rotation in `locals` (local order) and the root position.
    #[must_use]
    pub fn pose(
        &self,
        avatar_num: u32,
        locals: &[Transform],
        root_position: Vec3,
        time_us: u64,
    ) -> BinaryPose {
        BinaryPose {
            avatar_num,
            time_us: Some(time_us),
            root_position: Some(root_position),
            rotations: self
                .indices
                .iter()
                .zip(locals)
                .map(|(&i, t)| (i, t.rotation.normalize()))
                .collect::<Vec<(u16, Quat)>>(),
            weights: Vec::new(),
            trackers: Vec::new(),
        }
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    fn names(n: &[&str]) -> Vec<String> {
        n.iter().map(|s| (*s).to_owned()).collect()
    }

    #[test]
    fn joints_map_by_name_not_position() {
        let map = JointMap::new(
            &names(&["hip", "knee", "ankle"]),
            &names(&["ankle", "hip", "knee"]),
        )
        .unwrap();
        let q = |a: f32| Transform {
            rotation: Quat::from_rotation_x(a),
            ..Transform::IDENTITY
        };
        let pose = map.pose(7, &[q(0.1), q(0.2), q(0.3)], Vec3::Y, 5);
        let by_index: Vec<(u16, f32)> = pose
            .rotations
            .iter()
            .map(|(i, r)| (*i, r.to_axis_angle().1))
            .collect();
        assert_eq!(by_index.iter().map(|p| p.0).collect::<Vec<_>>(), [1, 2, 0]);
        assert!(
            (by_index[2].1 - 0.3).abs() < 1e-5,
            "ankle keeps its rotation"
        );
        assert_eq!(pose.avatar_num, 7);
        assert_eq!(pose.root_position, Some(Vec3::Y));
    }

    #[test]
    fn another_skeleton_is_refused() {
        let local = names(&["hip", "knee"]);
        assert!(JointMap::new(&local, &names(&["hip", "elbow"])).is_err());
        assert!(JointMap::new(&local, &names(&["hip", "knee", "ankle"])).is_err());
    }

    const TWO_FRAMES: &str = "HIERARCHY\nROOT hip\n{\n OFFSET 0 0 0\n CHANNELS 6 Xposition \
        Yposition Zposition Zrotation Xrotation Yrotation\n JOINT knee\n {\n  OFFSET 0 -1 0\n  \
        CHANNELS 3 Zrotation Xrotation Yrotation\n  End Site\n  {\n   OFFSET 0 -1 0\n  }\n }\n}\n\
        MOTION\nFrames: 3\nFrame Time: 0.5\n0 1 0 0 0 0 0 0 0\n0 1 2 0 0 0 0 90 0\n0 1 4 0 0 0 0 0 0\n";

    #[test]
    fn playback_time_loops_or_holds_and_samples_the_clip() {
        let mut source = ClipSource::from_bvh(Path::new("two.bvh"), TWO_FRAMES.as_bytes()).unwrap();
        assert!((source.duration() - 1.0).abs() < 1e-6);
        assert!((source.clip_time(1.25, true) - 0.25).abs() < 1e-5);
        assert!((source.clip_time(1.25, false) - 1.0).abs() < 1e-6);
        // The knee turns 90° about X between frames 0 and 2, so 45° at 0.25 s; the root moves.
        let (locals, root_at_quarter) = source.sample(0.25);
        let knee_angle = locals[1]
            .rotation
            .angle_between(Quat::IDENTITY)
            .to_degrees();
        assert!((knee_angle - 45.0).abs() < 0.5, "{knee_angle}");
        let (_, root_at_half) = source.sample(0.5);
        assert!(root_at_half.z > root_at_quarter.z);
    }
}
