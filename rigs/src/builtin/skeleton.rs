//! The built-in avatar's joints: H-Anim names, T-pose positions (metres, Y up, facing +Z, the
//! avatar's left at +X) and bind frames oriented along each bone.
//!
//! Everything here is `f64`: the generator rounds to `f32` only when it writes the file, so a
//! last-bit difference in a platform's `sin` or `cos` almost never changes a written byte.

use glam::{DMat3, DMat4, DQuat, DVec3};

/// Joint indices into [`JOINTS`], which is ordered parent before child.
pub mod joint {
    /// `humanoid_root`: the root, at the pelvis; the spine and `sacroiliac` hang from it.
    pub const HUMANOID_ROOT: usize = 0;
    /// `sacroiliac`: the pelvis, at the root; the legs hang from it.
    pub const SACROILIAC: usize = 1;
    /// `l_hip`: the left hip (the avatar's left, +X).
    pub const L_HIP: usize = 2;
    /// `l_knee`: the left knee.
    pub const L_KNEE: usize = 3;
    /// `l_ankle`: the left ankle.
    pub const L_ANKLE: usize = 4;
    /// `l_midtarsal`: the left midfoot; its bone runs to the toes.
    pub const L_MIDTARSAL: usize = 5;
    /// `r_hip`: the right hip (the avatar's right, −X).
    pub const R_HIP: usize = 6;
    /// `r_knee`: the right knee.
    pub const R_KNEE: usize = 7;
    /// `r_ankle`: the right ankle.
    pub const R_ANKLE: usize = 8;
    /// `r_midtarsal`: the right midfoot; its bone runs to the toes.
    pub const R_MIDTARSAL: usize = 9;
    /// `vl5`: the fifth lumbar vertebra, the bottom of the spine.
    pub const VL5: usize = 10;
    /// `vt10`: the tenth thoracic vertebra, mid-back.
    pub const VT10: usize = 11;
    /// `vt1`: the first thoracic vertebra, top of the chest; the arms hang from it.
    pub const VT1: usize = 12;
    /// `vc4`: the fourth cervical vertebra, the neck.
    pub const VC4: usize = 13;
    /// `skullbase`: the base of the skull; its bone runs to the top of the head.
    pub const SKULLBASE: usize = 14;
    /// `l_sternoclavicular`: the left collarbone's inner end.
    pub const L_STERNOCLAVICULAR: usize = 15;
    /// `l_shoulder`: the left shoulder.
    pub const L_SHOULDER: usize = 16;
    /// `l_elbow`: the left elbow.
    pub const L_ELBOW: usize = 17;
    /// `l_wrist`: the left wrist; its bone runs to the fingertips.
    pub const L_WRIST: usize = 18;
    /// `r_sternoclavicular`: the right collarbone's inner end.
    pub const R_STERNOCLAVICULAR: usize = 19;
    /// `r_shoulder`: the right shoulder.
    pub const R_SHOULDER: usize = 20;
    /// `r_elbow`: the right elbow.
    pub const R_ELBOW: usize = 21;
    /// `r_wrist`: the right wrist; its bone runs to the fingertips.
    pub const R_WRIST: usize = 22;
}

/// How many joints the built-in avatar has.
pub const JOINT_COUNT: usize = 23;

/// One joint of the T-pose: where it is and where its bone points.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct JointDef {
    /// H-Anim name.
    pub name: &'static str,
    /// Index of the parent in [`JOINTS`]; parents come first.
    pub parent: Option<usize>,
    /// Joint centre `C_j` in model space at bind (metres).
    pub head: [f64; 3],
    /// A point along the joint's bone (usually the child joint), which sets the bind frame's
    /// local +Y the way Blender's armature export does.
    pub tail: [f64; 3],
}

const fn def(
    name: &'static str,
    parent: Option<usize>,
    head: [f64; 3],
    tail: [f64; 3],
) -> JointDef {
    JointDef {
        name,
        parent,
        head,
        tail,
    }
}

/// The avatar's right side is its left mirrored through x = 0.
const fn mirror(p: [f64; 3]) -> [f64; 3] {
    [-p[0], p[1], p[2]]
}

