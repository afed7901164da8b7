//! Joint subsets: a subscription may ask for only some joints of every avatar (a distant or
//! small avatar needs its body, not its fingers), so its frames carry fewer rotations.
//!
//! A [`JointSet`] is chosen per subscription (`subscribe … joints`); for each avatar the server
//! and the client derive the same [`Selection`] from the avatar's description, so frames carry
//! no joint list: a chunk holds the selected joints' rotations in description order, and of
//! the description's `translated_joints` and `scaled_joints` those that are selected, in order.
//! Every joint not selected is at its rest transform on the client.
//!
//! A selection always holds every root and, with each joint, all its ancestors: the world
//! transform of every joint sent is then exact, and so is the avatar's placement and root
//! motion.

use crate::description::AvatarDescription;
use serde::{Deserialize, Serialize};

/// Most names a [`JointSet::Names`] may list.
pub const MAX_NAMES: usize = 1024;

/// Which joints of every avatar a subscription gets.
#[derive(Debug, Clone, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[cfg_attr(feature = "ts", derive(ts_rs::TS))]
#[serde(rename_all = "snake_case", deny_unknown_fields)]
pub enum JointSet {
    /// Joints at most this many levels below a root (`0`: the roots only). `{"depth": 3}`.
    Depth(u16),
    /// These joints and their ancestors (names no joint of an avatar has are skipped for
    /// that avatar; its roots are always sent). `{"names": ["LeftHand", "Head"]}`.
    Names(Vec<String>),
}

/// Why a joint set is refused.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum JointSetError {
    /// More names than [`MAX_NAMES`].
    #[error("a joint set lists at most {MAX_NAMES} names, this one {0}")]
    TooManyNames(usize),
    /// No names at all.
    #[error("a joint set of names must list at least one")]
    NoNames,
}

impl JointSet {
    /// Checks the set's limits.
    ///
    /// # Errors
    /// Too many names, or none.
    pub fn validate(&self) -> Result<(), JointSetError> {
        match self {
            Self::Depth(_) => Ok(()),
            Self::Names(names) if names.is_empty() => Err(JointSetError::NoNames),
            Self::Names(names) if names.len() > MAX_NAMES => {
                Err(JointSetError::TooManyNames(names.len()))
            }
            Self::Names(_) => Ok(()),
        }
    }

    /// The joints of `description` this set selects.
    #[must_use]
    pub fn select(&self, description: &AvatarDescription) -> Selection {
        let parents = &description.parents;
        let n = parents.len();
        let parent = |j: usize| {
            usize::try_from(parents[j])
                .ok()
                .filter(|&p| p < n && p != j)
        };
        let mut keep = vec![false; n];
        match self {
            Self::Depth(max) => {
                for (j, k) in keep.iter_mut().enumerate() {
                    // Walk up at most `max + 1` steps: a joint deeper than that is not kept
                    // (and a malformed cycle ends the walk too).
                    let mut at = j;
                    let mut depth = 0usize;
                    while let Some(p) = parent(at) {
                        depth += 1;
                        if depth > usize::from(*max) {
                            break;
                        }
                        at = p;
                    }
                    *k = depth <= usize::from(*max);
                }
            }
            Self::Names(names) => {
                // Hashed once: a long list costs its length plus the joints, not their product.
                let names: std::collections::HashSet<&str> =
                    names.iter().map(String::as_str).collect();
                for j in 0..n {
                    let named = description
                        .joint_names
                        .get(j)
                        .is_some_and(|own| names.contains(own.as_str()));
                    if parent(j).is_none() || named {
                        // The joint and its ancestors (at most n steps: a cycle ends it).
                        let mut at = j;
                        for _ in 0..n {
                            keep[at] = true;
                            match parent(at) {
                                Some(p) if !keep[p] => at = p,
                                _ => break,
                            }
                        }
                    }
                }
            }
        }
        Selection::from_mask(description, &keep)
    }
}

/// The joints of one avatar a [`JointSet`] selects, and which of its streamed translations and
/// scales they carry.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct Selection {
    /// The avatar's joint count.
    pub joint_count: usize,
    /// Selected joints, ascending.
    pub joints: Vec<u16>,
    /// Positions in the description's `translated_joints` of the selected joints.
    pub translations: Vec<usize>,
    /// Positions in the description's `scaled_joints` of the selected joints.
    pub scales: Vec<usize>,
}

impl Selection {
    fn from_mask(d: &AvatarDescription, keep: &[bool]) -> Self {
        let kept = |j: u16| keep.get(usize::from(j)).copied().unwrap_or(false);
        Self {
            joint_count: keep.len(),
            joints: (0..keep.len())
                .filter(|&j| keep[j])
                .map(|j| j as u16)
                .collect(),
            translations: d
                .translated_joints
                .iter()
                .enumerate()
                .filter(|&(_, &j)| kept(j))
                .map(|(i, _)| i)
                .collect(),
            scales: d
                .scaled_joints
                .iter()
                .enumerate()
                .filter(|&(_, &j)| kept(j))
                .map(|(i, _)| i)
                .collect(),
        }
    }

    /// The selection of exactly `joints` of `description` (a JSON frame's `joints`). `None`
    /// when they are not ascending joints of the description.
    #[must_use]
    pub fn of_joints(description: &AvatarDescription, joints: &[u16]) -> Option<Self> {
        let n = description.parents.len();
        let ascending = joints.windows(2).all(|w| w[0] < w[1]);
        if !ascending || joints.last().is_some_and(|&j| usize::from(j) >= n) {
            return None;
        }
        let mut keep = vec![false; n];
        for &j in joints {
            keep[usize::from(j)] = true;
        }
        Some(Self::from_mask(description, &keep))
    }

