//! The avatar description: the rig as a client needs it to rebuild world and skinning matrices
//! from streamed local rotations, with a hash that every pose frame carries.

use crate::ids::AvatarId;
use crate::skeleton::{Skeleton, SkeletonError};
use crate::transform::Transform;
use glam::{Mat4, Quat, Vec3};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// An avatar's normalised rig, sent once per subscription.
///
/// Joints are in parent-before-child order. A joint's local transform is
/// `D_j = T(t_j) · R_j · S_j` where `R_j` comes from every frame, `t_j` from the frame when
/// `j ∈ translated_joints` and from `rest_translations` otherwise, and likewise `S_j` with
/// `scaled_joints` / `rest_scales`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "ts", derive(ts_rs::TS))]
pub struct AvatarDescription {
    /// The avatar.
    pub id: AvatarId,
    /// The avatar's number in binary frames (unique on the server).
    pub num: u32,
    /// Display name (e.g. the asset's name).
    pub name: String,
    /// Joint names, in order.
    pub joint_names: Vec<String>,
    /// Parent index of each joint, `-1` for a root.
    pub parents: Vec<i32>,
    /// Rest local translation `t'_j` of each joint (metres, parent space).
    pub rest_translations: Vec<[f32; 3]>,
    /// Rest local rotation of each joint `[x, y, z, w]` (the neutral pose; identity after
    /// normalisation).
    pub rest_rotations: Vec<[f32; 4]>,
    /// Rest local scale of each joint.
    pub rest_scales: Vec<[f32; 3]>,
    /// Inverse bind matrix `B'_j⁻¹` of each joint, column-major.
    pub inverse_binds: Vec<[f32; 16]>,
    /// Joints whose translation every frame carries (always includes the roots).
    pub translated_joints: Vec<u16>,
    /// Joints whose scale every frame carries.
    pub scaled_joints: Vec<u16>,
    /// Where to fetch the skinned mesh (a .glb), relative to the server's HTTP root.
    pub mesh_url: Option<String>,
    /// Morph channels: the distinct morph target names over the avatar's meshes (every mesh
    /// target of that name follows one weight), in the order weights are streamed. Absent for
    /// a rig without morph targets.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub morph_targets: Vec<String>,
    /// Standard expression names (ARKit's 52, VRM presets, Oculus visemes: see
    /// `crate::expressions`) → the morph channel that plays each, found by name.
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub expressions: BTreeMap<String, String>,
    /// Expressions the file defines (VRM 0.x `blendShapeMaster`, VRM 1.0 `expressions`): each
    /// moves weighted channels together and may hold back the blink, look-at and mouth
    /// expressions while it shows (`crate::expressions::Expression`). A name set by a client
    /// resolves to one of these before `morph_targets` and `expressions`. Absent for other rigs.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub expression_binds: Vec<crate::expressions::Expression>,
    /// The name of the clip playing when the description was sent, for display only.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub clip: Option<String>,
    /// [`AvatarDescription::compute_hash`] of all the fields above except `clip` and `hash`,
    /// as 16 hex digits. Every frame carries it; a client whose description has another hash is
    /// holding a stale rig.
    pub hash: String,
}

/// Errors turning a description into a [`Skeleton`].
#[derive(Debug, thiserror::Error)]
pub enum DescriptionError {
    /// Arrays of different lengths.
    #[error("description of {avatar}: {field} has {actual} entries, expected {expected}")]
    Length {
        /// The avatar.
        avatar: String,
        /// Which array.
        field: &'static str,
        /// Joint count.
        expected: usize,
        /// What it has.
        actual: usize,
    },
    /// A parent index that is not a joint.
    #[error("description of {avatar}: joint {joint} has parent {parent}")]
    Parent {
        /// The avatar.
        avatar: String,
        /// The joint.
        joint: usize,
        /// Its parent index.
        parent: i32,
    },
    /// A streamed joint index out of range.
    #[error("description of {avatar}: streamed joint index {index} out of range")]
    StreamedJoint {
        /// The avatar.
        avatar: String,
        /// The index.
        index: u16,
    },
    /// The skeleton itself is invalid.
    #[error("description of {avatar}: {source}")]
    Skeleton {
        /// The avatar.
        avatar: String,
        /// Why.
        source: SkeletonError,
    },
    /// The hash does not match the content.
    #[error("description of {avatar}: hash {claimed} does not match content hash {actual}")]
    Hash {
        /// The avatar.
        avatar: String,
        /// The hash in the message.
        claimed: String,
        /// The hash of the content.
        actual: String,
    },
}

