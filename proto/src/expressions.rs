//! One expression vocabulary for face morph targets (blend shapes).
//!
//! Every rig names its morph targets its own way (Ready Player Me `mouthOpen`, `eyesClosed`;
//! ARKit-style `eyeBlinkLeft`, `eyeBlink_L`, `EyeBlinkLeft`; VRM 0.x clips `A`, `Blink_L`,
//! `Joy`; Oculus visemes `viseme_aa`), while clients send weights by *standard names*, the
//! union of three published vocabularies:
//!
//! - [`ARKIT`]: Apple ARKit's 52 `ARFaceAnchor.BlendShapeLocation`s, camelCase as in ARKit.
//! - [`VRM_PRESETS`]: the 18 expression presets of VRM 1.0 (`VRMC_vrm` `expressions.preset`).
//! - [`OCULUS_VISEMES`]: the 15 Oculus (Meta) Lipsync visemes, prefixed `viseme_` as Ready
//!   Player Me names them (so VRM's `aa` and the viseme `viseme_aa` stay distinct).
//!
//! VRM 0.x `blendShapeMaster` `presetName`s convert to VRM 1.0 presets with [`vrm0_preset`].
//! [`auto_map`] finds a rig target for every standard name it can (exact name, then a
//! normalised name, then a table of well-known aliases) and [`resolve`] turns a name sent by a
//! client into a target index.
//!
//! Choice: a one-eye ARKit channel (`eyeLookUpLeft`) is never mapped onto a both-eyes target
//! (`eyesLookUp`): a rig with only `eyesLookUp` is driven by the VRM preset `lookUp`.

use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// Apple ARKit's 52 blend shape locations (`ARFaceAnchor.BlendShapeLocation`), in Apple's
/// documentation order and ARKit's camelCase spelling.
pub const ARKIT: [&str; 52] = [
    "eyeBlinkLeft",
    "eyeLookDownLeft",
    "eyeLookInLeft",
    "eyeLookOutLeft",
    "eyeLookUpLeft",
    "eyeSquintLeft",
    "eyeWideLeft",
    "eyeBlinkRight",
    "eyeLookDownRight",
    "eyeLookInRight",
    "eyeLookOutRight",
    "eyeLookUpRight",
    "eyeSquintRight",
    "eyeWideRight",
    "jawForward",
    "jawLeft",
    "jawRight",
    "jawOpen",
    "mouthClose",
    "mouthFunnel",
    "mouthPucker",
    "mouthLeft",
    "mouthRight",
    "mouthSmileLeft",
    "mouthSmileRight",
    "mouthFrownLeft",
    "mouthFrownRight",
    "mouthDimpleLeft",
    "mouthDimpleRight",
    "mouthStretchLeft",
    "mouthStretchRight",
    "mouthRollLower",
    "mouthRollUpper",
    "mouthShrugLower",
    "mouthShrugUpper",
    "mouthPressLeft",
    "mouthPressRight",
    "mouthLowerDownLeft",
    "mouthLowerDownRight",
    "mouthUpperUpLeft",
    "mouthUpperUpRight",
    "browDownLeft",
    "browDownRight",
    "browInnerUp",
    "browOuterUpLeft",
    "browOuterUpRight",
    "cheekPuff",
    "cheekSquintLeft",
    "cheekSquintRight",
    "noseSneerLeft",
    "noseSneerRight",
    "tongueOut",
];

/// The 18 expression presets of VRM 1.0 (`VRMC_vrm` extension, `expressions.preset`).
pub const VRM_PRESETS: [&str; 18] = [
    "happy",
    "angry",
    "sad",
    "relaxed",
    "surprised",
    "aa",
    "ih",
    "ou",
    "ee",
    "oh",
    "blink",
    "blinkLeft",
    "blinkRight",
    "lookUp",
    "lookDown",
    "lookLeft",
    "lookRight",
    "neutral",
];

/// The 15 Oculus (Meta) Lipsync visemes, with the `viseme_` prefix Ready Player Me gives them.
pub const OCULUS_VISEMES: [&str; 15] = [
    "viseme_sil",
    "viseme_PP",
    "viseme_FF",
    "viseme_TH",
    "viseme_DD",
    "viseme_kk",
    "viseme_CH",
    "viseme_SS",
    "viseme_nn",
    "viseme_RR",
    "viseme_aa",
    "viseme_E",
    "viseme_I",
    "viseme_O",
    "viseme_U",
];

