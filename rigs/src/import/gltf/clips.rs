//! glTF animations of one skin: translation, rotation and scale channels (`STEP`, `LINEAR`,
//! `CUBICSPLINE`) of its joints, as [`Clip`]s.

use std::collections::HashMap;

use glam::{Quat, Vec3};
use gltf::accessor::Dimensions;
use gltf::animation::{Interpolation as GltfInterpolation, Property};

use super::Context;
use crate::clip::{
    ChannelMap, Clip, Interpolation, JointChannels, RotationChannel, Track, VectorChannel,
};
use crate::import::ImportError;

impl Context<'_> {
    pub(super) fn clips(
        &self,
        skel_of_node: &HashMap<usize, usize>,
        maps: &[ChannelMap],
        count: usize,
        notes: &mut Vec<String>,
    ) -> Result<Vec<Clip>, ImportError> {
        let mut clips = Vec::new();
        for anim in self.doc.animations() {
            let a = anim.index();
            let clip_name = match anim.name() {
                Some(n) if !n.is_empty() => n.to_owned(),
                _ => format!("animation{a}"),
            };
            let mut channels = vec![JointChannels::default(); count];
            let mut any = false;
            // The file's time range: tracks that hold one value collapse to one key, so a clip
            // of constant tracks would otherwise last 0 s.
            let mut range = (f32::INFINITY, f32::NEG_INFINITY);
            // Morph weights target mesh nodes, never joints: said once per animation.
            let morphs = anim
                .channels()
                .filter(|ch| ch.target().property() == Property::MorphTargetWeights)
                .count();
            if morphs > 0 {
                notes.push(format!(
                    "animation {a} ({clip_name}): {morphs} morph target weight channel(s) skipped"
                ));
            }
            let ignored = anim
                .channels()
                .filter(|ch| {
                    ch.target().property() != Property::MorphTargetWeights
                        && !skel_of_node.contains_key(&ch.target().node().index())
                })
                .count();
            if ignored > 0 {
                notes.push(format!(
                    "animation {a} ({clip_name}): {ignored} channel(s) on nodes outside this \
                     rig ignored"
                ));
            }
            for (c, ch) in anim.channels().enumerate() {
                let target = ch.target();
                let Some(&joint) = skel_of_node.get(&target.node().index()) else {
                    continue;
                };
                let sampler = ch.sampler();
                let interpolation = match sampler.interpolation() {
                    GltfInterpolation::Step => Interpolation::Step,
                    GltfInterpolation::Linear => Interpolation::Linear,
                    GltfInterpolation::CubicSpline => Interpolation::CubicSpline,
                };
                let times = self.buffers.read_as(
                    &sampler.input(),
                    Dimensions::Scalar,
                    "animation input",
                )?;
                for &t in &times {
                    if t.is_finite() {
                        range = (range.0.min(t), range.1.max(t));
                    }
                }
                let place = || format!("animation {a} ({clip_name}) channel {c}");
                let clip_err = |source| ImportError::Clip {
                    file: self.file.to_owned(),
                    place: place(),
                    source,
                };
                let out = sampler.output();
                let slot = &mut channels[joint];
                match target.property() {
                    Property::Translation | Property::Scale => {
                        let v: Vec<Vec3> = self
                            .buffers
                            .read_as(&out, Dimensions::Vec3, "animation output")?
                            .chunks_exact(3)
                            .map(Vec3::from_slice)
                            .collect();
                        let track = Track::new(interpolation, times, v).map_err(clip_err)?;
                        if target.property() == Property::Translation {
                            slot.translation = Some(VectorChannel::Keys(track));
                        } else {
                            slot.scale = Some(VectorChannel::Keys(track));
                        }
                    }
                    Property::Rotation => {
                        let v: Vec<Quat> = self
                            .buffers
                            .read_as(&out, Dimensions::Vec4, "animation output")?
                            .chunks_exact(4)
                            .map(|q| Quat::from_xyzw(q[0], q[1], q[2], q[3]))
                            .collect();
                        let track = Track::new(interpolation, times, v).map_err(clip_err)?;
                        slot.rotation = Some(RotationChannel::Keys(track));
                    }
                    // Noted above.
                    Property::MorphTargetWeights => continue,
                }
                any = true;
            }
            if !any {
                continue;
            }
            let range = range.0.is_finite().then_some(range);
            let mut clip = Clip::new(clip_name.clone(), channels, range).map_err(|source| {
                ImportError::Clip {
                    file: self.file.to_owned(),
                    place: format!("animation {a} ({clip_name})"),
                    source,
                }
            })?;
            for (j, map) in maps.iter().enumerate() {
                if *map != ChannelMap::IDENTITY {
                    clip.map_joint(j, *map);
                }
            }
            clips.push(clip);
        }
        Ok(clips)
    }
}
