//! glTF animations of one skin: translation, rotation and scale channels (`STEP`, `LINEAR`,
//! `CUBICSPLINE`) of its joints, and morph target `weights` channels of mesh nodes (split
//! into one [`MorphTrack`] per target, named as the mesh names its targets), as [`Clip`]s.

use std::collections::HashMap;

use glam::{Quat, Vec3};
use gltf::accessor::Dimensions;
use gltf::animation::{Interpolation as GltfInterpolation, Property};

use super::Context;
use crate::clip::{
    ChannelMap, Clip, Interpolation, JointChannels, MorphTrack, RotationChannel, Track,
    VectorChannel,
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
            let mut morphs: Vec<MorphTrack> = Vec::new();
            // `weights` channels of nodes with no morph targets to weigh.
            let mut targetless = 0usize;
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
                let joint = skel_of_node.get(&target.node().index()).copied();
                if joint.is_none() && target.property() != Property::MorphTargetWeights {
                    continue;
                }
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
                if target.property() == Property::MorphTargetWeights {
                    let node = target.node();
                    let tracks = self.morph_tracks(&node, &out, interpolation, &times, place())?;
                    targetless += usize::from(tracks.is_empty());
                    morphs.extend(tracks);
                    continue;
                }
                let Some(slot) = joint.and_then(|j| channels.get_mut(j)) else {
                    continue;
                };
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
                    // Read above.
                    Property::MorphTargetWeights => continue,
                }
                any = true;
            }
            if targetless > 0 {
                notes.push(format!(
                    "animation {a} ({clip_name}): {targetless} morph weight channel(s) on nodes \
                     without morph targets ignored"
                ));
            }
            if !any && morphs.is_empty() {
                continue;
            }
            if !morphs.is_empty() {
                notes.push(format!(
                    "animation {a} ({clip_name}): {} morph channel(s) animated",
                    morphs.len()
                ));
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
            clips.push(clip.with_morphs(morphs));
        }
        Ok(clips)
    }
}

impl Context<'_> {
    /// A `weights` channel of `node`'s mesh as one track per morph target: output `i·K + k`
    /// is target `k` at key `i` (`CUBICSPLINE`: in-tangents, values, out-tangents of the `K`
    /// targets, key by key), named by the mesh's `extras.targetNames` (else `target<k>`).
    fn morph_tracks(
        &self,
        node: &gltf::Node<'_>,
        out: &gltf::Accessor<'_>,
        interpolation: Interpolation,
        times: &[f32],
        place: String,
    ) -> Result<Vec<MorphTrack>, ImportError> {
        let clip_err = |source| ImportError::Clip {
            file: self.file.to_owned(),
            place: place.clone(),
            source,
        };
        let Some(mesh) = node.mesh() else {
            return Ok(Vec::new());
        };
        let targets = mesh
            .primitives()
            .map(|p| p.morph_targets().count())
            .max()
            .unwrap_or(0);
        let values = self
            .buffers
            .read_as(out, Dimensions::Scalar, "animation output")?;
        let per_key = if interpolation == Interpolation::CubicSpline {
            3
        } else {
            1
        };
        if targets == 0 {
            return Ok(Vec::new());
        }
        if values.len() != times.len() * per_key * targets {
            return Err(clip_err(crate::clip::ClipError::KeyCount {
                times: times.len(),
                values: values.len() / targets,
                per_key,
            }));
        }
        let names = super::mesh::target_names(&mesh);
        (0..targets)
            .map(|k| {
                let v: Vec<f32> = values.iter().skip(k).step_by(targets).copied().collect();
                Ok(MorphTrack {
                    channel: names
                        .get(k)
                        .filter(|n| !n.is_empty())
                        .cloned()
                        .unwrap_or_else(|| format!("target{k}")),
                    track: Track::new(interpolation, times.to_vec(), v).map_err(clip_err)?,
                })
            })
            .collect()
    }
}
