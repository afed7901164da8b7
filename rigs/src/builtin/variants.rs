//! Variants of the built-in avatar written as BVH text, for tests and figures: the same body
//! and clips under other exporters' joint names ([`Naming`]), optionally with every joint's
//! frame turned (a BVH holds no rest rotations, so the turns crumple its identity pose the way
//! Bandai-Namco-style offsets do, while the motion stays the same), and a small quadruped whose
//! joint names read like a person's ([`QUADRUPED_BVH`]).

use glam::Quat;

use super::{AVATAR_GLB, BuiltinError};
use crate::export::{ExportError, bvh};
use crate::import;
use crate::rig::{RigError, adjust_bind, simplify};

/// Joint names of a variant, by the built-in avatar's H-Anim names.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Naming {
    /// The built-in's own H-Anim names.
    HAnim,
    /// Mocapbank-style: `LeftCollar` is the clavicle, `LeftShoulder` the upper arm.
    Mocapbank,
    /// Bandai-Namco-style: `Shoulder_L` (clavicle), `UpperArm_L`, `LowerArm_L`, `Hand_L`.
    Bandai,
}

impl Naming {
    /// The name this naming gives the built-in joint `hanim`.
    #[must_use]
    pub fn name(self, hanim: &str) -> String {
        let table: &[(&str, &str, &str)] = &[
            // (H-Anim, mocapbank, Bandai)
            ("humanoid_root", "Hips", "Hips"),
            ("sacroiliac", "LowerHips", "LowerHips"),
            ("vl5", "Chest", "Spine"),
            ("vt10", "Chest2", "Chest"),
            ("vt1", "Chest3", "Chest2"),
            ("vc4", "Neck", "Neck"),
            ("skullbase", "Head", "Head"),
            ("sternoclavicular", "Collar", "Shoulder"),
            ("shoulder", "Shoulder", "UpperArm"),
            ("elbow", "Elbow", "LowerArm"),
            ("wrist", "Wrist", "Hand"),
            ("hip", "Hip", "UpperLeg"),
            ("knee", "Knee", "LowerLeg"),
            ("ankle", "Ankle", "Foot"),
            ("midtarsal", "Toe", "Toes"),
        ];
        if self == Self::HAnim {
            return hanim.to_owned();
        }
        let (side, part) = match hanim.split_once('_') {
            Some((s @ ("l" | "r"), part)) => (Some(s), part),
            _ => (None, hanim),
        };
        let Some(&(_, mocapbank, bandai)) = table.iter().find(|(h, _, _)| *h == part) else {
            return hanim.to_owned();
        };
        match (self, side) {
            (Self::Mocapbank, Some("l")) => format!("Left{mocapbank}"),
            (Self::Mocapbank, Some(_)) => format!("Right{mocapbank}"),
            (Self::Bandai, Some("l")) => format!("{bandai}_L"),
            (Self::Bandai, Some(_)) => format!("{bandai}_R"),
            (Self::Mocapbank, None) => mocapbank.to_owned(),
            _ => bandai.to_owned(),
        }
    }
}

