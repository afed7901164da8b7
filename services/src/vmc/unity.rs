//! Unity's side of the VMC protocol: its coordinate frame, its humanoid bone names
//! (`HumanBodyBones`) with their H-Anim names, and a typical humanoid's T-pose in glTF's frame.
//!
//! Unity is left-handed, Y up, the model facing +Z with its left at −X. glTF (and posecast) is
//! right-handed, Y up, the model facing +Z with its left at +X. Mirroring X maps one onto the
//! other and keeps the model facing +Z: a position `(x, y, z)` becomes `(−x, y, z)`, and a
//! rotation, conjugated by the mirror `M = diag(−1, 1, 1)` (`R' = M R M`: the axis mirrored,
//! the angle negated because a mirror reverses orientation), `(x, y, z, w)` becomes
//! `(x, −y, −z, w)`. Both maps are their own inverse. (Khronos' UnityGLTF converts the same
//! way, "multiply by a negative X scale"; UniVRM's VRM 0 exporter mirrors Z instead and so
//! turns models to face −Z, which posecast does not want.)

use glam::{Quat, Vec3};

/// A Unity position in glTF's frame (and back: the map is an involution).
#[must_use]
pub fn mirror_position(p: Vec3) -> Vec3 {
    Vec3::new(-p.x, p.y, p.z)
}

/// A Unity rotation in glTF's frame, `M R M` with `M = diag(−1, 1, 1)` (and back).
#[must_use]
pub fn mirror_rotation(q: Quat) -> Quat {
    Quat::from_xyzw(q.x, -q.y, -q.z, q.w)
}

/// Every `HumanBodyBones` name (Unity's enum, `LastBone` excepted): names a performer may send.
/// Those without an entry in [`BONES`] (eyes, jaw) are recognised and ignored.
pub const HUMAN_BODY_BONES: [&str; 55] = [
    "Hips",
    "LeftUpperLeg",
    "RightUpperLeg",
    "LeftLowerLeg",
    "RightLowerLeg",
    "LeftFoot",
    "RightFoot",
    "Spine",
    "Chest",
    "Neck",
    "Head",
    "LeftShoulder",
    "RightShoulder",
    "LeftUpperArm",
    "RightUpperArm",
    "LeftLowerArm",
    "RightLowerArm",
    "LeftHand",
    "RightHand",
    "LeftToes",
    "RightToes",
    "LeftEye",
    "RightEye",
    "Jaw",
    "LeftThumbProximal",
    "LeftThumbIntermediate",
    "LeftThumbDistal",
    "LeftIndexProximal",
    "LeftIndexIntermediate",
    "LeftIndexDistal",
    "LeftMiddleProximal",
    "LeftMiddleIntermediate",
    "LeftMiddleDistal",
    "LeftRingProximal",
    "LeftRingIntermediate",
    "LeftRingDistal",
    "LeftLittleProximal",
    "LeftLittleIntermediate",
    "LeftLittleDistal",
    "RightThumbProximal",
    "RightThumbIntermediate",
    "RightThumbDistal",
    "RightIndexProximal",
    "RightIndexIntermediate",
    "RightIndexDistal",
    "RightMiddleProximal",
    "RightMiddleIntermediate",
    "RightMiddleDistal",
    "RightRingProximal",
    "RightRingIntermediate",
    "RightRingDistal",
    "RightLittleProximal",
    "RightLittleIntermediate",
    "RightLittleDistal",
    "UpperChest",
];

/// Whether `name` is a Unity humanoid bone name (case-sensitive, as Unity's enum).
#[must_use]
pub fn is_human_body_bone(name: &str) -> bool {
    HUMAN_BODY_BONES.contains(&name)
}

/// One bone of the T-pose rig.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Bone {
    /// Its `HumanBodyBones` name.
    pub name: &'static str,
    /// Its parent's index in [`BONES`] (parents come first).
    pub parent: Option<usize>,
    /// Its offset from the parent in the T-pose, glTF frame (left at +X), metres.
    pub offset: [f32; 3],
    /// Its H-Anim name; the torso and neck bones' names are defaults that
    /// [`super::rig::VmcRig::for_target`] fits to each avatar's spine.
    pub hanim: &'static str,
}