const AT_ROOT: [f64; 3] = [0.0, 0.96, 0.0];
const AT_HIP: [f64; 3] = [0.09, 0.93, 0.0];
const AT_KNEE: [f64; 3] = [0.09, 0.50, 0.005];
const AT_ANKLE: [f64; 3] = [0.09, 0.08, 0.0];
const AT_MIDTARSAL: [f64; 3] = [0.09, 0.035, 0.10];
const AT_TOE: [f64; 3] = [0.09, 0.025, 0.20];
const AT_VL5: [f64; 3] = [0.0, 1.05, -0.01];
const AT_VT10: [f64; 3] = [0.0, 1.22, -0.02];
const AT_VT1: [f64; 3] = [0.0, 1.40, -0.02];
const AT_VC4: [f64; 3] = [0.0, 1.50, -0.01];
const AT_SKULLBASE: [f64; 3] = [0.0, 1.60, 0.0];
const AT_HEAD_TOP: [f64; 3] = [0.0, 1.75, 0.0];
const AT_STERNOCLAVICULAR: [f64; 3] = [0.03, 1.42, 0.02];
const AT_SHOULDER: [f64; 3] = [0.18, 1.42, 0.0];
const AT_ELBOW: [f64; 3] = [0.46, 1.42, 0.0];
const AT_WRIST: [f64; 3] = [0.72, 1.42, 0.0];
const AT_FINGERTIP: [f64; 3] = [0.90, 1.42, 0.0];

/// The joints in T-pose, parent before child (the H-Anim hierarchy: legs hang from
/// `sacroiliac`, the spine from `humanoid_root`, the arms from `vt1`).
pub const JOINTS: [JointDef; JOINT_COUNT] = {
    use joint::*;
    [
        def("humanoid_root", None, AT_ROOT, [0.0, 1.05, 0.0]),
        def("sacroiliac", Some(HUMANOID_ROOT), AT_ROOT, [0.0, 0.88, 0.0]),
        def("l_hip", Some(SACROILIAC), AT_HIP, AT_KNEE),
        def("l_knee", Some(L_HIP), AT_KNEE, AT_ANKLE),
        def("l_ankle", Some(L_KNEE), AT_ANKLE, AT_MIDTARSAL),
        def("l_midtarsal", Some(L_ANKLE), AT_MIDTARSAL, AT_TOE),
        def("r_hip", Some(SACROILIAC), mirror(AT_HIP), mirror(AT_KNEE)),
        def("r_knee", Some(R_HIP), mirror(AT_KNEE), mirror(AT_ANKLE)),
        def(
            "r_ankle",
            Some(R_KNEE),
            mirror(AT_ANKLE),
            mirror(AT_MIDTARSAL),
        ),
        def(
            "r_midtarsal",
            Some(R_ANKLE),
            mirror(AT_MIDTARSAL),
            mirror(AT_TOE),
        ),
        def("vl5", Some(HUMANOID_ROOT), AT_VL5, AT_VT10),
        def("vt10", Some(VL5), AT_VT10, AT_VT1),
        def("vt1", Some(VT10), AT_VT1, AT_VC4),
        def("vc4", Some(VT1), AT_VC4, AT_SKULLBASE),
        def("skullbase", Some(VC4), AT_SKULLBASE, AT_HEAD_TOP),
        def(
            "l_sternoclavicular",
            Some(VT1),
            AT_STERNOCLAVICULAR,
            AT_SHOULDER,
        ),
        def(
            "l_shoulder",
            Some(L_STERNOCLAVICULAR),
            AT_SHOULDER,
            AT_ELBOW,
        ),
        def("l_elbow", Some(L_SHOULDER), AT_ELBOW, AT_WRIST),
        def("l_wrist", Some(L_ELBOW), AT_WRIST, AT_FINGERTIP),
        def(
            "r_sternoclavicular",
            Some(VT1),
            mirror(AT_STERNOCLAVICULAR),
            mirror(AT_SHOULDER),
        ),
        def(
            "r_shoulder",
            Some(R_STERNOCLAVICULAR),
            mirror(AT_SHOULDER),
            mirror(AT_ELBOW),
        ),
        def(
            "r_elbow",
            Some(R_SHOULDER),
            mirror(AT_ELBOW),
            mirror(AT_WRIST),
        ),
        def(
            "r_wrist",
            Some(R_ELBOW),
            mirror(AT_WRIST),
            mirror(AT_FINGERTIP),
        ),
    ]
};