/// Why a variant could not be made (never expected: the built-in avatar is tested).
#[derive(Debug, thiserror::Error)]
pub enum VariantError {
    /// The embedded avatar did not load.
    #[error(transparent)]
    Builtin(#[from] BuiltinError),
    /// Simplifying or turning the avatar's bind, or renaming its joints, failed.
    #[error(transparent)]
    Rig(#[from] RigError),
    /// Writing the BVH text failed.
    #[error(transparent)]
    Export(#[from] ExportError),
    /// The avatar has no clip of this name (its clips are [`super::CLIP_NAMES`]).
    #[error("the built-in avatar has no clip {0}")]
    NoClip(String),
    /// `turns` does not give one rotation per joint: (rotations given, joints).
    #[error("{0} rotations for {1} joints")]
    Turns(usize, usize),
}

/// The built-in avatar's clip `clip` as BVH text with `naming`'s joint names, its bind
/// simplified (so its identity pose is its T-pose), then every joint's frame turned by
/// `turns` (seed 000's bind adjustment `V_i`, one per joint) when given.
///
/// # Errors
/// An unknown clip or a wrong number of turns.
pub fn bvh(naming: Naming, clip: &str, turns: Option<&[Quat]>) -> Result<String, VariantError> {
    let mut asset = import::gltf::from_slice("avatar.glb", AVATAR_GLB)
        .map_err(BuiltinError::from)?
        .into_iter()
        .next()
        .ok_or(BuiltinError::Empty)?;
    let (simple, _, _) = simplify(asset.clone())?;
    asset = simple;
    if let Some(v) = turns {
        if v.len() != asset.skeleton.len() {
            return Err(VariantError::Turns(v.len(), asset.skeleton.len()));
        }
        asset = adjust_bind(asset, v)?.0;
    }
    let clip = asset
        .clips
        .iter()
        .find(|c| c.name() == clip)
        .ok_or_else(|| VariantError::NoClip(clip.to_owned()))?;
    let sk = &asset.skeleton;
    let names = sk.names().iter().map(|n| naming.name(n)).collect();
    let renamed = posecast_proto::Skeleton::new(
        names,
        sk.parents().to_vec(),
        sk.rest().to_vec(),
        sk.inverse_bind().to_vec(),
    )
    .map_err(RigError::from)?;
    Ok(bvh::write(&renamed, clip, None)?)
}

/// A quadruped (fox-like: a level spine, hind legs from the hips, forelegs from the chest, a
/// tail) whose joint names a name-only mapping takes for a person's: `b_Hip`, `b_Spine01`,
/// `b_LeftUpperArm`, `b_LeftLeg01`, `b_LeftFoot01`, … Centimetres, Y up, facing +Z; two frames
/// of rest.
pub const QUADRUPED_BVH: &str = "HIERARCHY
ROOT b_Hip
{
  OFFSET 0 50 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation
  JOINT b_Spine01
  {
    OFFSET 0 2 15
    CHANNELS 3 Zrotation Yrotation Xrotation
    JOINT b_Spine02
    {
      OFFSET 0 0 15
      CHANNELS 3 Zrotation Yrotation Xrotation
      JOINT b_Neck
      {
        OFFSET 0 5 10
        CHANNELS 3 Zrotation Yrotation Xrotation
        JOINT b_Head
        {
          OFFSET 0 8 8
          CHANNELS 3 Zrotation Yrotation Xrotation
          End Site
          {
            OFFSET 0 0 10
          }
        }
      }
      JOINT b_LeftUpperArm
      {
        OFFSET 8 -3 0
        CHANNELS 3 Zrotation Yrotation Xrotation
        JOINT b_LeftForeArm
        {
          OFFSET 0 -22 0
          CHANNELS 3 Zrotation Yrotation Xrotation
          JOINT b_LeftHand
          {
            OFFSET 0 -22 0
            CHANNELS 3 Zrotation Yrotation Xrotation
            End Site
            {
              OFFSET 0 -3 4
            }
          }
        }
      }
      JOINT b_RightUpperArm
      {
        OFFSET -8 -3 0
        CHANNELS 3 Zrotation Yrotation Xrotation
        JOINT b_RightForeArm
        {
          OFFSET 0 -22 0
          CHANNELS 3 Zrotation Yrotation Xrotation
          JOINT b_RightHand
          {
            OFFSET 0 -22 0
            CHANNELS 3 Zrotation Yrotation Xrotation
            End Site
            {
              OFFSET 0 -3 4
            }
          }
        }
      }
    }
  }
  JOINT b_LeftLeg01
  {
    OFFSET 8 -4 0
    CHANNELS 3 Zrotation Yrotation Xrotation
    JOINT b_LeftLeg02
    {
      OFFSET 0 -22 -2
      CHANNELS 3 Zrotation Yrotation Xrotation
      JOINT b_LeftFoot01
      {
        OFFSET 0 -22 2
        CHANNELS 3 Zrotation Yrotation Xrotation
        End Site
        {
          OFFSET 0 -2 5
        }
      }
    }
  }
  JOINT b_RightLeg01
  {
    OFFSET -8 -4 0
    CHANNELS 3 Zrotation Yrotation Xrotation
    JOINT b_RightLeg02
    {
      OFFSET 0 -22 -2
      CHANNELS 3 Zrotation Yrotation Xrotation
      JOINT b_RightFoot01
      {
        OFFSET 0 -22 2
        CHANNELS 3 Zrotation Yrotation Xrotation
        End Site
        {
          OFFSET 0 -2 5
        }
      }
    }
  }
  JOINT b_Tail01
  {
    OFFSET 0 3 -5
    CHANNELS 3 Zrotation Yrotation Xrotation
    JOINT b_Tail02
    {
      OFFSET 0 -2 -15
      CHANNELS 3 Zrotation Yrotation Xrotation
      End Site
      {
        OFFSET 0 -2 -15
      }
    }
  }
}
MOTION
Frames: 2
Frame Time: 0.5
0 50 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0
0 50 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0
";

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_and_files() {
        assert_eq!(Naming::Mocapbank.name("l_shoulder"), "LeftShoulder");
        assert_eq!(Naming::Mocapbank.name("r_sternoclavicular"), "RightCollar");
        assert_eq!(Naming::Bandai.name("l_sternoclavicular"), "Shoulder_L");
        assert_eq!(Naming::Bandai.name("vt10"), "Chest");
        let text = bvh(Naming::Mocapbank, "wave", None).unwrap();
        let asset = import::bvh::parse("wave.bvh", &text).unwrap();
        assert!(asset.skeleton.find("LeftCollar").is_some());
        let q = import::bvh::parse("fox.bvh", QUADRUPED_BVH).unwrap();
        assert_eq!(q.skeleton.len(), 19);
        assert_eq!(q.clips[0].duration(), 0.5);
    }
}