/// The vocabulary a standard name belongs to.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "ts", derive(ts_rs::TS))]
#[serde(rename_all = "snake_case")]
pub enum Vocabulary {
    /// [`ARKIT`].
    Arkit,
    /// [`VRM_PRESETS`].
    Vrm,
    /// [`OCULUS_VISEMES`].
    Viseme,
}

/// Every standard name: [`ARKIT`], then [`VRM_PRESETS`], then [`OCULUS_VISEMES`] (85 names,
/// no two equal).
pub fn standard_names() -> impl Iterator<Item = &'static str> {
    ARKIT
        .iter()
        .chain(VRM_PRESETS.iter())
        .chain(OCULUS_VISEMES.iter())
        .copied()
}

/// The vocabulary of a standard name (exact, case-sensitive), `None` for any other name.
pub fn vocabulary_of(name: &str) -> Option<Vocabulary> {
    if ARKIT.contains(&name) {
        Some(Vocabulary::Arkit)
    } else if VRM_PRESETS.contains(&name) {
        Some(Vocabulary::Vrm)
    } else if OCULUS_VISEMES.contains(&name) {
        Some(Vocabulary::Viseme)
    } else {
        None
    }
}

/// VRM 0.x preset → VRM 1.0 preset. The VRM 0.x names are spelt as the clip names VMC sends
/// and VMC receivers expect (the `BlendShapePreset` names of UniVRM 0.x: `Joy`, `A`,
/// `Blink_L`); `presetName` in a file is the lower-case form.
const VRM0_PRESETS: [(&str, &str); 17] = [
    ("Neutral", "neutral"),
    ("A", "aa"),
    ("I", "ih"),
    ("U", "ou"),
    ("E", "ee"),
    ("O", "oh"),
    ("Blink", "blink"),
    ("Joy", "happy"),
    ("Angry", "angry"),
    ("Sorrow", "sad"),
    ("Fun", "relaxed"),
    ("LookUp", "lookUp"),
    ("LookDown", "lookDown"),
    ("LookLeft", "lookLeft"),
    ("LookRight", "lookRight"),
    ("Blink_L", "blinkLeft"),
    ("Blink_R", "blinkRight"),
];

/// The VRM 1.0 preset of a VRM 0.x preset name (`presetName` of `blendShapeMaster`, or the
/// clip name VMC sends such as `Joy`, `Blink_L`), ASCII case-insensitive; `None` for `unknown`
/// and any other name.
pub fn vrm0_preset(name: &str) -> Option<&'static str> {
    VRM0_PRESETS
        .iter()
        .find(|(v0, _)| v0.eq_ignore_ascii_case(name))
        .map(|&(_, v1)| v1)
}

/// Every VRM 0.x clip name VMC sends (`Joy`, `A`, `Blink_L`, …; exact case, as VMC receivers
/// compare them) with its VRM 1.0 preset.
pub fn vmc_blend_names() -> impl Iterator<Item = (&'static str, &'static str)> {
    VRM0_PRESETS.iter().copied()
}