impl AvatarDescription {
    /// Describes `skeleton` as avatar `id`/`num`. Roots are always in `translated_joints`.
    #[must_use]
    pub fn new(
        id: AvatarId,
        num: u32,
        name: String,
        skeleton: &Skeleton,
        translated: &[bool],
        scaled: &[bool],
        mesh_url: Option<String>,
    ) -> Self {
        let flagged = |flags: &[bool], always_roots: bool| -> Vec<u16> {
            (0..skeleton.len())
                .filter(|&j| {
                    flags.get(j).copied().unwrap_or(false)
                        || (always_roots && skeleton.parents()[j].is_none())
                })
                .map(|j| j as u16)
                .collect()
        };
        let mut d = Self {
            id,
            num,
            name,
            joint_names: skeleton.names().to_vec(),
            parents: skeleton
                .parents()
                .iter()
                .map(|p| p.map_or(-1, |p| p as i32))
                .collect(),
            rest_translations: skeleton
                .rest()
                .iter()
                .map(|t| t.translation.to_array())
                .collect(),
            rest_rotations: skeleton
                .rest()
                .iter()
                .map(|t| t.rotation.to_array())
                .collect(),
            rest_scales: skeleton.rest().iter().map(|t| t.scale.to_array()).collect(),
            inverse_binds: skeleton
                .inverse_bind()
                .iter()
                .map(Mat4::to_cols_array)
                .collect(),
            translated_joints: flagged(translated, true),
            scaled_joints: flagged(scaled, false),
            mesh_url,
            morph_targets: Vec::new(),
            expressions: BTreeMap::new(),
            expression_binds: Vec::new(),
            clip: None,
            hash: String::new(),
        };
        d.hash = format!("{:016x}", d.compute_hash());
        d
    }

    /// The same description with these morph channels and expression map, its hash updated.
    #[must_use]
    pub fn with_morphs(
        mut self,
        morph_targets: Vec<String>,
        expressions: BTreeMap<String, String>,
    ) -> Self {
        self.morph_targets = morph_targets;
        self.expressions = expressions;
        self.hash = format!("{:016x}", self.compute_hash());
        self
    }

    /// The same description with these file-defined expressions, its hash updated.
    #[must_use]
    pub fn with_expression_binds(mut self, defs: Vec<crate::expressions::Expression>) -> Self {
        self.expression_binds = defs;
        self.hash = format!("{:016x}", self.compute_hash());
        self
    }

    /// Number of joints.
    #[must_use]
    pub fn len(&self) -> usize {
        self.joint_names.len()
    }

    /// Whether there are no joints (never true for a valid description).
    #[must_use]
    pub fn is_empty(&self) -> bool {
        self.joint_names.is_empty()
    }

    /// The hash as a number (0 when the hex string is malformed).
    #[must_use]
    pub fn hash_u64(&self) -> u64 {
        u64::from_str_radix(&self.hash, 16).unwrap_or(0)
    }

