//! A rig ready to play: a normalised asset with its clips, the DOF limits in the frame they
//! were authored in, and the H-Anim names retargeting matches on ([`Rig::from_asset`] runs the
//! normalisation pipeline).

use super::humanoid::classify;
use super::pipeline::rig_height;
use super::{PipelineOptions, RigError, RigView, normalise};
use crate::asset::Asset;
use crate::clip::Clip;
use glam::Quat;
use posecast_core::error::Error;
use posecast_core::quota::{Quota, Quotas};
use posecast_proto::command::{AssetDetail, AssetInfo, ClipInfo, JointMapping, Units};
use posecast_proto::{JointDofs, Skeleton};
use std::sync::Arc;

/// A rig ready to play: the normalised asset, its clips shared with every avatar using them.
#[derive(Debug)]
pub struct Rig {
    /// The asset's (unique) name.
    pub name: String,
    /// The normalised asset, shared by the rigs [`Rig::with_clip`] makes from this one.
    pub asset: Arc<Asset>,
    /// Its clips, shared by the avatars playing them.
    pub clips: Vec<Arc<Clip>>,
    /// Per joint: whether any clip animates its translation (streamed in every frame).
    pub translated: Vec<bool>,
    /// Per joint: whether any clip animates its scale.
    pub scaled: Vec<bool>,
    /// Per joint: the DOFs and limits in the joint's authored frame, with the rotations that
    /// map an authored rotation `R` to the normalised one `R' = pre · R · post`.
    pub limits: Vec<Option<JointLimits>>,
    /// What the import pipeline did, in order, for people.
    pub pipeline: Vec<String>,
    /// Per joint, its H-Anim name if mapped (what retargeting matches on).
    pub hanim: Vec<Option<String>>,
    /// Whether it is a humanoid (retargeting matches humanoids with humanoids only).
    pub humanoid: bool,
    /// The pipeline options it was normalised with.
    pub options: PipelineOptions,
    /// What the importer skipped, defaulted or approximated, for people.
    pub notes: Vec<String>,
    /// The unit conversion the pipeline applied.
    pub units: Units,
    /// The upload it came from (`configure_asset` normalises that again), if uploaded.
    pub upload: Option<String>,
}

/// A joint's DOF limits and the frame they are expressed in.
#[derive(Debug, Clone)]
pub struct JointLimits {
    /// DOFs and limits as authored.
    pub dofs: JointDofs,
    /// `R' = pre · R · post` maps an authored rotation to the normalised rig.
    pub pre: Quat,
    /// See `pre`.
    pub post: Quat,
}

impl JointLimits {
    /// The rotation nearest `q` (normalised frame) that the limits allow, in the normalised
    /// frame: map back to the authored frame, project and clamp there, map forward.
    #[must_use]
    pub fn clamp(&self, q: Quat) -> Quat {
        let authored = self.pre.inverse() * q * self.post.inverse();
        let mut dofs = self.dofs.clone();
        match dofs.set_rotation(authored) {
            Ok(clamped) => (self.pre * clamped * self.post).normalize(),
            Err(_) => q,
        }
    }
}

impl Rig {
    /// Makes a playable rig from an imported asset: runs the normalisation pipeline with
    /// `options` (simplify → re-orient → units → H-Anim neutral pose when humanoid) and keeps DOF
    /// limits in the frame they were authored in, with the rotation maps that carry them over.
    ///
    /// # Errors
    /// The pipeline refused the rig (e.g. a mirrored bind).
    pub fn from_asset(asset: Asset, options: &PipelineOptions) -> Result<Self, RigError> {
        let dofs = asset.skeleton.dofs().to_vec();
        let n = normalise(asset, options)?;
        let limits = dofs
            .iter()
            .zip(&n.rotation_maps)
            .map(|(d, &(pre, post))| {
                d.is_limited().then(|| JointLimits {
                    dofs: d.clone(),
                    pre,
                    post,
                })
            })
            .collect();
        let mut steps = n.steps;
        if !n.unmapped.is_empty() {
            steps.push(format!(
                "joints without an H-Anim name: {}",
                n.unmapped.join(", ")
            ));
        }
        let mut rig = Self::new(n.asset, steps, limits, n.hanim);
        rig.humanoid = n.humanoid;
        rig.units = n.units;
        rig.options = options.clone();
        Ok(rig)
    }