    /// Whether every joint is selected (frames are then the same as without a set).
    #[must_use]
    pub fn is_all(&self) -> bool {
        self.joints.len() == self.joint_count
    }

    /// The selected items of `all` (one per joint, or one per streamed translation or scale
    /// when given [`Self::translations`] or [`Self::scales`] as `which`).
    #[must_use]
    pub fn pick<T: Clone>(all: &[T], which: impl IntoIterator<Item = usize>) -> Vec<T> {
        which
            .into_iter()
            .filter_map(|i| all.get(i).cloned())
            .collect()
    }

    /// The selected joints as indices (`usize`).
    pub fn joint_indices(&self) -> impl Iterator<Item = usize> + '_ {
        self.joints.iter().map(|&j| usize::from(j))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::msg::AvatarId;

    fn description_of(names: &[&str], parents: &[i32]) -> AvatarDescription {
        let n = names.len();
        AvatarDescription {
            id: AvatarId("a".into()),
            num: 1,
            name: "test".into(),
            joint_names: names.iter().map(|s| (*s).to_string()).collect(),
            parents: parents.to_vec(),
            rest_translations: vec![[0.0; 3]; n],
            rest_rotations: vec![[0.0, 0.0, 0.0, 1.0]; n],
            rest_scales: vec![[1.0; 3]; n],
            inverse_binds: vec![glam::Mat4::IDENTITY.to_cols_array(); n],
            translated_joints: vec![],
            scaled_joints: vec![],
            mesh_url: None,
            morph_targets: vec![],
            expressions: std::collections::BTreeMap::new(),
            expression_binds: Vec::new(),
            clip: None,
            hash: String::new(),
        }
    }

    /// A 7-joint tree: 0 root; 1, 2 children of 0; 3 child of 1; 4 child of 3; 5 child of 2;
    /// 6 a second root. Joints 0 and 4 are translated, 5 scaled.
    fn tree() -> AvatarDescription {
        let mut d = description_of(
            &["hips", "spine", "leg", "neck", "head", "foot", "prop"],
            &[-1, 0, 0, 1, 3, 2, -1],
        );
        d.translated_joints = vec![0, 4];
        d.scaled_joints = vec![5];
        d
    }

    #[test]
    fn depth_keeps_joints_by_level_below_any_root() {
        let d = tree();
        let s = |n| JointSet::Depth(n).select(&d);
        assert_eq!(s(0).joints, vec![0, 6]);
        assert_eq!(s(1).joints, vec![0, 1, 2, 6]);
        assert_eq!(s(2).joints, vec![0, 1, 2, 3, 5, 6]);
        assert_eq!(s(3).joints, vec![0, 1, 2, 3, 4, 5, 6]);
        assert!(s(3).is_all() && !s(2).is_all());
        assert_eq!(s(2).translations, vec![0]);
        assert_eq!(s(2).scales, vec![0]);
        assert_eq!(s(1).scales, Vec::<usize>::new());
        assert_eq!(s(3).translations, vec![0, 1]);
    }

    #[test]
    fn names_bring_their_ancestors_and_every_root() {
        let d = tree();
        let set = JointSet::Names(vec!["head".into(), "no such joint".into()]);
        let s = set.select(&d);
        assert_eq!(s.joints, vec![0, 1, 3, 4, 6]);
        assert_eq!(s.translations, vec![0, 1]);
        assert!(s.scales.is_empty());
        let foot = JointSet::Names(vec!["foot".into()]).select(&d);
        assert_eq!(foot.joints, vec![0, 2, 5, 6]);
        assert_eq!(foot.scales, vec![0]);
    }

    #[test]
    fn a_listed_selection_is_the_one_it_lists() {
        let d = tree();
        let s = JointSet::Depth(2).select(&d);
        assert_eq!(Selection::of_joints(&d, &s.joints), Some(s));
        assert_eq!(Selection::of_joints(&d, &[2, 1]), None);
        assert_eq!(Selection::of_joints(&d, &[1, 7]), None);
    }

    #[test]
    fn malformed_parents_end_the_walk() {
        // A cycle (1 ↔ 2) and an out-of-range parent: no panic, no endless loop.
        let d = description_of(&["a", "b", "c", "d"], &[-1, 2, 1, 99]);
        let s = JointSet::Depth(1).select(&d);
        assert!(s.joints.contains(&0) && s.joints.contains(&3));
        let n = JointSet::Names(vec!["b".into()]).select(&d);
        assert!(n.joints.contains(&1) && n.joints.contains(&2));
    }

    #[test]
    fn the_wire_form_is_one_key() {
        let depth: JointSet = serde_json::from_str(r#"{"depth":2}"#).unwrap();
        assert_eq!(depth, JointSet::Depth(2));
        let names: JointSet = serde_json::from_str(r#"{"names":["Head"]}"#).unwrap();
        assert_eq!(names, JointSet::Names(vec!["Head".into()]));
        assert!(serde_json::from_str::<JointSet>(r#"{"depth":-1}"#).is_err());
        assert!(serde_json::from_str::<JointSet>(r#"{"depth":1,"names":[]}"#).is_err());
        assert_eq!(
            JointSet::Names(vec![]).validate(),
            Err(JointSetError::NoNames)
        );
        assert_eq!(
            JointSet::Names(vec![String::new(); MAX_NAMES + 1]).validate(),
            Err(JointSetError::TooManyNames(MAX_NAMES + 1))
        );
    }
}
