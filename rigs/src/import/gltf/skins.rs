//! The skins of one skeleton merged into one rig (issue 33, goal 5).
//!
//! FBX2glTF and similar exporters split one character over several skins (one per hand, one
//! for the body) and RecursiveSkeletons binds 21 skins to each of its 4 skeletons. One asset
//! per skin gave one avatar per skin, each with part of the body. Skins are grouped here by
//! skeleton: two skins are one skeleton when a joint of each has the same **skeleton root**,
//! the topmost node reached from the joint through parents that are joints of some skin of
//! the file. Two characters under one scene node (FBX2glTF's `RootNode`) stay apart: that
//! node is no joint.
//!
//! **Inverse binds.** The asset holds one inverse bind per joint, the glTF one per skin and
//! joint. A skin `s` whose matrices `M_k` relate to the group's `B_k` by one transform,
//! `M_k = B_k · C_s` for every joint it shares with the skins merged before it, is merged
//! with its vertices stored as `C_s · v`: then `W_k · B_k · (C_s · v) = W_k · M_k · v`, the
//! skinning the file asks for, and its joints the group lacks get `B_k = M_k · C_s⁻¹`. Skins
//! sharing no joint have `C_s = I`. This covers the common case, skins of one bind pose whose
//! meshes were bound at different node transforms (`M_k = J_k⁻¹ · G_mesh`, so
//! `C_s = G_a⁻¹ · G_s` is the same for every joint). A skin whose matrices differ otherwise
//! (bound at another pose) cannot be skinned exactly with one matrix per joint: it stays an
//! asset of its own, with a note, as before.

use std::collections::{HashMap, HashSet};

use glam::Mat4;
use gltf::accessor::Dimensions;

use super::Context;
use crate::asset::Asset;
use crate::import::ImportError;

/// Relative tolerance on matrix entries for "the same inverse bind": f32 round-off of
/// exported matrices is ~1e-6 relative; 1e-4 keeps far from both that and real differences.
const BIND_TOLERANCE: f32 = 1e-4;

/// Skins merged into one rig.
pub(super) struct SkinGroup<'a> {
    pub skins: Vec<gltf::Skin<'a>>,
    /// Per skin (as `skins`), `C_s`: the transform its vertices are stored through.
    pub bakes: Vec<Mat4>,
    /// Joint node → its inverse bind in the merged rig.
    pub binds: HashMap<usize, Mat4>,
    /// The union of the skins' joints, first skin's order first.
    pub joints: Vec<usize>,
    pub notes: Vec<String>,
}

impl SkinGroup<'_> {
    /// Whether `ibm` (joint node → matrix) is `binds · C` for one `C`; `Some(C)` if so.
    fn fit(&self, ibm: &[(usize, Mat4)]) -> Option<Mat4> {
        let mut c = None;
        for (node, m) in ibm {
            let Some(b) = self.binds.get(node) else {
                continue;
            };
            let cm = *c.get_or_insert_with(|| b.inverse() * *m);
            if !same(&(*b * cm), m) {
                return None;
            }
        }
        let c = c.unwrap_or(Mat4::IDENTITY);
        (c.is_finite() && c.determinant().abs() > f32::MIN_POSITIVE).then_some(c)
    }
}

fn same(a: &Mat4, b: &Mat4) -> bool {
    let scale = b
        .abs()
        .to_cols_array()
        .iter()
        .fold(1.0f32, |m, v| m.max(*v));
    (*a - *b)
        .abs()
        .to_cols_array()
        .iter()
        .all(|d| *d <= BIND_TOLERANCE * scale)
}

fn skin_label(skin: &gltf::Skin<'_>) -> String {
    match skin.name() {
        Some(n) if !n.is_empty() => format!("skin {} ({n})", skin.index()),
        _ => format!("skin {}", skin.index()),
    }
}

impl<'d> Context<'d> {
    /// A skin's joints with their inverse binds (identity, with a note, when it has none).
    fn skin_binds(
        &self,
        skin: &gltf::Skin<'_>,
        notes: &mut Vec<String>,
    ) -> Result<Vec<(usize, Mat4)>, ImportError> {
        let joints: Vec<usize> = skin.joints().map(|n| n.index()).collect();
        if joints.is_empty() {
            return Err(ImportError::Unsupported {
                file: self.file.to_owned(),
                message: format!("skin {} has no joints", skin.index()),
            });
        }
        let mut seen = HashSet::with_capacity(joints.len());
        for &j in &joints {
            if j >= self.nodes.local.len() {
                return Err(self.node_err(j, "is not a node of the file"));
            }
            if !seen.insert(j) {
                return Err(self.node_err(j, format!("listed twice in skin {}", skin.index())));
            }
        }
        let Some(acc) = skin.inverse_bind_matrices() else {
            notes.push(format!(
                "{} has no inverseBindMatrices: identity used",
                skin_label(skin)
            ));
            return Ok(joints.into_iter().map(|j| (j, Mat4::IDENTITY)).collect());
        };
        let v = self
            .buffers
            .read_as(&acc, Dimensions::Mat4, "inverseBindMatrices")?;
        if v.len() < joints.len() * 16 {
            return Err(ImportError::Accessor {
                file: self.file.to_owned(),
                accessor: acc.index(),
                message: format!(
                    "{} inverse bind matrices for {} joints",
                    v.len() / 16,
                    joints.len()
                ),
            });
        }
        Ok(joints
            .into_iter()
            .zip(v.chunks_exact(16))
            .map(|(j, chunk)| {
                let mut a = [0.0f32; 16];
                a.copy_from_slice(chunk);
                (j, Mat4::from_cols_array(&a))
            })
            .collect())
    }

