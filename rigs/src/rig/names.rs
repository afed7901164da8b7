//! Joint names to H-Anim (ISO/IEC 19774) names: guessed from common naming schemes, overridable
//! by a mapping, with the joints left unmapped reported.
//!
//! Guessing, in order of precedence:
//! 1. a name that already is an H-Anim name (`l_hip`, `vl5`, `skullbase`, …);
//! 2. a side (`Left`/`Right`, `L`/`R`, `_l`/`_r`, `.L`, `l`/`r` glued to a known word) and a
//!    part word: Mixamo (`mixamorig:LeftUpLeg`, `LeftArm`, `LeftForeArm`), CMU/BVH (`LeftUpLeg`,
//!    `LowerBack`, `Neck1`), VRM (`leftUpperArm`, `upperChest`), Unreal (`thigh_l`, `calf_l`,
//!    `upperarm_l`);
//! 3. generic chains, as in CesiumMan and RiggedFigure (`arm_joint_L_1`, `leg_joint_R_2`,
//!    `torso_joint_3`): a side's `arm` or `leg` joints in depth order become shoulder, elbow,
//!    wrist / hip, knee, ankle, midtarsal; spine-like joints in depth order become `vl1`, `vt10`,
//!    `vt6`, …, necks `vc7`, `vc4`, …
//!
//! `humanoid_root` is the `Hips`/`Pelvis` joint or, failing that, the nearest common ancestor
//! of both hips. CMU's zero-length `LHipJoint`/`RHipJoint` connectors are left unmapped.
//!
//! Then the limbs are checked against the skeleton's **topology**: each arm is walked from the
//! hand up (its parent is the elbow, then the shoulder, then the clavicle, stopping at the joint
//! both arms hang from or at a spine joint), each leg from the foot up (knee, hip), skipping
//! twist and roll helpers. Where names and chain disagree the chain wins: in mocapbank-style
//! rigs `LeftShoulder` is the upper arm (its child is `LeftElbow`) and `LeftCollar` the
//! clavicle. The spine is then named from the chest down: the joint both arms hang from is
//! `vt1` (as in H-Anim, where the clavicles hang from `vt1`), and the generic spine joints
//! between it and the root are spread over `vl5` … `vt10` — so rigs with different numbers of
//! spine joints pair their chests when retargeted. A mapping given by the caller (a VRM
//! humanoid, a user's `name_map`) wins over all of these.

use std::collections::{BTreeMap, HashMap};

use posecast_proto::Skeleton;

use super::RigError;

/// The H-Anim spine from the pelvis up, in order (for the neutral pose's spine alignment).
pub const HANIM_SPINE: &[&str] = &[
    "humanoid_root",
    "sacroiliac",
    "vl5",
    "vl4",
    "vl3",
    "vl2",
    "vl1",
    "vt12",
    "vt11",
    "vt10",
    "vt9",
    "vt8",
    "vt7",
    "vt6",
    "vt5",
    "vt4",
    "vt3",
    "vt2",
    "vt1",
    "vc7",
    "vc6",
    "vc5",
    "vc4",
    "vc3",
    "vc2",
    "vc1",
    "skullbase",
];

/// H-Anim names of one side's limb joints, without the `l_`/`r_` prefix.
const SIDED: &[&str] = &[
    "hip",
    "knee",
    "talocrural",
    "ankle",
    "subtalar",
    "midtarsal",
    "metatarsal",
    "sternoclavicular",
    "acromioclavicular",
    "shoulder",
    "elbow",
    "radiocarpal",
    "wrist",
    "midcarpal",
];

const FINGERS: &[(&str, &str)] = &[
    ("thumb", "thumb"),
    ("index", "index"),
    ("middle", "middle"),
    ("ring", "ring"),
    ("pinky", "pinky"),
    ("little", "pinky"),
];

/// Words that carry no meaning for the mapping.
const NOISE: &[&str] = &[
    "mixamorig",
    "skeleton",
    "armature",
    "joint",
    "jnt",
    "bone",
    "bn",
    "def",
    "bip",
    "bip01",
    "b",
    "j",
    "ctrl",
    "c",
];