/// Well-known rig target names of a standard name, in order of preference (a vowel shape
/// before `mouthOpen`). They match exactly or after [normalisation](normalise), and only when
/// the rig has no direct match; a few (`Blink`, `JawOpen`) already meet their standard name
/// after normalisation and are listed for the record.
const ALIASES: &[(&str, &[&str])] = &[
    ("blink", &["eyesClosed", "Blink", "EyeBlink", "blink_both"]),
    ("aa", &["A", "viseme_aa", "vrc.v_aa", "mouthOpen"]),
    ("ih", &["I", "viseme_I", "vrc.v_ih"]),
    ("ou", &["U", "viseme_U", "vrc.v_ou"]),
    ("ee", &["E", "viseme_E", "vrc.v_e"]),
    ("oh", &["O", "viseme_O", "vrc.v_oh"]),
    ("happy", &["Joy", "mouthSmile", "Smile"]),
    ("sad", &["Sorrow"]),
    ("relaxed", &["Fun"]),
    ("lookUp", &["eyesLookUp", "LookUp"]),
    ("lookDown", &["eyesLookDown"]),
    ("lookLeft", &["eyesLookLeft"]),
    ("lookRight", &["eyesLookRight"]),
    ("blinkLeft", &["eyeBlinkLeft", "Blink_L"]),
    ("blinkRight", &["eyeBlinkRight", "Blink_R"]),
    ("jawOpen", &["mouthOpen", "JawOpen"]),
    ("eyeBlinkLeft", &["Blink_L", "blinkLeft"]),
    ("eyeBlinkRight", &["Blink_R", "blinkRight"]),
    // VRChat's viseme shape keys.
    ("viseme_sil", &["vrc.v_sil"]),
    ("viseme_PP", &["vrc.v_pp"]),
    ("viseme_FF", &["vrc.v_ff"]),
    ("viseme_TH", &["vrc.v_th"]),
    ("viseme_DD", &["vrc.v_dd"]),
    ("viseme_kk", &["vrc.v_kk"]),
    ("viseme_CH", &["vrc.v_ch"]),
    ("viseme_SS", &["vrc.v_ss"]),
    ("viseme_nn", &["vrc.v_nn"]),
    ("viseme_RR", &["vrc.v_rr"]),
    ("viseme_aa", &["vrc.v_aa"]),
    ("viseme_E", &["vrc.v_e"]),
    ("viseme_I", &["vrc.v_ih"]),
    ("viseme_O", &["vrc.v_oh"]),
    ("viseme_U", &["vrc.v_ou"]),
];

/// Prefixes dropped (after lower-casing) before comparing names.
const PREFIXES: [&str; 4] = ["blendshape_", "bs_", "arkit_", "face_"];

/// The key two names are compared by: a Blender duplicate suffix (`.001`) is dropped, side
/// suffixes `_L`/`.L`/`-L`/` L` (and `R`, either case) become `left`/`right` at the end,
/// everything up to the last `.` (mesh names, `blendShape1.`, `vrc.`) and a prefix of
/// [`PREFIXES`] are dropped, the rest is lower-cased and keeps only ASCII letters and digits. `eyeBlink_L`, `head.EyeBlinkLeft` and
/// `eyeBlinkLeft` share `eyeblinkleft`; `lookLeft` (`lookleft`) never meets `look`.
fn normalise(name: &str) -> String {
    let name = name.trim();
    let name = match name.rsplit_once('.') {
        Some((rest, n)) if !n.is_empty() && n.bytes().all(|b| b.is_ascii_digit()) => rest,
        _ => name,
    };
    let mut side = "";
    let mut body = name;
    for sep in ['_', '.', '-', ' '] {
        for (letter, word) in [('l', "left"), ('r', "right")] {
            if let Some(rest) = name
                .strip_suffix(letter)
                .or_else(|| name.strip_suffix(letter.to_ascii_uppercase()))
                && let Some(rest) = rest.strip_suffix(sep)
            {
                side = word;
                body = rest;
            }
        }
    }
    let body = body.rfind('.').map_or(body, |dot| &body[dot + 1..]);
    let mut lower = body.to_ascii_lowercase();
    while let Some(rest) = PREFIXES.iter().find_map(|p| lower.strip_prefix(p)) {
        lower = rest.to_owned();
    }
    let mut key: String = lower.chars().filter(char::is_ascii_alphanumeric).collect();
    if !key.is_empty() {
        key.push_str(side);
    }
    key
}

/// The target named `name` exactly, else the first whose [normalised](normalise) key is
/// `name`'s (keys holds the targets' keys).
fn find(name: &str, targets: &[String], keys: &[String]) -> Option<usize> {
    targets.iter().position(|t| t == name).or_else(|| {
        let key = normalise(name);
        if key.is_empty() {
            None
        } else {
            keys.iter().position(|k| *k == key)
        }
    })
}

