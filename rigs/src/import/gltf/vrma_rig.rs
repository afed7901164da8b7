//! The asset of a VRM animation: a skeleton-only rig of its humanoid bones, the file's bone
//! map as its H-Anim mapping, and its animations as clips on it.
//!
//! The skeleton is the bone nodes that have an H-Anim name plus every ancestor of one (the
//! nodes between two bones, and above the hips), folded like a skin's non-joint ancestors
//! where they are static and rigid ([`Context::rig`]). Every joint is bound at rest: the file
//! has no vertices. Its rest pose is the file's, the VRM T-pose, which rig normalisation turns
//! into the H-Anim neutral pose like any other humanoid's; retargeting (`play … from_asset`)
//! then plays the clips on any humanoid through world rotations, as the VRM animation
//! specification's non-normative "how to transform human pose" describes
//! (`W · L⁻¹ · A · W⁻¹` per bone: the pose relative to the T-pose in model space).

use super::vrm::{self, Humanoid, Version};
use super::vrma::{VrmAnimation, VrmaError};
use super::{Context, listed};
use crate::asset::Asset;
use crate::import::ImportError;

impl Context<'_> {
    /// A VRM animation's asset (see the module docs); the notes say what it kept and left,
    /// with counts.
    ///
    /// # Errors
    /// [`ImportError::VrmAnimation`] when the bone map does not fit the document; the
    /// importer's usual errors for its animations.
    pub(super) fn animation_rig(
        &self,
        animation: &VrmAnimation,
        name: String,
    ) -> Result<Asset, ImportError> {
        let nodes = self.nodes;
        animation
            .check(&nodes.parent)
            .map_err(|source| ImportError::VrmAnimation {
                file: self.file.to_owned(),
                source,
            })?;
        let upper_chest = animation.bones.iter().any(|(b, _)| b == "upperChest");
        let mut bones = Vec::new();
        let mut unnamed = Vec::new();
        for (bone, node) in &animation.bones {
            match vrm::hanim(bone, Version::V1, upper_chest) {
                Some(h) => bones.push((*node, bone.clone(), h)),
                None => unnamed.push(bone.clone()),
            }
        }
        let mut joints: Vec<usize> = bones.iter().map(|b| b.0).collect();
        joints.sort_unstable();
        if joints.is_empty() {
            // `check` wants the hips, which has an H-Anim name: unreachable, but typed.
            return Err(ImportError::VrmAnimation {
                file: self.file.to_owned(),
                source: VrmaError::MissingBones {
                    bones: vec!["hips".into()],
                },
            });
        }
        let humanoid = Humanoid {
            version: Version::V1,
            bones,
        };
        let ctx = Context {
            vrm: Some(&humanoid),
            ..*self
        };
        let mut asset = ctx.rig(&joints, None, name)?;

        // What the skeleton holds: the bones and their ancestors.
        let count = nodes.parent.len();
        let mut in_rig = vec![false; count];
        for &j in &joints {
            let mut cur = Some(j);
            while let Some(n) = cur {
                if in_rig[n] {
                    break;
                }
                in_rig[n] = true;
                cur = nodes.parent[n];
            }
        }
        let between = in_rig.iter().filter(|&&x| x).count() - joints.len();
        let mut notes = vec![format!(
            "VRM animation ({}): a skeleton of {} joints from {} humanoid bones and {between} \
             nodes above or between them (static ones folded into their children), {} clip(s)",
            match &animation.spec_version {
                Some(v) => format!("VRMC_vrm_animation {v}"),
                None => "VRMC_vrm_animation without specVersion, read as 1.0".to_owned(),
            },
            asset.skeleton.len(),
            joints.len(),
            asset.clips.len(),
        )];
        if !unnamed.is_empty() {
            notes.push(format!(
                "{} humanoid bones without an H-Anim counterpart not imported: {}",
                unnamed.len(),
                listed(&unnamed)
            ));
        }
        let channels_on = |node: usize| {
            self.doc
                .animations()
                .flat_map(|a| a.channels().collect::<Vec<_>>())
                .filter(|c| c.target().node().index() == node)
                .count()
        };
        if !animation.expressions.is_empty() {
            let names: Vec<String> = animation.expressions.iter().map(|e| e.0.clone()).collect();
            let channels: usize = animation.expressions.iter().map(|e| channels_on(e.1)).sum();
            notes.push(format!(
                "{} expressions not imported (their weights drive morph targets, which are not \
                 imported yet), {channels} channel(s) on them ignored: {}",
                names.len(),
                listed(&names)
            ));
        }
        if let Some(node) = animation.look_at {
            notes.push(format!(
                "lookAt target (node {node}) not imported, {} channel(s) on it ignored",
                channels_on(node)
            ));
        }
        let named: Vec<usize> = animation
            .expressions
            .iter()
            .map(|e| e.1)
            .chain(animation.look_at)
            .chain(animation.bones.iter().map(|b| b.1))
            .collect();
        let others: Vec<String> = (0..count)
            .filter(|&n| !in_rig[n] && !named.contains(&n))
            .map(|n| nodes.names[n].clone())
            .collect();
        if !others.is_empty() {
            notes.push(format!(
                "{} nodes outside the humanoid bone map not imported: {}",
                others.len(),
                listed(&others)
            ));
        }
        let (meshes, skins) = (self.doc.meshes().len(), self.doc.skins().len());
        if meshes + skins > 0 {
            notes.push(format!(
                "{meshes} mesh(es) and {skins} skin(s) not imported: a VRM animation is motion \
                 only"
            ));
        }
        asset.source.notes.extend(notes);
        Ok(asset)
    }
}