/// The result of mapping a skeleton's joint names.
#[derive(Clone, Debug, PartialEq)]
pub struct NameMapping {
    /// Per joint, its H-Anim name if mapped.
    pub hanim: Vec<Option<String>>,
    /// Names of the joints left unmapped, in joint order.
    pub unmapped: Vec<String>,
    /// Joints whose name-based guess the limb chains corrected, for people.
    pub corrections: Vec<String>,
}

impl NameMapping {
    /// The joint mapped to an H-Anim name.
    #[must_use]
    pub fn find(&self, hanim: &str) -> Option<usize> {
        find(&self.hanim, hanim)
    }
}

/// The joint whose H-Anim name is `hanim`.
#[must_use]
pub fn find(hanim_names: &[Option<String>], hanim: &str) -> Option<usize> {
    hanim_names.iter().position(|n| n.as_deref() == Some(hanim))
}

/// Whether `name` is an H-Anim joint name this module knows.
#[must_use]
pub fn is_hanim(name: &str) -> bool {
    HANIM_SPINE.contains(&name)
        || ["l_", "r_"].iter().any(|side| {
            name.strip_prefix(side).is_some_and(|rest| {
                SIDED.contains(&rest)
                    || FINGERS.iter().any(|(_, f)| {
                        rest.strip_prefix(f)
                            .is_some_and(|n| matches!(n, "0" | "1" | "2" | "3"))
                    })
            })
        })
}

/// Maps every joint of `skeleton` to an H-Anim name. `overrides` (joint name → H-Anim name,
/// an empty value meaning "unmapped") replaces the guess for the joints it names; naming a
/// joint the skeleton has not got is an error, as is mapping two joints to one name. Guessed
/// duplicates keep the shallowest joint.
pub fn map_names(
    skeleton: &Skeleton,
    overrides: Option<&BTreeMap<String, String>>,
    rig: &str,
) -> Result<NameMapping, RigError> {
    let n = skeleton.len();
    let depth = depths(skeleton);
    let mut hanim: Vec<Option<String>> = vec![None; n];
    // (priority, H-Anim name) per joint before chains and duplicates are resolved.
    let mut guess: Vec<Option<Guess>> = skeleton.names().iter().map(|s| classify(s)).collect();
    // Generic chains: group by (side, limb) and assign in depth order.
    let mut groups: BTreeMap<(char, Limb), Vec<usize>> = BTreeMap::new();
    let mut spine = Vec::new();
    let mut neck = Vec::new();
    for (j, g) in guess.iter().enumerate() {
        match g {
            Some(Guess::Chain(side, limb)) => groups.entry((*side, *limb)).or_default().push(j),
            Some(Guess::Spine) => spine.push(j),
            Some(Guess::Neck) => neck.push(j),
            _ => {}
        }
    }
    for ((side, limb), mut joints) in groups {
        joints.sort_by_key(|&j| (depth[j], j));
        let names: &[&str] = match (limb, joints.len()) {
            (Limb::Arm, 1) => &["shoulder"],
            (Limb::Leg, 1) => &["knee"],
            (Limb::Arm, _) => &["shoulder", "elbow", "wrist"],
            (Limb::Leg, _) => &["hip", "knee", "ankle", "midtarsal"],
        };
        for (k, &j) in joints.iter().enumerate() {
            guess[j] = names.get(k).map(|p| Guess::Name(1, format!("{side}_{p}")));
        }
    }
    // humanoid_root: Hips/Pelvis, else the nearest common ancestor of the hips.
    let has_root = guess
        .iter()
        .any(|g| matches!(g, Some(Guess::Name(_, s)) if s == "humanoid_root"));
    if !has_root {
        let hip = |side: &str| {
            guess
                .iter()
                .position(|g| matches!(g, Some(Guess::Name(_, s)) if s == &format!("{side}_hip")))
        };
        if let (Some(l), Some(r)) = (hip("l"), hip("r"))
            && let Some(a) = common_ancestor(skeleton, l, r)
        {
            guess[a] = Some(Guess::Name(1, "humanoid_root".into()));
            spine.retain(|&j| j != a);
            neck.retain(|&j| j != a);
        }
    }
    for (list, names) in [
        (&mut spine, &["vl1", "vt10", "vt6", "vt3", "vt1"][..]),
        (&mut neck, &["vc7", "vc4", "vc2", "vc1"][..]),
    ] {
        list.sort_by_key(|&j| (depth[j], j));
        for (k, &j) in list.iter().enumerate() {
            guess[j] = names.get(k).map(|s| Guess::Name(1, (*s).to_owned()));
        }
    }
    // Resolve duplicates: higher priority, then shallower, then earlier wins.
    let mut owner: HashMap<String, usize> = HashMap::new();
    let mut order: Vec<usize> = (0..n).collect();
    order.sort_by_key(|&j| {
        let p = match &guess[j] {
            Some(Guess::Name(p, _)) => *p,
            _ => 0,
        };
        (std::cmp::Reverse(p), depth[j], j)
    });
    for j in order {
        if let Some(Guess::Name(_, name)) = &guess[j]
            && !owner.contains_key(name)
        {
            owner.insert(name.clone(), j);
            hanim[j] = Some(name.clone());
        }
    }
    let mut corrections = limb_chains(skeleton, &mut hanim);
    corrections.extend(spine_by_chest(skeleton, &mut hanim, &spine));
    if let Some(map) = overrides {
        let mut by_override: HashMap<&str, &str> = HashMap::new();
        for (joint, target) in map {
            let j = skeleton.find(joint).ok_or_else(|| RigError::UnknownJoint {
                rig: rig.to_owned(),
                joint: joint.clone(),
            })?;
            if target.is_empty() {
                hanim[j] = None;
                continue;
            }
            if let Some(first) = by_override.insert(target, joint) {
                return Err(RigError::DuplicateMapping {
                    rig: rig.to_owned(),
                    hanim: target.clone(),
                    first: first.to_owned(),
                    second: joint.clone(),
                });
            }
            // An override takes the name from whichever joint guessed it.
            for h in hanim.iter_mut() {
                if h.as_deref() == Some(target.as_str()) {
                    *h = None;
                }
            }
            hanim[j] = Some(target.clone());
        }
    }
    let unmapped = hanim
        .iter()
        .zip(skeleton.names())
        .filter(|(h, _)| h.is_none())
        .map(|(_, n)| n.clone())
        .collect();
    Ok(NameMapping {
        hanim,
        unmapped,
        corrections,
    })
}