/// The joint names in file order.
pub fn joint_names() -> impl Iterator<Item = &'static str> {
    JOINTS.iter().map(|j| j.name)
}

/// The T-pose bind of every joint: `B_j = T(C_j) · U_j`, with `U_j` turning local +Y onto the
/// bone. Rest equals bind: the rest locals are derived from these.
#[derive(Clone, Debug, PartialEq)]
pub struct Rig {
    /// `C_j`, model space, metres.
    pub position: Vec<DVec3>,
    /// `U_j`, model space.
    pub rotation: Vec<DQuat>,
}

impl Default for Rig {
    fn default() -> Self {
        Self::new()
    }
}

impl Rig {
    /// Derives the bind frames from [`JOINTS`].
    #[must_use]
    pub fn new() -> Self {
        Self {
            position: JOINTS.iter().map(|j| DVec3::from(j.head)).collect(),
            rotation: JOINTS.iter().map(bone_frame).collect(),
        }
    }

    fn parent_frame(&self, j: usize) -> (DVec3, DQuat) {
        match JOINTS[j].parent {
            Some(p) => (self.position[p], self.rotation[p]),
            None => (DVec3::ZERO, DQuat::IDENTITY),
        }
    }

    /// The rest (= bind) local transform `D_j = B_parent⁻¹ · B_j` (seed 001's `L_j`):
    /// `t_j = U_p⁻¹ (C_j − C_p)`, `R_j = U_p⁻¹ U_j`.
    #[must_use]
    pub fn rest_local(&self, j: usize) -> (DVec3, DQuat) {
        let (c_p, u_p) = self.parent_frame(j);
        let inv = u_p.inverse();
        (
            inv * (self.position[j] - c_p),
            (inv * self.rotation[j]).normalize(),
        )
    }

    /// `B_j⁻¹ = U_j⁻¹ · T(−C_j)`.
    #[must_use]
    pub fn inverse_bind(&self, j: usize) -> DMat4 {
        DMat4::from_rotation_translation(self.rotation[j], self.position[j]).inverse()
    }

    /// The joint-local rotation that poses joint `j` by `delta`, where `delta` is expressed in
    /// the world-aligned frame the parent carries (the frame a simplified rig, with every bind
    /// rotation identity, would use): `R_j = U_p⁻¹ · Δ_j · U_j`. This is seed 000's
    /// `R'_i = V_p R_i V_i⁻¹` with `V = U`, solved for the rotated-frame `R_i`.
    #[must_use]
    pub fn local_rotation(&self, j: usize, delta: DQuat) -> DQuat {
        let (_, u_p) = self.parent_frame(j);
        (u_p.inverse() * delta * self.rotation[j]).normalize()
    }

    /// Joint centres in model space for a pose given as per-joint `delta`s (see
    /// [`Rig::local_rotation`]) and an offset of `humanoid_root` from its bind position.
    ///
    /// With `W_j = Δ_0 ⋯ Δ_j · U_j`, a child sits at `C'_p + (Δ_0 ⋯ Δ_p)(C_j − C_p)`.
    #[must_use]
    pub fn joint_positions(&self, delta: &[DQuat; JOINT_COUNT], root_offset: DVec3) -> Vec<DVec3> {
        let mut carried = [DQuat::IDENTITY; JOINT_COUNT];
        let mut position = vec![DVec3::ZERO; JOINT_COUNT];
        for (j, def) in JOINTS.iter().enumerate() {
            match def.parent {
                Some(p) => {
                    position[j] = position[p] + carried[p] * (self.position[j] - self.position[p]);
                    carried[j] = carried[p] * delta[j];
                }
                None => {
                    position[j] = self.position[j] + root_offset;
                    carried[j] = delta[j];
                }
            }
        }
        position
    }
}

