//! VRM avatars (`.vrm` files are GLB): the humanoid bone map of VRM 0.x (the `VRM` extension,
//! `humanoid.humanBones: [{bone, node}]`) and VRM 1.0 (`VRMC_vrm`,
//! `humanoid.humanBones: {bone: {node}}`), read as H-Anim names. The file's JSON is read again
//! here because the `gltf` crate keeps no unknown extensions.

use serde_json::Value;

/// Which VRM specification a file follows.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Version {
    /// VRM 0.x (`VRM` extension).
    V0,
    /// VRM 1.0 (`VRMC_vrm` extension).
    V1,
}

/// A VRM's humanoid bones: its version and, per bone, the node and the H-Anim name.
#[derive(Clone, Debug, PartialEq)]
pub struct Humanoid {
    /// Which VRM version's extension the bones came from.
    pub version: Version,
    /// `(node index, VRM bone name, H-Anim name)`; bones without an H-Anim counterpart (eyes,
    /// jaw) are left out.
    pub bones: Vec<(usize, String, String)>,
}

/// The JSON of a glTF document: a GLB's JSON chunk, or the bytes themselves.
#[must_use]
pub fn json_chunk(bytes: &[u8]) -> Option<&[u8]> {
    if bytes.starts_with(b"glTF") {
        let len = u32::from_le_bytes(bytes.get(12..16)?.try_into().ok()?) as usize;
        if bytes.get(16..20)? != b"JSON" {
            return None;
        }
        bytes.get(20..20usize.checked_add(len)?)
    } else {
        Some(bytes)
    }
}

/// The humanoid bone map of a glTF document (GLB or JSON bytes), if it is a VRM.
#[must_use]
pub fn humanoid(bytes: &[u8]) -> Option<Humanoid> {
    let doc: Value = serde_json::from_slice(json_chunk(bytes)?).ok()?;
    humanoid_of(&doc)
}

/// [`humanoid`] of the document's JSON, already parsed.
#[must_use]
pub fn humanoid_of(doc: &Value) -> Option<Humanoid> {
    let ext = doc.get("extensions")?;
    let (version, pairs): (Version, Vec<(String, usize)>) =
        if let Some(bones) = ext.pointer("/VRMC_vrm/humanoid/humanBones") {
            let pairs = bones
                .as_object()?
                .iter()
                .filter_map(|(bone, v)| Some((bone.clone(), node(v.get("node")?)?)))
                .collect();
            (Version::V1, pairs)
        } else {
            let bones = ext.pointer("/VRM/humanoid/humanBones")?.as_array()?;
            let pairs = bones
                .iter()
                .filter_map(|b| Some((b.get("bone")?.as_str()?.to_owned(), node(b.get("node")?)?)))
                .collect();
            (Version::V0, pairs)
        };
    let upper_chest = pairs.iter().any(|(b, _)| b == "upperChest");
    let bones = pairs
        .into_iter()
        .filter_map(|(bone, node)| {
            let h = hanim(&bone, version, upper_chest)?;
            Some((node, bone, h))
        })
        .collect();
    Some(Humanoid { version, bones })
}

fn node(v: &Value) -> Option<usize> {
    v.as_u64().and_then(|n| usize::try_from(n).ok())
}

/// The H-Anim name of a VRM humanoid bone. The spine follows posecast's convention that the
/// joint the clavicles hang from is `vt1`: `upperChest` when the rig has one, else `chest`.
#[must_use]
pub fn hanim(bone: &str, version: Version, upper_chest: bool) -> Option<String> {
    let fixed = match bone {
        "hips" => "humanoid_root",
        "spine" => "vl5",
        "chest" if upper_chest => "vt10",
        "chest" => "vt1",
        "upperChest" => "vt1",
        "neck" => "vc4",
        "head" => "skullbase",
        _ => "",
    };
    if !fixed.is_empty() {
        return Some(fixed.to_owned());
    }
    let (side, part) = if let Some(p) = bone.strip_prefix("left") {
        ("l", p)
    } else if let Some(p) = bone.strip_prefix("right") {
        ("r", p)
    } else {
        return None;
    };
    let limb = match part {
        "Shoulder" => Some("sternoclavicular"),
        "UpperArm" => Some("shoulder"),
        "LowerArm" => Some("elbow"),
        "Hand" => Some("wrist"),
        "UpperLeg" => Some("hip"),
        "LowerLeg" => Some("knee"),
        "Foot" => Some("ankle"),
        "Toes" => Some("midtarsal"),
        _ => None,
    };
    if let Some(limb) = limb {
        return Some(format!("{side}_{limb}"));
    }
    // Fingers: VRM 1.0 thumbs are Metacarpal, Proximal, Distal; VRM 0.x thumbs and every
    // other finger Proximal, Intermediate, Distal.
    for (word, finger) in [
        ("Thumb", "thumb"),
        ("Index", "index"),
        ("Middle", "middle"),
        ("Ring", "ring"),
        ("Little", "pinky"),
    ] {
        let Some(segment) = part.strip_prefix(word) else {
            continue;
        };
        let k = match (segment, finger, version) {
            ("Metacarpal", "thumb", Version::V1) => 1,
            ("Proximal", "thumb", Version::V1) => 2,
            ("Proximal", _, _) => 1,
            ("Intermediate", _, _) => 2,
            ("Distal", _, _) => 3,
            _ => return None,
        };
        return Some(format!("{side}_{finger}{k}"));
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn both_versions_read() {
        let v0 = br#"{"extensions":{"VRM":{"humanoid":{"humanBones":[
            {"bone":"hips","node":0},{"bone":"leftUpperArm","node":3},{"bone":"leftEye","node":9},
            {"bone":"leftThumbProximal","node":5}]}}}}"#;
        let h = humanoid(v0).unwrap();
        assert_eq!(h.version, Version::V0);
        let names: Vec<&str> = h.bones.iter().map(|b| b.2.as_str()).collect();
        assert_eq!(names, ["humanoid_root", "l_shoulder", "l_thumb1"]);
        let v1 = br#"{"extensions":{"VRMC_vrm":{"humanoid":{"humanBones":{
            "chest":{"node":2},"rightThumbProximal":{"node":7}}}}}}"#;
        let h = humanoid(v1).unwrap();
        assert_eq!(h.version, Version::V1);
        let names: Vec<&str> = h.bones.iter().map(|b| b.2.as_str()).collect();
        assert_eq!(names, ["vt1", "r_thumb2"]);
        assert!(humanoid(br#"{"asset":{"version":"2.0"}}"#).is_none());
        assert!(humanoid(b"glTF\x02\0\0\0").is_none());
    }
}