/// Renames the generic spine joints (`spine`: guessed from words like `Spine`, `Chest`) from
/// the chest down: the chest — the nearest joint both clavicles (or shoulders) hang from,
/// when it is a generic spine joint or unmapped — becomes `vt1`, and the generic spine joints
/// between the root and it, in depth order, are spread over `vl5` … `vt10` (the first `vl5`,
/// the last `vt10`). Returns what changed, for people.
fn spine_by_chest(
    skeleton: &Skeleton,
    hanim: &mut [Option<String>],
    spine: &[usize],
) -> Vec<String> {
    let parents = skeleton.parents();
    let pair = |part: &str| match (
        find(hanim, &format!("l_{part}")),
        find(hanim, &format!("r_{part}")),
    ) {
        (Some(l), Some(r)) => Some((l, r)),
        _ => None,
    };
    let (Some((l, r)), Some(root)) = (
        pair("sternoclavicular").or_else(|| pair("shoulder")),
        find(hanim, "humanoid_root"),
    ) else {
        return Vec::new();
    };
    let ancestors = |mut j: usize| {
        let mut v = vec![j];
        while let Some(p) = parents[j] {
            v.push(p);
            j = p;
        }
        v
    };
    let (al, ar) = (ancestors(l), ancestors(r));
    let Some(chest) = al.iter().copied().find(|j| ar.contains(j)) else {
        return Vec::new();
    };
    let path = ancestors(chest);
    let Some(root_at) = path.iter().position(|&j| j == root) else {
        return Vec::new();
    };
    if chest == root || !(hanim[chest].is_none() || spine.contains(&chest)) {
        return Vec::new();
    }
    // Root (exclusive) to chest (exclusive), root side first.
    let mut lower: Vec<usize> = path[1..root_at]
        .iter()
        .copied()
        .filter(|j| spine.contains(j))
        .collect();
    lower.reverse();
    let range = &HANIM_SPINE[2..=9]; // vl5 … vt10
    let wide = &HANIM_SPINE[2..=17]; // vl5 … vt2
    let list = if lower.len() <= range.len() {
        range
    } else {
        wide
    };
    let k = lower.len();
    let mut wanted: Vec<(usize, &str)> = lower
        .iter()
        .enumerate()
        .filter_map(|(i, &j)| {
            let at = if k <= 1 {
                list.len() - 1
            } else {
                (i * (list.len() - 1) + (k - 1) / 2) / (k - 1)
            };
            list.get(at).map(|name| (j, *name))
        })
        .collect();
    wanted.push((chest, "vt1"));
    let mut corrections = Vec::new();
    let names = skeleton.names();
    for (j, name) in wanted {
        if hanim[j].as_deref() == Some(name) {
            continue;
        }
        corrections.push(format!(
            "{} is {name} ({}), counting the spine from the joint both arms hang from",
            names[j],
            hanim[j]
                .as_deref()
                .map_or("unmapped by name".to_owned(), |h| format!("not {h}"))
        ));
        for h in hanim.iter_mut() {
            if h.as_deref() == Some(name) {
                *h = None;
            }
        }
        hanim[j] = Some(name.to_owned());
    }
    corrections
}