    /// 64-bit FNV-1a over a canonical byte serialisation of every rig field (id, num, name,
    /// names, parents, rest TRS, inverse binds, streamed joint lists, mesh URL, and the morph
    /// channels and expression map when there are any). Floats are hashed by their bit
    /// patterns, so any change to the rig changes the hash.
    #[must_use]
    pub fn compute_hash(&self) -> u64 {
        let mut h = Fnv1a::new();
        h.str(&self.id.0);
        h.bytes(&self.num.to_le_bytes());
        h.str(&self.name);
        h.bytes(&(self.joint_names.len() as u64).to_le_bytes());
        for n in &self.joint_names {
            h.str(n);
        }
        for p in &self.parents {
            h.bytes(&p.to_le_bytes());
        }
        let floats = self
            .rest_translations
            .iter()
            .flatten()
            .chain(self.rest_rotations.iter().flatten())
            .chain(self.rest_scales.iter().flatten())
            .chain(self.inverse_binds.iter().flatten());
        for f in floats {
            h.bytes(&f.to_bits().to_le_bytes());
        }
        h.bytes(&(self.translated_joints.len() as u64).to_le_bytes());
        for j in self.translated_joints.iter().chain(&self.scaled_joints) {
            h.bytes(&j.to_le_bytes());
        }
        h.str(self.mesh_url.as_deref().unwrap_or(""));
        // Only when present, so the hash of a rig without morph targets is what it was.
        if !self.morph_targets.is_empty() || !self.expressions.is_empty() {
            h.bytes(&(self.morph_targets.len() as u64).to_le_bytes());
            for n in &self.morph_targets {
                h.str(n);
            }
            h.bytes(&(self.expressions.len() as u64).to_le_bytes());
            for (k, v) in &self.expressions {
                h.str(k);
                h.str(v);
            }
        }
        if !self.expression_binds.is_empty() {
            h.bytes(&(self.expression_binds.len() as u64).to_le_bytes());
            for e in &self.expression_binds {
                h.str(&e.name);
                h.bytes(&[
                    u8::from(e.is_binary),
                    e.override_blink as u8,
                    e.override_look_at as u8,
                    e.override_mouth as u8,
                ]);
                h.bytes(&(e.binds.len() as u64).to_le_bytes());
                for b in &e.binds {
                    h.str(&b.channel);
                    h.bytes(&b.weight.to_bits().to_le_bytes());
                }
            }
        }
        h.finish()
    }

    /// Rebuilds the [`Skeleton`] (validating everything a peer could get wrong) and checks the
    /// hash.
    ///
    /// # Errors
    /// Any inconsistency: lengths, parents, streamed joint indices, invalid skeleton, hash.
    pub fn to_skeleton(&self) -> Result<Skeleton, DescriptionError> {
        let n = self.len();
        let avatar = || self.id.0.clone();
        let check = |field: &'static str, actual: usize| {
            if actual == n {
                Ok(())
            } else {
                Err(DescriptionError::Length {
                    avatar: avatar(),
                    field,
                    expected: n,
                    actual,
                })
            }
        };
        check("parents", self.parents.len())?;
        check("rest_translations", self.rest_translations.len())?;
        check("rest_rotations", self.rest_rotations.len())?;
        check("rest_scales", self.rest_scales.len())?;
        check("inverse_binds", self.inverse_binds.len())?;
        for &index in self.translated_joints.iter().chain(&self.scaled_joints) {
            if usize::from(index) >= n {
                return Err(DescriptionError::StreamedJoint {
                    avatar: avatar(),
                    index,
                });
            }
        }
        let actual = format!("{:016x}", self.compute_hash());
        if actual != self.hash {
            return Err(DescriptionError::Hash {
                avatar: avatar(),
                claimed: self.hash.clone(),
                actual,
            });
        }
        let mut parents = Vec::with_capacity(n);
        for (joint, &parent) in self.parents.iter().enumerate() {
            parents.push(match parent {
                -1 => None,
                p if p >= 0 && (p as usize) < n => Some(p as usize),
                _ => {
                    return Err(DescriptionError::Parent {
                        avatar: avatar(),
                        joint,
                        parent,
                    });
                }
            });
        }
        let rest = (0..n)
            .map(|j| Transform {
                translation: Vec3::from_array(self.rest_translations[j]),
                rotation: Quat::from_array(self.rest_rotations[j]),
                scale: Vec3::from_array(self.rest_scales[j]),
            })
            .collect();
        let ibm = self
            .inverse_binds
            .iter()
            .map(Mat4::from_cols_array)
            .collect();
        Skeleton::new(self.joint_names.clone(), parents, rest, ibm).map_err(|source| {
            DescriptionError::Skeleton {
                avatar: avatar(),
                source,
            }
        })
    }
}

