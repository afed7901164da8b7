//! A take of several avatars as one `.glb` ([`take_glb`]): each avatar its own figure — a root
//! node named after it holding its rig's joints, its skinned mesh and skin — and one
//! animation moving them all.
//!
//! Layout ([`super::glb`]'s, figure by figure in the avatars' order): avatar `k` is skin `k`;
//! its joints are nodes from its node offset (the nodes of the avatars before it), at their
//! rest transforms, under a plain node named after the avatar (identity transform, a root of
//! the scene); its meshes, if it has any, are the primitives of one mesh named
//! `<avatar>-mesh` on a node of that name, a root of the scene too (glTF ignores the parents
//! of a skinned mesh node, and the validator warns about them). The animation holds, avatar
//! by avatar, the channels [`animation::animation`] makes of its clip — retargeted to its
//! joints' nodes — and its `weights` channel on its mesh node when the clip drives a morph
//! target of its meshes. Each clip keeps its own key times, shifted so it starts at 0: clips
//! of different lengths end at different times.

use super::{ExportError, GENERATOR, animation, glb, skinned_mesh};
use crate::clip::Clip;
use crate::rig::Rig;

/// One avatar of a take export: its node name (the avatar's id), its rig, and its motion as a
/// clip of that rig (root motion in scene space: the avatar's own root moves it).
#[derive(Clone, Copy, Debug)]
pub struct TakeAvatar<'a> {
    /// The avatar's root node name (and its skin's); its mesh is `<name>-mesh`.
    pub name: &'a str,
    /// Its rig: skeleton, meshes.
    pub rig: &'a Rig,
    /// Its motion, a clip of `rig` (one channel slot per joint at most).
    pub clip: &'a Clip,
}