/// Twist and roll helpers sit inside limb chains without being one of their H-Anim joints.
fn is_helper(name: &str) -> bool {
    let lower = name.to_ascii_lowercase();
    lower.contains("twist") || lower.contains("roll")
}

/// Corrects each side's arm (from the wrist up: elbow, shoulder, sternoclavicular) and leg
/// (from the ankle up: knee, hip) by the skeleton's topology, stopping at a joint the other
/// side's limb also hangs from or at a spine joint. Returns what changed, for people.
fn limb_chains(skeleton: &Skeleton, hanim: &mut [Option<String>]) -> Vec<String> {
    let names = skeleton.names();
    let parents = skeleton.parents();
    let up = |j: usize| -> Option<usize> {
        let mut p = parents[j]?;
        while is_helper(&names[p]) {
            p = parents[p]?;
        }
        Some(p)
    };
    let is_self_or_ancestor = |a: usize, mut b: usize| loop {
        if a == b {
            return true;
        }
        match parents[b] {
            Some(p) => b = p,
            None => return false,
        }
    };
    let mut corrections = Vec::new();
    for (side, other) in [('l', 'r'), ('r', 'l')] {
        for (end, parts) in [
            ("wrist", &["elbow", "shoulder", "sternoclavicular"][..]),
            ("ankle", &["knee", "hip"][..]),
        ] {
            let Some(mut j) = find(hanim, &format!("{side}_{end}")) else {
                continue;
            };
            let other_end = find(hanim, &format!("{other}_{end}"));
            for part in parts {
                let Some(p) = up(j) else { break };
                let spine = hanim[p]
                    .as_deref()
                    .is_some_and(|h| HANIM_SPINE.contains(&h));
                if spine || other_end.is_some_and(|o| is_self_or_ancestor(p, o)) {
                    break;
                }
                let name = format!("{side}_{part}");
                if hanim[p].as_deref() != Some(name.as_str()) {
                    corrections.push(format!(
                        "{} is {name} ({}), its place in the chain from {side}_{end}",
                        names[p],
                        hanim[p]
                            .as_deref()
                            .map_or("unmapped by name".to_owned(), |h| {
                                format!("not {h} as its name suggests")
                            })
                    ));
                    for h in hanim.iter_mut() {
                        if h.as_deref() == Some(name.as_str()) {
                            *h = None;
                        }
                    }
                    hanim[p] = Some(name);
                }
                j = p;
            }
        }
    }
    corrections
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
enum Limb {
    Arm,
    Leg,
}

#[derive(Clone, Debug, PartialEq)]
enum Guess {
    /// A name with a priority (2: already H-Anim or an exact scheme word, 1: a chain guess).
    Name(u8, String),
    /// A generic `arm`/`leg` joint of a side, resolved by chain position.
    Chain(char, Limb),
    Spine,
    Neck,
}

fn classify(name: &str) -> Option<Guess> {
    let base = name.rsplit([':', '|']).next().unwrap_or(name);
    let lower = base.to_ascii_lowercase();
    if is_hanim(&lower) {
        return Some(Guess::Name(3, lower));
    }
    let mut side = None;
    let mut words = Vec::new();
    let mut number = None;
    for token in tokens(base) {
        let t = token.to_ascii_lowercase();
        if let Ok(k) = t.parse::<u32>() {
            number = Some(k);
            continue;
        }
        match t.as_str() {
            "left" | "l" | "lft" => side = Some('l'),
            "right" | "r" | "rt" | "rgt" => side = Some('r'),
            w if NOISE.contains(&w) => {}
            _ => words.push(t),
        }
    }
    let mut core: String = words.concat();
    // `lshoulder`, `rknee`: a side glued to a known word.
    if side.is_none() && core.len() > 1 {
        let (first, rest) = core.split_at(1);
        if matches!(first, "l" | "r") && sided_part(rest).is_some() {
            side = first.chars().next();
            core = rest.to_owned();
        }
    }
    if core == "hip" && words.len() == 1 && name.to_ascii_lowercase().contains("joint") {
        return None; // CMU's zero-length LHipJoint / RHipJoint.
    }
    if let Some(side) = side {
        for (word, hanim) in FINGERS {
            if core.contains(word) {
                return Some(Guess::Name(
                    2,
                    format!("{side}_{hanim}{}", number.unwrap_or(1)),
                ));
            }
        }
        if core == "arm" {
            return Some(Guess::Chain(side, Limb::Arm));
        }
        if core == "leg" {
            return Some(Guess::Chain(side, Limb::Leg));
        }
        return sided_part(&core).map(|p| Guess::Name(2, format!("{side}_{p}")));
    }
    match core.as_str() {
        "hips" | "hip" | "pelvis" => Some(Guess::Name(2, "humanoid_root".into())),
        "head" => Some(Guess::Name(2, "skullbase".into())),
        "neck" => Some(Guess::Neck),
        "spine" | "lowerback" | "chest" | "upperchest" | "torso" | "abdomen" => Some(Guess::Spine),
        _ => None,
    }
}

fn sided_part(core: &str) -> Option<&'static str> {
    Some(match core {
        "upleg" | "upperleg" | "thigh" | "hip" | "femur" => "hip",
        "lowerleg" | "calf" | "shin" | "knee" | "tibia" => "knee",
        "foot" | "ankle" => "ankle",
        "toebase" | "toe" | "toes" | "ball" => "midtarsal",
        "shoulder" | "clavicle" | "collar" => "sternoclavicular",
        "upperarm" | "humerus" => "shoulder",
        "forearm" | "lowerarm" | "elbow" => "elbow",
        "hand" | "wrist" => "wrist",
        _ => return None,
    })
}