    /// A rig from an asset that has already been normalised; `pipeline` records how.
    #[must_use]
    pub fn new(
        asset: Asset,
        pipeline: Vec<String>,
        limits: Vec<Option<JointLimits>>,
        hanim: Vec<Option<String>>,
    ) -> Self {
        let n = asset.skeleton.len();
        let mut translated = vec![false; n];
        let mut scaled = vec![false; n];
        for clip in &asset.clips {
            for j in 0..n.min(clip.joint_count()) {
                translated[j] |= clip.animates_translation(j);
                scaled[j] |= clip.animates_scale(j);
            }
        }
        let clips = asset.clips.iter().cloned().map(Arc::new).collect();
        let mut limits = limits;
        limits.resize(n, None);
        let mut hanim = hanim;
        hanim.resize(n, None);
        let humanoid = classify(&asset, &hanim).humanoid;
        Self {
            name: asset.name.clone(),
            notes: asset.source.notes.clone(),
            units: Units {
                metres_per_unit: 1.0,
                source: "file".into(),
                height: rig_height(&asset),
            },
            asset: Arc::new(asset),
            clips,
            translated,
            scaled,
            limits,
            pipeline,
            hanim,
            humanoid,
            options: PipelineOptions::default(),
            upload: None,
        }
    }

    /// The same rig with one more clip (recorded on it, so in its normalised frames).
    ///
    /// Cheap whatever the rig holds: the clips are shared (`Arc`), not copied, and the new one
    /// goes into [`Rig::clips`] only — never into `asset.clips`, which stays the imported
    /// file's. Copying every clip on each add made restoring n recordings cost O(n²) bytes
    /// (issue 37: 202 s for 1 GiB) and stalled the tick of every scene while a 64 MiB take
    /// was added.
    #[must_use]
    pub fn with_clip(&self, clip: Clip) -> Self {
        self.with_clips(vec![clip])
    }

    /// [`Rig::with_clip`] for several clips at once (a restore adds a rig's recordings in one
    /// step).
    #[must_use]
    pub fn with_clips(&self, new: Vec<Clip>) -> Self {
        let mut translated = self.translated.clone();
        let mut scaled = self.scaled.clone();
        let mut clips = self.clips.clone();
        for clip in new {
            for j in 0..translated.len().min(clip.joint_count()) {
                translated[j] |= clip.animates_translation(j);
                scaled[j] |= clip.animates_scale(j);
            }
            clips.push(Arc::new(clip));
        }
        self.with_clip_list(clips, translated, scaled)
    }

    /// The same rig without clip `name` (what `delete_clip` leaves); `None` when it has none
    /// of that name. Joints stay streamed as before (the description of avatars playing
    /// other clips must not change under them).
    #[must_use]
    pub fn without_clip(&self, name: &str) -> Option<Self> {
        let at = self.clips.iter().position(|c| c.name() == name)?;
        let mut clips = self.clips.clone();
        clips.remove(at);
        Some(self.with_clip_list(clips, self.translated.clone(), self.scaled.clone()))
    }

    fn with_clip_list(
        &self,
        clips: Vec<Arc<Clip>>,
        translated: Vec<bool>,
        scaled: Vec<bool>,
    ) -> Self {
        Self {
            name: self.name.clone(),
            asset: self.asset.clone(),
            clips,
            translated,
            scaled,
            limits: self.limits.clone(),
            pipeline: self.pipeline.clone(),
            hanim: self.hanim.clone(),
            humanoid: self.humanoid,
            options: self.options.clone(),
            notes: self.notes.clone(),
            units: self.units.clone(),
            upload: self.upload.clone(),
        }
    }