/// The avatars of a take as one `.glb`: per avatar a root node named after it holding that
/// rig's joint nodes (rest transforms), its skinned meshes and one skin; one animation named
/// `animation_name` whose channels drive every avatar's joints (and morph weights where the
/// rig has morph targets), times starting at 0 (each clip's own times, which start at 0 —
/// clips may have different key times and lengths). See the module for the layout.
///
/// An avatar whose clip animates nothing stands at rest.
///
/// # Errors
/// No avatars ([`ExportError::NoAvatars`]); a clip with more joint slots than its rig has
/// joints ([`ExportError::JointCount`]); no clip animating anything
/// ([`ExportError::NothingAnimated`], named after the animation); inconsistent meshes or
/// channels, or a file over 4 GiB, as [`glb::write_scene`].
pub fn take_glb(avatars: &[TakeAvatar<'_>], animation_name: &str) -> Result<Vec<u8>, ExportError> {
    if avatars.is_empty() {
        return Err(ExportError::NoAvatars);
    }
    let mut meshes = Vec::with_capacity(avatars.len());
    let mut motions = Vec::with_capacity(avatars.len());
    for avatar in avatars {
        let rig_meshes = &avatar.rig.asset.meshes;
        let targets = posecast_proto::morph::channels(rig_meshes.iter().map(|m| &m.mesh));
        let joints = avatar.rig.skeleton().len();
        motions.push(match animation::animation(avatar.clip, joints, &targets) {
            Ok(motion) => Some(motion),
            Err(ExportError::NothingAnimated { .. }) => None,
            Err(e) => return Err(e),
        });
        meshes.push(skinned_mesh(
            format!("{}-mesh", avatar.name),
            rig_meshes,
            &targets,
        ));
    }
    let figures: Vec<glb::Figure<'_>> = avatars
        .iter()
        .zip(&meshes)
        .map(|(avatar, mesh)| glb::Figure {
            name: Some(avatar.name),
            skin: Some(avatar.name),
            skeleton: avatar.rig.skeleton(),
            mesh: mesh.as_ref(),
        })
        .collect();
    let parts: Vec<glb::Part<'_>> = motions
        .iter()
        .enumerate()
        .filter_map(|(figure, motion)| {
            let animation = motion.as_ref()?;
            Some(glb::Part { figure, animation })
        })
        .collect();
    // A weights channel is written only on a figure with a mesh (`animation` makes one only
    // for a rig with morph targets, so only with meshes).
    let moves = parts
        .iter()
        .any(|p| !p.animation.channels.is_empty() || p.animation.weights.is_some());
    if !moves {
        return Err(ExportError::NothingAnimated {
            clip: animation_name.to_owned(),
        });
    }
    let animation = glb::SceneAnimation {
        name: animation_name,
        parts,
    };
    glb::write_scene(&glb::Scene {
        generator: GENERATOR,
        name: Some(animation_name),
        figures: &figures,
        animations: std::slice::from_ref(&animation),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::asset::Asset;
    use crate::clip::{Interpolation, MorphTrack, Track};
    use glam::{Quat, Vec3};
    use gltf::animation::util::ReadOutputs;
    use posecast_proto::morph::MorphTarget;
    use std::sync::Arc;

    fn builtin() -> Rig {
        crate::builtin::rig().unwrap()
    }

    fn clip(rig: &Rig, name: &str) -> Clip {
        (**rig.clip(name).unwrap()).clone()
    }

    /// The built-in avatar with a `smile` morph target on its first mesh.
    fn smiling() -> Rig {
        let rig = builtin();
        let mut asset = (*rig.asset).clone();
        let mesh = &mut asset.meshes[0].mesh;
        let smile = MorphTarget {
            name: "smile".into(),
            positions: (0..mesh.vertex_count())
                .map(|i| Vec3::Y * 0.01 * (i % 3) as f32)
                .collect(),
            normals: Vec::new(),
        };
        *mesh = mesh.clone().with_targets(vec![smile]).unwrap();
        Rig {
            asset: Arc::new(asset),
            ..rig
        }
    }

    /// The built-in avatar's skeleton without meshes.
    fn bare() -> Rig {
        let rig = builtin();
        let asset = Asset {
            meshes: Vec::new(),
            ..(*rig.asset).clone()
        };
        Rig {
            asset: Arc::new(asset),
            ..rig
        }
    }

    /// `wave` also driving `smile`: 0 → 1 → 0.25 over its range.
    fn smiling_wave(rig: &Rig) -> Clip {
        let wave = clip(rig, "wave");
        let (s, e) = (wave.start(), wave.end());
        let smile = Track::new(
            Interpolation::Linear,
            vec![s, (s + e) / 2.0, e],
            vec![0.0, 1.0, 0.25],
        )
        .unwrap();
        wave.with_morphs(vec![MorphTrack {
            channel: "smile".into(),
            track: smile,
        }])
    }

    /// The same rotation to 1e-6 per component (`q` and `−q` are one rotation).
    fn same_rotation(a: Quat, b: Quat) -> bool {
        a.abs_diff_eq(b, 1e-6) || a.abs_diff_eq(-b, 1e-6)
    }

    /// Every node below `node`, itself excluded.
    fn descendants(node: gltf::Node<'_>) -> Vec<usize> {
        node.children()
            .flat_map(|c| std::iter::once(c.index()).chain(descendants(c)))
            .collect()
    }

    /// Reads `bytes` back with the `gltf` crate and checks each avatar's figure: a scene root
    /// named after it holding its joints (in skeleton order, with its names) at identity,
    /// skin `k` named after it, and its mesh node (a scene root, `<name>-mesh`, skin `k`, a
    /// primitive per rig mesh) if the rig has meshes. Then checks that the one animation's
    /// channels are, skin by skin, the avatar's clip as [`animation::animation`] writes it:
    /// the same count, each on the right joint, from 0 to the clip's duration, and with the
    /// clip's rotations at their first, middle and last key times (and a third of the way).
    /// Returns the document and buffers for further checks.
    fn assert_take(
        bytes: &[u8],
        avatars: &[TakeAvatar<'_>],
        name: &str,
    ) -> (gltf::Document, Vec<gltf::buffer::Data>) {
        let (doc, buffers, _) = gltf::import_slice(bytes).unwrap();
        let scene = doc.default_scene().unwrap();
        let skins: Vec<gltf::Skin<'_>> = doc.skins().collect();
        assert_eq!(skins.len(), avatars.len());
        for (k, (skin, avatar)) in skins.iter().zip(avatars).enumerate() {
            assert_eq!(skin.name(), Some(avatar.name));
            let joints: Vec<gltf::Node<'_>> = skin.joints().collect();
            let names: Vec<&str> = joints.iter().map(|n| n.name().unwrap()).collect();
            assert_eq!(names, avatar.rig.skeleton().names(), "{}", avatar.name);
            let root = scene
                .nodes()
                .find(|n| n.name() == Some(avatar.name))
                .unwrap_or_else(|| panic!("no scene root named {}", avatar.name));
            let (t, r, s) = root.transform().decomposed();
            assert_eq!((t, r, s), ([0.0; 3], [0.0, 0.0, 0.0, 1.0], [1.0; 3]));
            let below = descendants(root);
            assert_eq!(below.len(), joints.len(), "{}", avatar.name);
            assert!(joints.iter().all(|j| below.contains(&j.index())));
            let mesh_nodes: Vec<gltf::Node<'_>> = doc
                .nodes()
                .filter(|n| n.skin().is_some_and(|s| s.index() == k))
                .collect();
            let meshes = &avatar.rig.asset.meshes;
            if meshes.is_empty() {
                assert!(mesh_nodes.is_empty(), "{}", avatar.name);
                continue;
            }
            let [mesh_node] = mesh_nodes.as_slice() else {
                panic!("{}: {} mesh nodes", avatar.name, mesh_nodes.len());
            };
            let mesh_name = format!("{}-mesh", avatar.name);
            assert_eq!(mesh_node.name(), Some(mesh_name.as_str()));
            assert!(scene.nodes().any(|n| n.index() == mesh_node.index()));
            let mesh = mesh_node.mesh().unwrap();
            assert_eq!(mesh.primitives().count(), meshes.len());
        }

        let animations: Vec<gltf::Animation<'_>> = doc.animations().collect();
        assert_eq!(animations.len(), 1);
        assert_eq!(animations[0].name(), Some(name));
        let mut channels = vec![0; avatars.len()];
        let mut checked = vec![0; avatars.len()];
        for ch in animations[0].channels() {
            let node = ch.target().node().index();
            let Some((k, j)) = skins
                .iter()
                .enumerate()
                .find_map(|(k, s)| s.joints().position(|n| n.index() == node).map(|j| (k, j)))
            else {
                continue; // a weights channel, checked by the caller
            };
            channels[k] += 1;
            let (rig, clip) = (avatars[k].rig, avatars[k].clip);
            let reader = ch.reader(|b| Some(&buffers[b.index()]));
            let times: Vec<f32> = reader.read_inputs().unwrap().collect();
            assert_eq!(times[0], 0.0);
            let last = times[times.len() - 1];
            assert!((last - clip.duration()).abs() < 1e-6, "{last}");
            let ReadOutputs::Rotations(rotations) = reader.read_outputs().unwrap() else {
                continue;
            };
            assert_ne!(
                ch.sampler().interpolation(),
                gltf::animation::Interpolation::CubicSpline
            );
            let values: Vec<Quat> = rotations.into_f32().map(Quat::from_array).collect();
            assert_eq!(values.len(), times.len());
            let rest = rig.skeleton().rest();
            let mut locals = rest.to_vec();
            let n = times.len();
            for key in [0, n / 3, n / 2, n - 1] {
                clip.sample(clip.start() + times[key], rest, &mut locals);
                assert!(
                    same_rotation(values[key], locals[j].rotation),
                    "{} joint {j} at {}: {} in the file, {} in the clip",
                    avatars[k].name,
                    times[key],
                    values[key],
                    locals[j].rotation
                );
                checked[k] += 1;
            }
        }
        let expected: Vec<usize> = avatars
            .iter()
            .map(|a| {
                animation::animation(a.clip, a.rig.skeleton().len(), &[])
                    .map_or(0, |m| m.channels.len())
            })
            .collect();
        assert_eq!(channels, expected, "joint channels per skin");
        for (k, a) in avatars.iter().enumerate() {
            assert!(checked[k] > 0, "no rotation of {} checked", a.name);
        }
        (doc, buffers)
    }

    #[test]
    fn two_avatars_are_two_skins_moved_by_one_animation() {
        let (alice, bob) = (builtin(), builtin());
        let (walk, wave) = (clip(&alice, "walk"), clip(&bob, "wave"));
        let avatars = [
            TakeAvatar {
                name: "alice",
                rig: &alice,
                clip: &walk,
            },
            TakeAvatar {
                name: "bob",
                rig: &bob,
                clip: &wave,
            },
        ];
        let bytes = take_glb(&avatars, "take").unwrap();
        let (doc, _) = assert_take(&bytes, &avatars, "take");
        assert_eq!(doc.meshes().count(), 2);
        assert_eq!(doc.default_scene().unwrap().nodes().count(), 4);
        // Nothing but joints is animated: the builtin has no morph targets.
        let animation = doc.animations().next().unwrap();
        assert!(
            animation
                .channels()
                .all(|c| c.target().property() != gltf::animation::Property::MorphTargetWeights)
        );
    }

    #[test]
    fn a_bare_skeleton_and_morph_weights_take_their_places() {
        let (alice, bob, carl) = (builtin(), smiling(), bare());
        let (walk, wave, idle) = (
            clip(&alice, "walk"),
            smiling_wave(&bob),
            clip(&carl, "idle"),
        );
        let avatars = [
            TakeAvatar {
                name: "alice",
                rig: &alice,
                clip: &walk,
            },
            TakeAvatar {
                name: "bob",
                rig: &bob,
                clip: &wave,
            },
            TakeAvatar {
                name: "carl",
                rig: &carl,
                clip: &idle,
            },
        ];
        let bytes = take_glb(&avatars, "trio").unwrap();
        let (doc, buffers) = assert_take(&bytes, &avatars, "trio");
        assert_eq!(doc.meshes().count(), 2);
        let animation = doc.animations().next().unwrap();
        let weights: Vec<gltf::animation::Channel<'_>> = animation
            .channels()
            .filter(|c| c.target().property() == gltf::animation::Property::MorphTargetWeights)
            .collect();
        let [smile] = weights.as_slice() else {
            panic!("{} weights channels", weights.len());
        };
        assert_eq!(smile.target().node().name(), Some("bob-mesh"));
        assert_eq!(smile.target().node().skin().unwrap().index(), 1);
        let reader = smile.reader(|b| Some(&buffers[b.index()]));
        let times: Vec<f32> = reader.read_inputs().unwrap().collect();
        let ReadOutputs::MorphTargetWeights(values) = reader.read_outputs().unwrap() else {
            panic!("not weights");
        };
        let values: Vec<f32> = values.into_f32().collect();
        assert_eq!(values.len(), times.len());
        let track = &wave.morphs()[0];
        for (t, w) in times.iter().zip(&values) {
            assert!((track.sample(wave.start() + t) - w).abs() < 1e-6, "{t}");
        }
        assert!(values.contains(&1.0));
    }

    #[test]
    fn no_avatars_or_no_motion_is_refused() {
        assert!(matches!(take_glb(&[], "take"), Err(ExportError::NoAvatars)));
        let rig = builtin();
        let still = Clip::new("still", Vec::new(), None).unwrap();
        let avatar = TakeAvatar {
            name: "a",
            rig: &rig,
            clip: &still,
        };
        let err = take_glb(&[avatar, avatar], "take").unwrap_err();
        assert!(
            matches!(&err, ExportError::NothingAnimated { clip } if clip == "take"),
            "{err}"
        );
        // One still avatar among moving ones stands at rest.
        let walk = clip(&rig, "walk");
        let moving = TakeAvatar {
            clip: &walk,
            ..avatar
        };
        take_glb(&[avatar, moving], "take").unwrap();
        let too_many = clip(&builtin(), "walk").remap_joints(&vec![Some(0); 40]);
        let wide = TakeAvatar {
            clip: &too_many,
            ..avatar
        };
        assert!(matches!(
            take_glb(&[moving, wide], "take"),
            Err(ExportError::JointCount { .. })
        ));
    }

    /// The Khronos validator finds nothing to warn about in a take (under `CI=true` a missing
    /// validator fails the test, see `posecast_proto::testing::skip`).
    #[test]
    fn takes_pass_the_khronos_validator_without_warnings() {
        let (alice, bob, carl) = (builtin(), smiling(), bare());
        let (walk, wave, idle) = (
            clip(&alice, "walk"),
            smiling_wave(&bob),
            clip(&carl, "idle"),
        );
        let pair = [
            TakeAvatar {
                name: "alice",
                rig: &alice,
                clip: &walk,
            },
            TakeAvatar {
                name: "bob",
                rig: &builtin(),
                clip: &clip(&alice, "wave"),
            },
        ];
        let trio = [
            pair[0],
            TakeAvatar {
                name: "bob",
                rig: &bob,
                clip: &wave,
            },
            TakeAvatar {
                name: "carl",
                rig: &carl,
                clip: &idle,
            },
        ];
        let dir = std::env::temp_dir().join(format!("posecast-take-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let files = [
            ("pair", take_glb(&pair, "take").unwrap()),
            ("trio", take_glb(&trio, "take").unwrap()),
        ];
        let paths: Vec<std::path::PathBuf> = files
            .iter()
            .map(|(label, bytes)| {
                let path = dir.join(format!("{label}.glb"));
                std::fs::write(&path, bytes).unwrap();
                path
            })
            .collect();
        let reports = posecast_proto::testing::validate_gltf(&paths);
        std::fs::remove_dir_all(&dir).ok();
        let Some(reports) = reports else {
            return; // skipped: node or the validator is missing (a failure under CI=true)
        };
        for ((label, _), r) in files.iter().zip(&reports) {
            eprintln!(
                "{label}: {} errors, {} warnings, {} infos, {} hints",
                r.errors, r.warnings, r.infos, r.hints
            );
            for m in &r.messages {
                eprintln!("  {m}");
            }
        }
        for ((label, _), r) in files.iter().zip(&reports) {
            assert_eq!(
                (r.errors, r.warnings),
                (0, 0),
                "{label}: see the messages above"
            );
        }
    }
}