/// Splits on non-alphanumerics, lower→upper case changes, letter↔digit changes and before the
/// last capital of a capital run followed by a lower-case letter (`LHipJoint` → L, Hip, Joint).
fn tokens(name: &str) -> Vec<String> {
    let chars: Vec<char> = name.chars().collect();
    let mut out = Vec::new();
    let mut cur = String::new();
    for (i, &c) in chars.iter().enumerate() {
        if !c.is_ascii_alphanumeric() {
            if !cur.is_empty() {
                out.push(std::mem::take(&mut cur));
            }
            continue;
        }
        if let Some(&prev) = cur.chars().last().as_ref() {
            let next = chars.get(i + 1).copied();
            let split = (prev.is_ascii_lowercase() && c.is_ascii_uppercase())
                || (prev.is_ascii_digit() != c.is_ascii_digit())
                || (prev.is_ascii_uppercase()
                    && c.is_ascii_uppercase()
                    && next.is_some_and(|n| n.is_ascii_lowercase()));
            if split {
                out.push(std::mem::take(&mut cur));
            }
        }
        cur.push(c);
    }
    if !cur.is_empty() {
        out.push(cur);
    }
    out
}

fn depths(skeleton: &Skeleton) -> Vec<usize> {
    let mut d = vec![0; skeleton.len()];
    for (j, p) in skeleton.parents().iter().enumerate() {
        if let Some(p) = *p {
            d[j] = d[p] + 1;
        }
    }
    d
}