/// `U_j`: local +Y along the bone; local +Z towards the front (+Z) for bones that do not point
/// forwards, else towards up (+Y) — the roll Blender picks for a humanoid built facing -Y, here
/// turned to face +Z.
fn bone_frame(def: &JointDef) -> DQuat {
    let y = (DVec3::from(def.tail) - DVec3::from(def.head)).normalize();
    let reference = if y.z.abs() > 0.7 { DVec3::Y } else { DVec3::Z };
    let x = y.cross(reference).normalize();
    let z = x.cross(y);
    DQuat::from_mat3(&DMat3::from_cols(x, y, z)).normalize()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn constants_name_their_joints() {
        let named = [
            (joint::HUMANOID_ROOT, "humanoid_root"),
            (joint::SACROILIAC, "sacroiliac"),
            (joint::L_HIP, "l_hip"),
            (joint::L_KNEE, "l_knee"),
            (joint::L_ANKLE, "l_ankle"),
            (joint::L_MIDTARSAL, "l_midtarsal"),
            (joint::R_HIP, "r_hip"),
            (joint::R_KNEE, "r_knee"),
            (joint::R_ANKLE, "r_ankle"),
            (joint::R_MIDTARSAL, "r_midtarsal"),
            (joint::VL5, "vl5"),
            (joint::VT10, "vt10"),
            (joint::VT1, "vt1"),
            (joint::VC4, "vc4"),
            (joint::SKULLBASE, "skullbase"),
            (joint::L_STERNOCLAVICULAR, "l_sternoclavicular"),
            (joint::L_SHOULDER, "l_shoulder"),
            (joint::L_ELBOW, "l_elbow"),
            (joint::L_WRIST, "l_wrist"),
            (joint::R_STERNOCLAVICULAR, "r_sternoclavicular"),
            (joint::R_SHOULDER, "r_shoulder"),
            (joint::R_ELBOW, "r_elbow"),
            (joint::R_WRIST, "r_wrist"),
        ];
        assert_eq!(named.len(), JOINT_COUNT);
        for (index, name) in named {
            assert_eq!(JOINTS[index].name, name);
        }
        for (j, def) in JOINTS.iter().enumerate() {
            assert!(
                def.parent.is_none_or(|p| p < j),
                "{} before its parent",
                def.name
            );
        }
    }

    #[test]
    fn bind_frames_point_local_y_along_the_bone() {
        let rig = Rig::new();
        for (j, def) in JOINTS.iter().enumerate() {
            let bone = (DVec3::from(def.tail) - DVec3::from(def.head)).normalize();
            let local_y = rig.rotation[j] * DVec3::Y;
            assert!((local_y - bone).length() < 1e-12, "{}", def.name);
        }
        // The leg points down: its frame is a half turn, far from identity.
        assert!(rig.rotation[joint::L_KNEE].angle_between(DQuat::IDENTITY) > 3.0);
    }

    #[test]
    fn rest_locals_chain_back_to_the_bind() {
        let rig = Rig::new();
        let mut world: Vec<DMat4> = Vec::new();
        for (j, def) in JOINTS.iter().enumerate() {
            let (t, r) = rig.rest_local(j);
            let local = DMat4::from_rotation_translation(r, t);
            let w = def.parent.map_or(local, |p| world[p] * local);
            let identity = w * rig.inverse_bind(j);
            assert!(identity.abs_diff_eq(DMat4::IDENTITY, 1e-12), "{}", def.name);
            world.push(w);
        }
    }

    #[test]
    fn identity_deltas_give_the_bind_pose() {
        let rig = Rig::new();
        let at_rest = rig.joint_positions(&[DQuat::IDENTITY; JOINT_COUNT], DVec3::ZERO);
        for (p, c) in at_rest.iter().zip(&rig.position) {
            assert!(p.abs_diff_eq(*c, 1e-12));
        }
        for j in 0..JOINT_COUNT {
            let r = rig.local_rotation(j, DQuat::IDENTITY);
            assert!(r.abs_diff_eq(rig.rest_local(j).1, 1e-12));
        }
    }
}