const fn bone(
    name: &'static str,
    parent: Option<usize>,
    offset: [f32; 3],
    hanim: &'static str,
) -> Bone {
    Bone {
        name,
        parent,
        offset,
        hanim,
    }
}

/// Indices into [`BONES`] of the bones others hang from.
mod at {
    pub const HIPS: usize = 0;
    pub const SPINE: usize = 1;
    pub const CHEST: usize = 2;
    pub const UPPER_CHEST: usize = 3;
    pub const NECK: usize = 4;
    pub const L_UPPER_LEG: usize = 6;
    pub const L_LOWER_LEG: usize = 7;
    pub const L_FOOT: usize = 8;
    pub const R_UPPER_LEG: usize = 10;
    pub const R_LOWER_LEG: usize = 11;
    pub const R_FOOT: usize = 12;
    pub const L_SHOULDER: usize = 14;
    pub const L_UPPER_ARM: usize = 15;
    pub const L_LOWER_ARM: usize = 16;
    pub const L_HAND: usize = 17;
    pub const R_SHOULDER: usize = 33;
    pub const R_UPPER_ARM: usize = 34;
    pub const R_LOWER_ARM: usize = 35;
    pub const R_HAND: usize = 36;
}

/// The Unity humanoid in its T-pose, a typical adult about 1.7 m tall standing on y = 0, in
/// glTF's frame (facing +Z, left at +X), parent before child: arms straight out along ±X with
/// the palms down and the thumbs forward, legs straight down, feet forward. In VMC every bone's
/// local rotation is relative to this pose (identity in the T-pose), so these are also the
/// rest transforms (rotations identity) of the source rig the stream drives.
pub const BONES: [Bone; 52] = {
    use at::*;
    [
        bone("Hips", None, [0.0, 0.95, 0.0], "humanoid_root"),
        bone("Spine", Some(HIPS), [0.0, 0.10, 0.0], "vl5"),
        bone("Chest", Some(SPINE), [0.0, 0.12, 0.0], "vt10"),
        bone("UpperChest", Some(CHEST), [0.0, 0.13, 0.0], "vt1"),
        bone("Neck", Some(UPPER_CHEST), [0.0, 0.12, 0.0], "vc4"),
        bone("Head", Some(NECK), [0.0, 0.10, 0.0], "skullbase"),
        // 6: the left leg.
        bone("LeftUpperLeg", Some(HIPS), [0.09, -0.05, 0.0], "l_hip"),
        bone(
            "LeftLowerLeg",
            Some(L_UPPER_LEG),
            [0.0, -0.42, 0.0],
            "l_knee",
        ),
        bone("LeftFoot", Some(L_LOWER_LEG), [0.0, -0.41, 0.0], "l_ankle"),
        bone("LeftToes", Some(L_FOOT), [0.0, 0.0, 0.13], "l_midtarsal"),
        // 10: the right leg.
        bone("RightUpperLeg", Some(HIPS), [-0.09, -0.05, 0.0], "r_hip"),
        bone(
            "RightLowerLeg",
            Some(R_UPPER_LEG),
            [0.0, -0.42, 0.0],
            "r_knee",
        ),
        bone("RightFoot", Some(R_LOWER_LEG), [0.0, -0.41, 0.0], "r_ankle"),
        bone("RightToes", Some(R_FOOT), [0.0, 0.0, 0.13], "r_midtarsal"),
        // 14: the left arm and hand.
        bone(
            "LeftShoulder",
            Some(UPPER_CHEST),
            [0.03, 0.09, 0.0],
            "l_sternoclavicular",
        ),
        bone(
            "LeftUpperArm",
            Some(L_SHOULDER),
            [0.14, 0.0, 0.0],
            "l_shoulder",
        ),
        bone(
            "LeftLowerArm",
            Some(L_UPPER_ARM),
            [0.27, 0.0, 0.0],
            "l_elbow",
        ),
        bone("LeftHand", Some(L_LOWER_ARM), [0.25, 0.0, 0.0], "l_wrist"),
        bone(
            "LeftThumbProximal",
            Some(L_HAND),
            [0.02, 0.0, 0.025],
            "l_thumb1",
        ),
        bone(
            "LeftThumbIntermediate",
            Some(18),
            [0.025, 0.0, 0.02],
            "l_thumb2",
        ),
        bone("LeftThumbDistal", Some(19), [0.025, 0.0, 0.01], "l_thumb3"),
        bone(
            "LeftIndexProximal",
            Some(L_HAND),
            [0.09, 0.0, 0.025],
            "l_index1",
        ),
        bone(
            "LeftIndexIntermediate",
            Some(21),
            [0.04, 0.0, 0.0],
            "l_index2",
        ),
        bone("LeftIndexDistal", Some(22), [0.025, 0.0, 0.0], "l_index3"),
        bone(
            "LeftMiddleProximal",
            Some(L_HAND),
            [0.095, 0.0, 0.0],
            "l_middle1",
        ),
        bone(
            "LeftMiddleIntermediate",
            Some(24),
            [0.045, 0.0, 0.0],
            "l_middle2",
        ),
        bone("LeftMiddleDistal", Some(25), [0.028, 0.0, 0.0], "l_middle3"),
        bone(
            "LeftRingProximal",
            Some(L_HAND),
            [0.09, 0.0, -0.015],
            "l_ring1",
        ),
        bone(
            "LeftRingIntermediate",
            Some(27),
            [0.04, 0.0, 0.0],
            "l_ring2",
        ),
        bone("LeftRingDistal", Some(28), [0.026, 0.0, 0.0], "l_ring3"),
        bone(
            "LeftLittleProximal",
            Some(L_HAND),
            [0.08, 0.0, -0.035],
            "l_pinky1",
        ),
        bone(
            "LeftLittleIntermediate",
            Some(30),
            [0.032, 0.0, 0.0],
            "l_pinky2",
        ),
        bone("LeftLittleDistal", Some(31), [0.022, 0.0, 0.0], "l_pinky3"),
        // 33: the right arm and hand, the left mirrored.
        bone(
            "RightShoulder",
            Some(UPPER_CHEST),
            [-0.03, 0.09, 0.0],
            "r_sternoclavicular",
        ),
        bone(
            "RightUpperArm",
            Some(R_SHOULDER),
            [-0.14, 0.0, 0.0],
            "r_shoulder",
        ),
        bone(
            "RightLowerArm",
            Some(R_UPPER_ARM),
            [-0.27, 0.0, 0.0],
            "r_elbow",
        ),
        bone("RightHand", Some(R_LOWER_ARM), [-0.25, 0.0, 0.0], "r_wrist"),
        bone(
            "RightThumbProximal",
            Some(R_HAND),
            [-0.02, 0.0, 0.025],
            "r_thumb1",
        ),
        bone(
            "RightThumbIntermediate",
            Some(37),
            [-0.025, 0.0, 0.02],
            "r_thumb2",
        ),
        bone(
            "RightThumbDistal",
            Some(38),
            [-0.025, 0.0, 0.01],
            "r_thumb3",
        ),
        bone(
            "RightIndexProximal",
            Some(R_HAND),
            [-0.09, 0.0, 0.025],
            "r_index1",
        ),
        bone(
            "RightIndexIntermediate",
            Some(40),
            [-0.04, 0.0, 0.0],
            "r_index2",
        ),
        bone("RightIndexDistal", Some(41), [-0.025, 0.0, 0.0], "r_index3"),
        bone(
            "RightMiddleProximal",
            Some(R_HAND),
            [-0.095, 0.0, 0.0],
            "r_middle1",
        ),
        bone(
            "RightMiddleIntermediate",
            Some(43),
            [-0.045, 0.0, 0.0],
            "r_middle2",
        ),
        bone(
            "RightMiddleDistal",
            Some(44),
            [-0.028, 0.0, 0.0],
            "r_middle3",
        ),
        bone(
            "RightRingProximal",
            Some(R_HAND),
            [-0.09, 0.0, -0.015],
            "r_ring1",
        ),
        bone(
            "RightRingIntermediate",
            Some(46),
            [-0.04, 0.0, 0.0],
            "r_ring2",
        ),
        bone("RightRingDistal", Some(47), [-0.026, 0.0, 0.0], "r_ring3"),
        bone(
            "RightLittleProximal",
            Some(R_HAND),
            [-0.08, 0.0, -0.035],
            "r_pinky1",
        ),
        bone(
            "RightLittleIntermediate",
            Some(49),
            [-0.032, 0.0, 0.0],
            "r_pinky2",
        ),
        bone(
            "RightLittleDistal",
            Some(50),
            [-0.022, 0.0, 0.0],
            "r_pinky3",
        ),
    ]
};