/// Standard name → rig target name, for every standard name a target is found for: the target
/// of that exact name, else the first target equal after normalisation (case, punctuation,
/// mesh and `bs_`/`arkit_`/`face_` prefixes, `_L`/`.L` ≡ `Left`), else the first alias of a
/// built-in table found the same way (`blink` ← `eyesClosed`, `aa` ← `A`, `viseme_aa`,
/// `mouthOpen`, `happy` ← `Joy`, `mouthSmile`, `jawOpen` ← `mouthOpen`, …). One target may
/// serve several standard names (`mouthOpen` is `jawOpen` and `aa`); a standard name gets at
/// most one target.
pub fn auto_map(targets: &[String]) -> BTreeMap<String, String> {
    let keys: Vec<String> = targets.iter().map(|t| normalise(t)).collect();
    let mut map = BTreeMap::new();
    for name in standard_names() {
        let aliases = ALIASES
            .iter()
            .find(|(n, _)| *n == name)
            .map_or(&[][..], |&(_, a)| a);
        let found = find(name, targets, &keys)
            .or_else(|| aliases.iter().find_map(|alias| find(alias, targets, &keys)));
        if let Some(target) = found.and_then(|i| targets.get(i)) {
            map.insert(name.to_owned(), target.clone());
        }
    }
    map
}

/// The index in `targets` of the morph target a client names `name`: the rig's own target of
/// that exact name first, then the target `map` (from [`auto_map`]) gives the standard name,
/// then the one it gives the VRM 1.0 preset of a VRM 0.x name ([`vrm0_preset`]: `Joy` →
/// `happy`). Case-sensitive except for VRM 0.x names; `None` when nothing matches.
pub fn resolve(name: &str, targets: &[String], map: &BTreeMap<String, String>) -> Option<usize> {
    let index = |target: &String| targets.iter().position(|t| t == target);
    targets
        .iter()
        .position(|t| t == name)
        .or_else(|| map.get(name).and_then(index))
        .or_else(|| vrm0_preset(name).and_then(|v1| map.get(v1)).and_then(index))
}

/// How an expression holds back a group of others while it shows (VRM 1.0 `overrideBlink`,
/// `overrideLookAt`, `overrideMouth`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "ts", derive(ts_rs::TS))]
#[serde(rename_all = "snake_case")]
pub enum Override {
    /// No effect on the group.
    #[default]
    None,
    /// The group is held at 0 while this expression's weight is above 0.
    Block,
    /// The group is scaled by `1 − weight` of this expression.
    Blend,
}

impl Override {
    /// Whether this is [`Override::None`] (for `skip_serializing_if`).
    #[must_use]
    pub fn is_none(&self) -> bool {
        *self == Self::None
    }

    /// How much of its group this override takes away at an expression's output weight `w`
    /// (three-vrm's `overrideBlinkAmount`): `block` all of it once `w > 0`, `blend` `w`.
    #[must_use]
    pub fn amount(self, w: f32) -> f32 {
        match self {
            Self::None => 0.0,
            Self::Block => f32::from(w > 0.0),
            Self::Blend => w,
        }
    }
}

/// One morph channel an expression moves, and how far at expression weight 1.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "ts", derive(ts_rs::TS))]
pub struct ExpressionBind {
    /// The morph channel (one of the description's `morph_targets`).
    pub channel: String,
    /// The channel's weight when the expression's weight is 1 (VRM 0.x `weight / 100`).
    pub weight: f32,
}

/// An expression a file defines (VRM 0.x `blendShapeMaster.blendShapeGroups`, VRM 1.0
/// `expressions.preset` and `expressions.custom`): weighted morph channels shown together, and
/// how it holds back the blink, look-at and mouth expressions while it shows.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "ts", derive(ts_rs::TS))]
pub struct Expression {
    /// Its name: the VRM 1.0 preset (`happy`, `aa`, `blinkLeft`, …; a VRM 0.x preset converted
    /// with [`vrm0_preset`]) or the file's custom name.
    pub name: String,
    /// The channels it moves.
    pub binds: Vec<ExpressionBind>,
    /// Shown only fully or not at all (weight > 0.5 is 1, else 0).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub is_binary: bool,
    /// Its effect on `blink`, `blinkLeft`, `blinkRight`.
    #[serde(default, skip_serializing_if = "Override::is_none")]
    pub override_blink: Override,
    /// Its effect on `lookUp`, `lookDown`, `lookLeft`, `lookRight`.
    #[serde(default, skip_serializing_if = "Override::is_none")]
    pub override_look_at: Override,
    /// Its effect on `aa`, `ih`, `ou`, `ee`, `oh`.
    #[serde(default, skip_serializing_if = "Override::is_none")]
    pub override_mouth: Override,
}