    /// Checks the rig's size and every clip's duration × joints against the limits for any rig.
    ///
    /// # Errors
    /// [`Quota::Joints`] or [`Quota::ClipJointSeconds`], with its typed error.
    pub fn check_quotas(&self, quotas: &Quotas) -> Result<(), (Quota, Error)> {
        let joints = self.skeleton().len();
        if joints > quotas.max_joints {
            return Err((
                Quota::Joints,
                Quota::Joints.exceeded(
                    format!("rig {} has {joints} joints", self.name),
                    quotas.max_joints,
                ),
            ));
        }
        for clip in &self.clips {
            let cost = f64::from(clip.duration()) * joints as f64;
            if cost > quotas.max_clip_joint_seconds {
                return Err((
                    Quota::ClipJointSeconds,
                    Quota::ClipJointSeconds.exceeded(
                    format!(
                        "clip {} of rig {} lasts {} s × {joints} joints = {cost:.0} joint-seconds",
                        clip.name(),
                        self.name,
                        clip.duration()
                    ),
                    quotas.max_clip_joint_seconds,
                ),
                ));
            }
        }
        Ok(())
    }

    /// The rig as retargeting sees it (asset and H-Anim names).
    #[must_use]
    pub fn view(&self) -> RigView<'_> {
        RigView {
            asset: &self.asset,
            hanim: &self.hanim,
            humanoid: self.humanoid,
        }
    }

    /// The skeleton.
    #[must_use]
    pub fn skeleton(&self) -> &Skeleton {
        &self.asset.skeleton
    }

    /// A joint by the rig's own name, else by the H-Anim name it is mapped to (`l_wrist` on
    /// a Mixamo rig is its `mixamorig:LeftHand`).
    #[must_use]
    pub fn joint(&self, name: &str) -> Option<usize> {
        self.skeleton()
            .find(name)
            .or_else(|| self.hanim.iter().position(|h| h.as_deref() == Some(name)))
    }

    /// A joint by the H-Anim name it is mapped to, else by the rig's own name.
    #[must_use]
    pub fn hanim_joint(&self, name: &str) -> Option<usize> {
        self.hanim
            .iter()
            .position(|h| h.as_deref() == Some(name))
            .or_else(|| self.skeleton().find(name))
    }

    /// A clip by name.
    #[must_use]
    pub fn clip(&self, name: &str) -> Option<&Arc<Clip>> {
        self.clips.iter().find(|c| c.name() == name)
    }

    /// The listing shown to clients.
    #[must_use]
    pub fn info(&self) -> AssetInfo {
        AssetInfo {
            name: self.name.clone(),
            joints: self.skeleton().len(),
            clips: self
                .clips
                .iter()
                .map(|c| ClipInfo {
                    name: c.name().to_string(),
                    duration: c.duration(),
                })
                .collect(),
            pipeline: self.pipeline.clone(),
            humanoid: self.humanoid,
            mapped: self.hanim.iter().filter(|h| h.is_some()).count(),
            notes: self.notes.clone(),
        }
    }

    /// The full description `get_asset` answers.
    #[must_use]
    pub fn detail(&self) -> AssetDetail {
        let sk = self.skeleton();
        AssetDetail {
            info: self.info(),
            mapping: sk
                .names()
                .iter()
                .zip(sk.parents())
                .zip(&self.hanim)
                .map(|((joint, parent), hanim)| JointMapping {
                    joint: joint.clone(),
                    parent: parent.map(|p| sk.names()[p].clone()),
                    hanim: hanim.clone(),
                })
                .collect(),
            options: self.options.clone(),
            units: self.units.clone(),
            configurable: self.upload.is_some(),
        }
    }
}