    /// The skins of the file grouped by skeleton (see the module docs), in skin order.
    pub(super) fn skin_groups(
        &self,
        skins: &[gltf::Skin<'d>],
    ) -> Result<Vec<SkinGroup<'d>>, ImportError> {
        let all_joints: HashSet<usize> = skins
            .iter()
            .flat_map(|s| s.joints().map(|n| n.index()).collect::<Vec<_>>())
            .collect();
        let parent = &self.nodes.parent;
        let root_of = |joint: usize| {
            let mut cur = joint;
            for _ in 0..parent.len() {
                match parent.get(cur).copied().flatten() {
                    Some(p) if all_joints.contains(&p) => cur = p,
                    _ => break,
                }
            }
            cur
        };
        // Union-find of skins through their skeleton roots.
        let mut leader: Vec<usize> = (0..skins.len()).collect();
        fn find(leader: &mut [usize], mut i: usize) -> usize {
            while leader[i] != i {
                leader[i] = leader[leader[i]];
                i = leader[i];
            }
            i
        }
        let mut skin_of_root: HashMap<usize, usize> = HashMap::new();
        for (i, skin) in skins.iter().enumerate() {
            for joint in skin.joints() {
                let root = root_of(joint.index());
                let other = *skin_of_root.entry(root).or_insert(i);
                let (a, b) = (find(&mut leader, i), find(&mut leader, other));
                leader[a.max(b)] = a.min(b);
            }
        }
        let mut groups: Vec<SkinGroup<'d>> = Vec::new();
        // Per skeleton (leader skin): the groups made of its skins.
        let mut of_skeleton: HashMap<usize, Vec<usize>> = HashMap::new();
        for (i, skin) in skins.iter().enumerate() {
            let mut notes = Vec::new();
            let ibm = self.skin_binds(skin, &mut notes)?;
            let candidates = of_skeleton.entry(find(&mut leader, i)).or_default();
            let fitting = candidates
                .iter()
                .find_map(|&g| groups[g].fit(&ibm).map(|c| (g, c)));
            let (g, c) = match fitting {
                Some(x) => x,
                None => {
                    if let Some(&first) = candidates.first() {
                        notes.push(format!(
                            "{} shares its skeleton with {} but binds shared joints at another \
                             pose: imported as an asset of its own",
                            skin_label(skin),
                            skin_label(&groups[first].skins[0])
                        ));
                    }
                    candidates.push(groups.len());
                    groups.push(SkinGroup {
                        skins: Vec::new(),
                        bakes: Vec::new(),
                        binds: HashMap::new(),
                        joints: Vec::new(),
                        notes: Vec::new(),
                    });
                    (groups.len() - 1, Mat4::IDENTITY)
                }
            };
            let group = &mut groups[g];
            let c_inv = c.inverse();
            for (node, m) in ibm {
                if let std::collections::hash_map::Entry::Vacant(e) = group.binds.entry(node) {
                    e.insert(m * c_inv);
                    group.joints.push(node);
                }
            }
            group.skins.push(skin.clone());
            group.bakes.push(c);
            group.notes.extend(notes);
        }
        for group in &mut groups {
            if group.skins.len() > 1 {
                let moved = group
                    .bakes
                    .iter()
                    .filter(|c| !same(c, &Mat4::IDENTITY))
                    .count();
                let labels: Vec<String> = group.skins.iter().map(skin_label).collect();
                let mut note = format!(
                    "{} skins of one skeleton merged into this rig ({} joints): {}",
                    group.skins.len(),
                    group.joints.len(),
                    super::listed(&labels)
                );
                if moved > 0 {
                    note.push_str(&format!(
                        "; the vertices of {moved} of them moved into the first one's bind space"
                    ));
                }
                group.notes.insert(0, note);
            }
        }
        Ok(groups)
    }

    /// The asset of one group of skins.
    pub(super) fn skin_group(
        &self,
        group: &SkinGroup<'_>,
        name: String,
    ) -> Result<Asset, ImportError> {
        self.rig(&group.joints, Some(group), name)
    }
}