/// The T-pose leg length (hip to knee to ankle) of [`BONES`], metres: a performer's own leg
/// length, from the bone positions it sends, over this is its model's scale.
pub const LEG_LENGTH: f32 = 0.42 + 0.41;

/// The bones whose offsets give a performer's leg length: (knee, ankle) of each side.
pub const LEG_BONES: [(usize, usize); 2] =
    [(at::L_LOWER_LEG, at::L_FOOT), (at::R_LOWER_LEG, at::R_FOOT)];

/// Index of a bone of [`BONES`] by name.
#[must_use]
pub fn bone_index(name: &str) -> Option<usize> {
    BONES.iter().position(|b| b.name == name)
}

/// The torso bones from the pelvis up and the neck: the ones whose H-Anim names follow the
/// avatar ([`super::rig::VmcRig::for_target`]).
pub const TORSO: [usize; 3] = [at::SPINE, at::CHEST, at::UPPER_CHEST];
/// See [`TORSO`].
pub const NECK: usize = at::NECK;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bones_are_parent_first_named_once_and_human_body_bones() {
        for (i, b) in BONES.iter().enumerate() {
            assert!(b.parent.is_none_or(|p| p < i), "{}", b.name);
            assert!(is_human_body_bone(b.name), "{}", b.name);
            assert_eq!(bone_index(b.name), Some(i));
            assert!(posecast_rigs::rig::names::is_hanim(b.hanim), "{}", b.hanim);
        }
        // The right side mirrors the left.
        for (i, b) in BONES.iter().enumerate() {
            if let Some(rest) = b.name.strip_prefix("Left") {
                let r = bone_index(&format!("Right{rest}")).unwrap();
                let o = BONES[r].offset;
                assert_eq!([-o[0], o[1], o[2]], b.offset, "{}", b.name);
                assert_eq!(BONES[r].hanim, b.hanim.replacen("l_", "r_", 1));
                assert_eq!(
                    BONES[r]
                        .parent
                        .map(|p| BONES[p].name.replace("Right", "Left")),
                    b.parent.map(|p| BONES[p].name.to_owned()),
                    "{i}"
                );
            }
        }
    }

    /// The mirror conjugates rotations: mirrored rotation of a mirrored vector is the
    /// mirrored rotated vector (`M R M · M v = M R v`), and it is its own inverse.
    #[test]
    fn mirroring_conjugates_rotations() {
        let q = Quat::from_euler(glam::EulerRot::XYZ, 0.3, -1.1, 0.7);
        let v = Vec3::new(0.2, -0.5, 0.9);
        let left = mirror_rotation(q) * mirror_position(v);
        let right = mirror_position(q * v);
        assert!(left.abs_diff_eq(right, 1e-6), "{left} {right}");
        assert_eq!(mirror_rotation(mirror_rotation(q)), q);
        // A Unity turn to the model's left (−90° about Unity's Y: +Z forward to −X, Unity's
        // left) is a turn to the left in glTF too: +Z forward to +X.
        let turn_left = mirror_rotation(Quat::from_rotation_y(-std::f32::consts::FRAC_PI_2));
        assert!((turn_left * Vec3::Z).abs_diff_eq(Vec3::X, 1e-6));
    }
}