impl Expression {
    /// An expression of `name` moving `binds`, with no overrides.
    #[must_use]
    pub fn new(name: impl Into<String>, binds: Vec<ExpressionBind>) -> Self {
        Self {
            name: name.into(),
            binds,
            is_binary: false,
            override_blink: Override::None,
            override_look_at: Override::None,
            override_mouth: Override::None,
        }
    }

    /// The weight it shows at `w` before overrides: `w`, or for a binary one 1 above 0.5 and
    /// 0 otherwise.
    #[must_use]
    pub fn output_weight(&self, w: f32) -> f32 {
        if self.is_binary {
            f32::from(w > 0.5)
        } else {
            w
        }
    }
}

/// The override groups of VRM 1.0: blink, look-at and mouth presets.
const BLINK_GROUP: [&str; 3] = ["blink", "blinkLeft", "blinkRight"];
const LOOK_AT_GROUP: [&str; 4] = ["lookUp", "lookDown", "lookLeft", "lookRight"];
const MOUTH_GROUP: [&str; 5] = ["aa", "ih", "ou", "ee", "oh"];

/// The weight each expression of `defs` shows when they are set to `weights` (one per def,
/// missing ones 0), as the VRM 1.0 specification and its reference implementation (three-vrm's
/// `VRMExpressionManager`) evaluate them: binary expressions snap; each group (blink, look-at,
/// mouth) is scaled by `max(0, 1 − Σ amount)` over every expression's override of it
/// ([`Override::amount`]); a binary expression scaled below 1 shows 0. A channel then moves by
/// `Σ shown × bind weight` over the binds that name it.
#[must_use]
pub fn shown_weights(defs: &[Expression], weights: &[f32]) -> Vec<f32> {
    let output: Vec<f32> = defs
        .iter()
        .enumerate()
        .map(|(i, d)| d.output_weight(weights.get(i).copied().unwrap_or(0.0)))
        .collect();
    let (mut blink, mut look_at, mut mouth) = (1.0f32, 1.0f32, 1.0f32);
    for (d, &w) in defs.iter().zip(&output) {
        blink -= d.override_blink.amount(w);
        look_at -= d.override_look_at.amount(w);
        mouth -= d.override_mouth.amount(w);
    }
    defs.iter()
        .zip(output)
        .map(|(d, w)| {
            let name = d.name.as_str();
            let mut m = 1.0f32;
            if BLINK_GROUP.contains(&name) {
                m *= blink.max(0.0);
            }
            if LOOK_AT_GROUP.contains(&name) {
                m *= look_at.max(0.0);
            }
            if MOUTH_GROUP.contains(&name) {
                m *= mouth.max(0.0);
            }
            let shown = w * m;
            if d.is_binary && shown < 1.0 {
                0.0
            } else {
                shown
            }
        })
        .collect()
}

/// `map` (from [`auto_map`]) with a user's corrections applied: each entry of `corrections`
/// replaces the guess for its standard name, or removes it when the target is `""`.
///
/// # Errors
/// The first correction whose name is not a standard one (`"… is not a standard expression
/// name"`) or whose target is not one of `targets`.
pub fn corrected(
    mut map: BTreeMap<String, String>,
    corrections: &BTreeMap<String, String>,
    targets: &[String],
) -> Result<BTreeMap<String, String>, String> {
    for (name, target) in corrections {
        if vocabulary_of(name).is_none() {
            return Err(format!(
                "{name:?} is not a standard expression name (ARKit, VRM 1.0 preset or viseme_*)"
            ));
        }
        if target.is_empty() {
            map.remove(name);
        } else if targets.contains(target) {
            map.insert(name.clone(), target.clone());
        } else {
            return Err(format!(
                "{name:?} maps to {target:?}, which is not one of the rig's morph targets"
            ));
        }
    }
    Ok(map)
}