fn common_ancestor(skeleton: &Skeleton, a: usize, b: usize) -> Option<usize> {
    let chain = |mut j: usize| {
        let mut v = vec![j];
        while let Some(p) = skeleton.parents()[j] {
            v.push(p);
            j = p;
        }
        v
    };
    let ca = chain(a);
    let cb = chain(b);
    ca.into_iter().skip(1).find(|j| cb.contains(j))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn guess(name: &str) -> Option<String> {
        match classify(name) {
            Some(Guess::Name(_, s)) => Some(s),
            _ => None,
        }
    }

    #[test]
    fn schemes() {
        for (name, expected) in [
            ("mixamorig:LeftUpLeg", "l_hip"),
            ("mixamorig:RightForeArm", "r_elbow"),
            ("LeftUpLeg", "l_hip"),
            ("LeftToeBase", "l_midtarsal"),
            ("LeftShoulder", "l_sternoclavicular"),
            ("leftUpperArm", "l_shoulder"),
            ("rightLowerLeg", "r_knee"),
            ("thigh_l", "l_hip"),
            ("upperarm_r", "r_shoulder"),
            ("Hand.L", "l_wrist"),
            ("L_Elbow", "l_elbow"),
            ("lshoulder", "l_sternoclavicular"),
            ("Hips", "humanoid_root"),
            ("Head", "skullbase"),
            ("l_hip", "l_hip"),
            ("vl5", "vl5"),
            ("LeftHandIndex1", "l_index1"),
        ] {
            assert_eq!(guess(name).as_deref(), Some(expected), "{name}");
        }
        assert_eq!(guess("LHipJoint"), None);
        assert_eq!(guess("LeftCollar").as_deref(), Some("l_sternoclavicular"));
        assert_eq!(guess("HeadTop_End"), None);
        assert_eq!(
            tokens("Skeleton_arm_joint_L__4_"),
            ["Skeleton", "arm", "joint", "L", "4"]
        );
    }
}

#[cfg(test)]
mod chain_tests {
    use super::*;
    use glam::Mat4;
    use posecast_proto::Transform;

    fn skeleton(joints: &[(&str, Option<usize>)]) -> Skeleton {
        let n = joints.len();
        Skeleton::new(
            joints.iter().map(|(n, _)| (*n).to_owned()).collect(),
            joints.iter().map(|(_, p)| *p).collect(),
            vec![Transform::IDENTITY; n],
            vec![Mat4::IDENTITY; n],
        )
        .unwrap()
    }

    /// Mocapbank-style arms: `LeftShoulder` is the upper arm (its child is `LeftElbow`) and
    /// `LeftCollar` the clavicle; by names alone both claim the clavicle.
    #[test]
    fn arms_are_found_from_the_hands_up() {
        let sk = skeleton(&[
            ("Hips", None),
            ("Chest", Some(0)),
            ("LeftCollar", Some(1)),
            ("LeftShoulder", Some(2)),
            ("LeftElbow", Some(3)),
            ("LeftWrist", Some(4)),
            ("RightCollar", Some(1)),
            ("RightShoulder", Some(6)),
            ("RightForeArmRoll", Some(7)),
            ("RightElbow", Some(8)),
            ("RightWrist", Some(9)),
            ("LeftHip", Some(0)),
            ("LeftKnee", Some(11)),
            ("LeftAnkle", Some(12)),
        ]);
        let m = map_names(&sk, None, "mocapbank").unwrap();
        let h = |j: usize| m.hanim[j].as_deref();
        assert_eq!(h(2), Some("l_sternoclavicular"));
        assert_eq!(h(3), Some("l_shoulder"));
        assert_eq!(h(4), Some("l_elbow"));
        assert_eq!(h(7), Some("r_shoulder"), "the roll helper is skipped");
        assert_eq!(h(8), None);
        assert_eq!(h(9), Some("r_elbow"));
        assert_eq!(h(11), Some("l_hip"));
        assert!(m.unmapped.contains(&"RightForeArmRoll".to_owned()));
        assert_eq!(m.corrections.len(), 3, "{:?}", m.corrections);
        assert_eq!(h(1), Some("vt1"), "the chest both arms hang from");
        // The user's mapping still wins.
        let mut over = BTreeMap::new();
        over.insert("LeftShoulder".to_owned(), String::new());
        let m = map_names(&sk, Some(&over), "mocapbank").unwrap();
        assert_eq!(m.hanim[3], None);
    }
}