/// 64-bit FNV-1a, with lengths prefixed to strings so concatenations cannot collide.
struct Fnv1a(u64);

impl Fnv1a {
    fn new() -> Self {
        Self(0xcbf2_9ce4_8422_2325)
    }
    fn bytes(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.0 ^= u64::from(b);
            self.0 = self.0.wrapping_mul(0x0000_0100_0000_01b3);
        }
    }
    fn str(&mut self, s: &str) {
        self.bytes(&(s.len() as u64).to_le_bytes());
        self.bytes(s.as_bytes());
    }
    fn finish(&self) -> u64 {
        self.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::{arb_skeleton, skeleton_bound_at_rest};
    use proptest::prelude::*;

    fn two_joint() -> Skeleton {
        skeleton_bound_at_rest(
            vec![None, Some(0)],
            vec![
                Transform::IDENTITY,
                Transform {
                    translation: Vec3::Y,
                    ..Transform::IDENTITY
                },
            ],
        )
    }

    #[test]
    fn hash_changes_with_any_field_and_round_trips_through_json() {
        let s = two_joint();
        let d = AvatarDescription::new(
            AvatarId("a".into()),
            1,
            "A".into(),
            &s,
            &[],
            &[],
            Some("/mesh".into()),
        );
        assert_eq!(d.translated_joints, vec![0], "roots are always translated");
        let text = serde_json::to_string(&d).unwrap();
        let back: AvatarDescription = serde_json::from_str(&text).unwrap();
        assert_eq!(back, d);
        back.to_skeleton().unwrap();
        let mut changed = d.clone();
        changed.rest_translations[1][1] = 1.0001;
        assert_ne!(changed.compute_hash(), d.compute_hash());
        assert!(matches!(
            changed.to_skeleton(),
            Err(DescriptionError::Hash { .. })
        ));
        // Morph channels and the expression map are covered once present; absent, the hash
        // is the joints-only one.
        let plain = d.compute_hash();
        let faced = d.clone().with_morphs(
            vec!["mouthOpen".into(), "blink".into()],
            BTreeMap::from([("aa".to_owned(), "mouthOpen".to_owned())]),
        );
        assert_ne!(faced.hash_u64(), plain);
        let text = serde_json::to_string(&faced).unwrap();
        assert!(
            text.contains(r#""morph_targets":["mouthOpen","blink"]"#),
            "{text}"
        );
        let back: AvatarDescription = serde_json::from_str(&text).unwrap();
        back.to_skeleton().unwrap();
        let mut remapped = faced.clone();
        remapped.expressions.insert("aa".into(), "blink".into());
        assert_ne!(remapped.compute_hash(), faced.compute_hash());
        let mut renamed = faced.clone();
        renamed.morph_targets[1] = "blinks".into();
        assert_ne!(renamed.compute_hash(), faced.compute_hash());
        assert!(!serde_json::to_string(&d).unwrap().contains("morph_targets"));
        let mut bad = d.clone();
        bad.parents[1] = 7;
        bad.hash = format!("{:016x}", bad.compute_hash());
        assert!(matches!(
            bad.to_skeleton(),
            Err(DescriptionError::Parent { .. })
        ));
    }

    proptest! {
        #[test]
        fn skeleton_round_trips(s in arb_skeleton(1..40)) {
            let d = AvatarDescription::new(AvatarId("x".into()), 0, "x".into(), &s, &[], &[], None);
            let back = d.to_skeleton().unwrap();
            prop_assert_eq!(back.parents(), s.parents());
            prop_assert_eq!(back.names(), s.names());
            prop_assert_eq!(back.rest(), s.rest());
            prop_assert_eq!(back.inverse_bind(), s.inverse_bind());
        }
    }
}