/// The index in `defs` of the expression a client names `name`: its exact name, else the VRM
/// 1.0 preset of a VRM 0.x name (`Joy` → `happy`).
#[must_use]
pub fn find_expression(defs: &[Expression], name: &str) -> Option<usize> {
    defs.iter().position(|d| d.name == name).or_else(|| {
        let v1 = vrm0_preset(name)?;
        defs.iter().position(|d| d.name == v1)
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::BTreeSet;

    fn strings(names: &[&str]) -> Vec<String> {
        names.iter().map(|n| (*n).to_owned()).collect()
    }

    fn distinct<'a>(names: impl IntoIterator<Item = &'a str>) -> usize {
        names.into_iter().collect::<BTreeSet<_>>().len()
    }

    /// The whole map, as pairs, so an extra entry fails as surely as a missing one.
    fn pairs(map: &BTreeMap<String, String>) -> BTreeSet<(&str, &str)> {
        map.iter().map(|(k, v)| (k.as_str(), v.as_str())).collect()
    }

    fn get<'a>(map: &'a BTreeMap<String, String>, name: &str) -> Option<&'a str> {
        map.get(name).map(String::as_str)
    }

    #[test]
    fn vocabularies_have_their_published_sizes_without_duplicates() {
        assert_eq!(distinct(ARKIT), 52);
        assert_eq!(distinct(VRM_PRESETS), 18);
        assert_eq!(distinct(OCULUS_VISEMES), 15);
        assert_eq!(distinct(standard_names()), 52 + 18 + 15);
        // No two standard names meet after normalisation, so no target is ambiguous.
        let keys: BTreeSet<String> = standard_names().map(normalise).collect();
        assert_eq!(keys.len(), 52 + 18 + 15);
        assert!(standard_names().all(|n| n.chars().all(|c| c.is_ascii_alphanumeric() || c == '_')));
    }

    #[test]
    fn vocabulary_of_each_list() {
        assert_eq!(vocabulary_of("jawOpen"), Some(Vocabulary::Arkit));
        assert_eq!(vocabulary_of("aa"), Some(Vocabulary::Vrm));
        assert_eq!(vocabulary_of("viseme_aa"), Some(Vocabulary::Viseme));
        assert_eq!(vocabulary_of("JawOpen"), None);
        assert_eq!(vocabulary_of(""), None);
        assert!(standard_names().all(|n| vocabulary_of(n).is_some()));
        let json = serde_json::to_string(&Vocabulary::Viseme).ok();
        assert_eq!(json.as_deref(), Some("\"viseme\""));
    }

    #[test]
    fn vrm0_presets_convert_case_insensitively() {
        for (v0, v1) in VRM0_PRESETS {
            assert_eq!(vrm0_preset(v0), Some(v1));
            assert!(VRM_PRESETS.contains(&v1), "{v1}");
        }
        assert_eq!(vrm0_preset("A"), Some("aa"));
        assert_eq!(vrm0_preset("Joy"), Some("happy"));
        assert_eq!(vrm0_preset("Blink_R"), Some("blinkRight"));
        assert_eq!(vrm0_preset("LookUp"), Some("lookUp"));
        assert_eq!(vrm0_preset("unknown"), None);
        assert_eq!(vrm0_preset("happy"), None);
    }

    #[test]
    fn ready_player_me_basic_targets() {
        let rpm = [
            "mouthOpen",
            "mouthSmile",
            "eyesClosed",
            "eyesLookUp",
            "eyesLookDown",
        ];
        let expected = [
            ("blink", "eyesClosed"),
            ("aa", "mouthOpen"),
            ("jawOpen", "mouthOpen"),
            ("happy", "mouthSmile"),
            ("lookUp", "eyesLookUp"),
            ("lookDown", "eyesLookDown"),
        ];
        // Nothing else: one-eye ARKit channels (eyeLookUpLeft, eyeBlinkLeft) stay unmapped.
        assert_eq!(
            pairs(&auto_map(&strings(&rpm))),
            expected.into_iter().collect()
        );
    }

    #[test]
    fn full_arkit_rig_maps_onto_itself() {
        let map = auto_map(&strings(&ARKIT));
        let mut expected: BTreeSet<(&str, &str)> = ARKIT.iter().map(|&n| (n, n)).collect();
        expected.insert(("blinkLeft", "eyeBlinkLeft"));
        expected.insert(("blinkRight", "eyeBlinkRight"));
        assert_eq!(pairs(&map), expected);
    }

    #[test]
    fn other_arkit_spellings() {
        let targets = [
            "Head.eyeBlink_L",
            "EyeBlinkRight",
            "JawOpen",
            "bs_mouthSmile.R",
        ];
        let map = auto_map(&strings(
            &[&targets[..], &["mouthClose.001", "Face.001"]].concat(),
        ));
        assert_eq!(get(&map, "mouthClose"), Some("mouthClose.001"));
        assert_eq!(get(&map, "eyeBlinkLeft"), Some("Head.eyeBlink_L"));
        assert_eq!(get(&map, "eyeBlinkRight"), Some("EyeBlinkRight"));
        assert_eq!(get(&map, "jawOpen"), Some("JawOpen"));
        assert_eq!(get(&map, "mouthSmileRight"), Some("bs_mouthSmile.R"));
        assert_eq!(get(&map, "mouthSmileLeft"), None);
        assert_eq!(get(&map, "blinkLeft"), Some("Head.eyeBlink_L"));
        assert_eq!(get(&map, "happy"), None);
    }

    #[test]
    fn vrm0_rig() {
        let vrm0 = ["A", "I", "U", "E", "O", "Blink", "Blink_L", "Blink_R"];
        let emotions = ["Joy", "Angry", "Sorrow", "Fun"];
        let targets = strings(&[&vrm0[..], &emotions[..]].concat());
        let map = auto_map(&targets);
        let presets = [
            "aa",
            "ih",
            "ou",
            "ee",
            "oh",
            "blink",
            "blinkLeft",
            "blinkRight",
        ];
        let emotion_presets = ["happy", "angry", "sad", "relaxed"];
        for (v1, target) in presets.iter().chain(&emotion_presets).zip(&targets) {
            assert_eq!(get(&map, v1), Some(target.as_str()), "{v1}");
        }
        assert_eq!(get(&map, "eyeBlinkLeft"), Some("Blink_L"));
        assert_eq!(get(&map, "viseme_aa"), None);
        assert_eq!(resolve("blink_r", &targets, &map), Some(7));
    }

    #[test]
    fn side_suffixes_never_collapse_onto_the_bare_name() {
        let map = auto_map(&strings(&["look", "Left", "blink"]));
        assert_eq!(pairs(&map), [("blink", "blink")].into_iter().collect());
        for target in ["lookLeft", "LookLeft", "look_left", "Face.look.L"] {
            let map = auto_map(&strings(&["look", target]));
            assert_eq!(pairs(&map), [("lookLeft", target)].into_iter().collect());
        }
    }

    #[test]
    fn direct_matches_beat_aliases_and_exact_beats_normalised() {
        let rig = ["eyesClosed", "mouthOpen", "Blink", "viseme_aa", "JAW_OPEN"];
        let map = auto_map(&strings(&rig));
        assert_eq!(get(&map, "blink"), Some("Blink"));
        assert_eq!(get(&map, "aa"), Some("viseme_aa"));
        assert_eq!(get(&map, "jawOpen"), Some("JAW_OPEN"));
        let map = auto_map(&strings(&["jaw_open", "jawOpen"]));
        assert_eq!(get(&map, "jawOpen"), Some("jawOpen"));
        let map = auto_map(&strings(&["Jaw_Open", "jaw_open"]));
        assert_eq!(get(&map, "jawOpen"), Some("Jaw_Open"));
    }

    #[test]
    fn resolve_order() {
        let targets = strings(&["mouthSmile", "happy", "mouthOpen"]);
        let mut map = BTreeMap::new();
        map.insert("happy".to_owned(), "mouthSmile".to_owned());
        map.insert("aa".to_owned(), "mouthOpen".to_owned());
        assert_eq!(resolve("happy", &targets, &map), Some(1));
        assert_eq!(resolve("mouthSmile", &targets, &map), Some(0));
        assert_eq!(resolve("aa", &targets, &map), Some(2));
        assert_eq!(resolve("A", &targets, &map), Some(2));
        assert_eq!(resolve("MOUTHSMILE", &targets, &map), None);
        assert_eq!(resolve("surprised", &targets, &map), None);
        assert_eq!(resolve("", &targets, &map), None);
        let rpm = strings(&["mouthOpen", "mouthSmile", "eyesClosed"]);
        let map = auto_map(&rpm);
        assert_eq!(resolve("Blink", &rpm, &map), Some(2));
        assert_eq!(resolve("Joy", &rpm, &map), Some(1));
        assert_eq!(resolve("jawOpen", &rpm, &map), Some(0));
    }

    #[test]
    fn odd_names_neither_panic_nor_match() {
        let odd = [
            "", ".", "_L", "_R", ".L", "bs_", "é.L", "ß_r", "..", " ", "face_bs_", "L",
        ];
        let map = auto_map(&strings(&odd));
        assert!(map.is_empty(), "{map:?}");
        for name in odd {
            assert_eq!(resolve(name, &[], &map), None);
        }
    }

    fn expr(name: &str, binary: bool, blink: Override, mouth: Override) -> Expression {
        let mut e = Expression::new(name, Vec::new());
        e.is_binary = binary;
        e.override_blink = blink;
        e.override_mouth = mouth;
        e
    }

    fn assert_close(got: &[f32], want: &[f32]) {
        assert_eq!(got.len(), want.len(), "{got:?} against {want:?}");
        assert!(
            got.iter().zip(want).all(|(g, w)| (g - w).abs() < 1e-6),
            "{got:?} against {want:?}"
        );
    }

    /// The VRM 1.0 evaluation, values derived by hand from the specification's rules.
    #[test]
    fn shown_weights_follow_vrm_overrides_and_binary() {
        use Override::{Blend, Block, None as Free};
        let defs = [
            expr("blink", false, Free, Free),
            expr("aa", false, Free, Free),
            expr("happy", false, Block, Blend),
            expr("angry", true, Free, Blend),
        ];
        // Nothing overriding: every weight as set.
        assert_close(
            &shown_weights(&defs, &[0.7, 0.6, 0.0, 0.0]),
            &[0.7, 0.6, 0.0, 0.0],
        );
        // happy 0.25 blocks blink whole and blends the mouth by 1 − 0.25.
        assert_close(
            &shown_weights(&defs, &[0.7, 0.6, 0.25]),
            &[0.0, 0.45, 0.25, 0.0],
        );
        // angry is binary: 0.5 is off (its blend takes nothing), 0.51 is on and takes the
        // rest of the mouth with happy's 0.25 (1 − 0.25 − 1 < 0 → 0).
        assert_close(
            &shown_weights(&defs, &[0.0, 0.6, 0.25, 0.5]),
            &[0.0, 0.45, 0.25, 0.0],
        );
        assert_close(
            &shown_weights(&defs, &[0.0, 0.6, 0.25, 0.51]),
            &[0.0, 0.0, 0.25, 1.0],
        );
        // A binary expression held back below 1 shows nothing.
        let held = [
            expr("blink", true, Free, Free),
            expr("sad", false, Blend, Free),
        ];
        assert_close(&shown_weights(&held, &[1.0, 0.1]), &[0.0, 0.1]);
        assert_close(&shown_weights(&held, &[1.0, 0.0]), &[1.0, 0.0]);
    }

    #[test]
    fn expressions_are_found_by_name_and_vrm0_name() {
        let defs = [expr("happy", false, Override::None, Override::None)];
        assert_eq!(find_expression(&defs, "happy"), Some(0));
        assert_eq!(find_expression(&defs, "Joy"), Some(0));
        assert_eq!(find_expression(&defs, "joy"), Some(0));
        assert_eq!(find_expression(&defs, "Happy"), None);
    }

    #[test]
    fn corrections_replace_unmap_and_refuse() {
        let targets = strings(&["mouthOpen", "eyesClosed", "smile"]);
        let map = auto_map(&targets);
        assert_eq!(get(&map, "jawOpen"), Some("mouthOpen"));
        let fix = |pairs: &[(&str, &str)]| -> BTreeMap<String, String> {
            pairs
                .iter()
                .map(|(k, v)| ((*k).to_owned(), (*v).to_owned()))
                .collect()
        };
        let c = corrected(
            map.clone(),
            &fix(&[("jawOpen", "smile"), ("blink", "")]),
            &targets,
        )
        .unwrap();
        assert_eq!(get(&c, "jawOpen"), Some("smile"));
        assert_eq!(get(&c, "blink"), None);
        assert_eq!(get(&c, "aa"), get(&map, "aa"));
        let e = corrected(map.clone(), &fix(&[("grin", "smile")]), &targets).unwrap_err();
        assert!(e.contains("not a standard expression name"), "{e}");
        let e = corrected(map, &fix(&[("jawOpen", "nope")]), &targets).unwrap_err();
        assert!(e.contains("not one of the rig's morph targets"), "{e}");
    }
}
