//! glTF 2.0 (`.gltf` + `.bin`, embedded data URIs, `.glb`) through the `gltf` crate's parser
//! and validator, with bounds-checked accessor reading of our own.
//!
//! **One asset per skeleton.** The skins of one skeleton (one per hand and one for the body
//! in FBX2glTF exports; RecursiveSkeletons' 21 skins on each of its 4 skeletons) are merged
//! into one rig whose meshes hold each primitive once (`skins.rs`); skins of disjoint
//! skeletons (two characters in one file) give several assets, `<stem>#<first skin's name
//! or index>`, each with the meshes of the nodes that use its skins and the clips that move
//! its joints. A file without skins is refused.
//!
//! **Non-joint ancestors.** The skeleton of a skin is its joints plus every ancestor node of a
//! joint. Ancestors that are not joints are folded into their children when they are static
//! (no animation channel) and rigid (unit scale): e.g. the `Z_UP` and `Armature` nodes of
//! COLLADA2GLTF exports become part of the root joint's rest transform, and a
//! [`ChannelMap`] on the root's channels applies them to animation too, so world matrices
//! equal the file's node globals exactly. Ancestors that are animated or scaled are kept as
//! joints (listed in [`SourceInfo::helper_joints`], bound at rest, weighted by nothing).
//!
//! **Meshes.** Vertices stay in mesh space; the skinned mesh node's own transform is ignored,
//! as the glTF spec requires. Meshes on nodes without a skin that hang from a joint (robots,
//! props: a mesh node parented to a bone) are imported rigidly skinned to that joint, weight 1,
//! in its bind space, so they move with it as the node hierarchy says. Triangle primitives only; `JOINTS_0`/`WEIGHTS_0` (u8 or u16,
//! float or normalised weights) and `JOINTS_1`/`WEIGHTS_1` when present (8 influences).
//! Normals are computed when absent.
//!
//! **VRM.** A `.vrm` is a GLB; its humanoid bone map (VRM 0.x `VRM`, 1.0 `VRMC_vrm`) becomes
//! [`SourceInfo::bone_map`], the mapping normalisation takes as it is ([`vrm`]).
//!
//! **Animations.** Translation, rotation and scale channels with `STEP`, `LINEAR` (slerp for
//! rotations) and `CUBICSPLINE`; a clip's range is its first to last key, so it may start
//! after 0. Morph-target weights are skipped with a note.

mod clips;
mod mesh;
mod skins;
pub mod vrm;
pub mod vrm_expressions;
pub mod vrma;
mod vrma_rig;

use std::borrow::Cow;
use std::collections::HashMap;
use std::path::Path;

use base64::Engine as _;
use glam::{Mat4, Quat, Vec3};
use gltf::animation::Property;
use posecast_proto::skeleton::topological_order;
use posecast_proto::{Skeleton, Transform};

use super::ImportError;
use super::accessor::Buffers;
use super::skel::{renamed_note, unique_names};
use crate::asset::{Asset, SourceFormat, SourceInfo, UpAxis};
use crate::clip::ChannelMap;

/// Imports a `.glb` or a `.gltf` whose buffers are embedded (GLB binary chunk or `data:`
/// URIs). External buffer files are refused: use [`super::load_path`] for those.
pub fn from_slice(name: &str, bytes: &[u8]) -> Result<Vec<Asset>, ImportError> {
    from_slice_with_base(name, bytes, None)
}

/// [`from_slice`] without the meshes: skeletons and clips only. What restoring a stored
/// recording needs (its rig's mesh is in every recording file, and decoding it thousands of
/// times dominated a restart with a full quota).
///
/// # Errors
/// As [`from_slice`].
pub fn skeletons_and_clips(name: &str, bytes: &[u8]) -> Result<Vec<Asset>, ImportError> {
    import_slice(name, bytes, None, false)
}

/// Reads an external buffer named by a plain relative URI (already checked, `%20` decoded):
/// from the file's folder ([`super::load_path`]) or from an uploaded file set.
pub(crate) type External<'a> = &'a dyn Fn(&str) -> Result<Vec<u8>, ImportError>;

/// As [`from_slice`], reading external buffers with `external` when given.
pub(crate) fn from_slice_with_base(
    name: &str,
    bytes: &[u8],
    base: Option<External<'_>>,
) -> Result<Vec<Asset>, ImportError> {
    import_slice(name, bytes, base, true)
}

fn import_slice(
    name: &str,
    bytes: &[u8],
    base: Option<External<'_>>,
    with_meshes: bool,
) -> Result<Vec<Asset>, ImportError> {
    let (document, blob) = parse(bytes).map_err(|source| ImportError::Gltf {
        file: name.to_owned(),
        source,
    })?;
    let doc = &document;
    validate(name, doc)?;
    check_channel_targets(name, doc)?;
    // The JSON once more, for the VRM extensions the gltf crate drops: once, and only when the
    // root has `extensions`, where each of them hangs (a plain glTF, like the built-in avatar,
    // is not read again). Each parse cost as much as the gltf crate's own: 0.1–0.25 ms for
    // the built-in avatar's 13 kB, which a server's start waits for.
    let json = doc
        .as_json()
        .extensions
        .is_some()
        .then(|| vrm::json_chunk(bytes))
        .flatten();
    let value = json.and_then(|j| serde_json::from_slice::<serde_json::Value>(j).ok());
    let vrm = value.as_ref().and_then(vrm::humanoid_of);
    let expressions = value.as_ref().and_then(vrm_expressions::read);
    let vrma_err = |source| ImportError::VrmAnimation {
        file: name.to_owned(),
        source,
    };
    // `vrma::read` parses again, keeping what `Value` would merge (duplicate bone keys are an
    // error there): only when the extension is there, which `Value` tells exactly (both keep
    // the last of duplicate keys on the way to it).
    let maybe_vrma = value.as_ref().is_none_or(|v| {
        v.get("extensions")
            .and_then(|e| e.get(vrma::EXTENSION))
            .is_some()
    });
    let animation = match json.filter(|_| maybe_vrma).map(vrma::read).transpose() {
        Ok(a) => a.flatten(),
        Err(e) => return Err(vrma_err(e)),
    };
    let is_vrma = super::files::extension(name) == "vrma";
    if is_vrma && animation.is_none() {
        return Err(vrma_err(vrma::VrmaError::Absent));
    }
    let source = Source {
        vrm: vrm.as_ref(),
        expressions: expressions.as_ref(),
        // A `.vrma` is always read as one; another glTF with the extension when it has no
        // skin (with one, it is a skinned rig and the extension is not its business).
        animation: animation
            .as_ref()
            .filter(|_| is_vrma || doc.skins().len() == 0),
    };
    // The gltf crate's accessors index the document with `unwrap` after its validation; a
    // gap in that validation must not take the server down, so a panic in it becomes an
    // error here (the explicit checks above and in `accessor` cover every case we know of).
    std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
        import_document(name, doc, blob, base, source, with_meshes)
    }))
    .unwrap_or_else(|_| {
        Err(ImportError::Unsupported {
            file: name.to_owned(),
            message: "the glTF parser failed on malformed input".to_owned(),
        })
    })
}

/// A glTF's document and a GLB's binary chunk, borrowed from the file.
type Parsed<'a> = (gltf::Document, Option<Cow<'a, [u8]>>);

/// `gltf::Gltf::from_slice_without_validation` less its copy of the binary chunk (all of a
/// mesh's data: 250 kB for the built-in avatar).
fn parse(bytes: &[u8]) -> Result<Parsed<'_>, gltf::Error> {
    let (json, blob) = if bytes.starts_with(b"glTF") {
        let glb = gltf::binary::Glb::from_slice(bytes)?;
        (gltf::json::deserialize::from_slice(&glb.json)?, glb.bin)
    } else {
        (gltf::json::deserialize::from_slice(bytes)?, None)
    };
    Ok((gltf::Document::from_json_without_validation(json), blob))
}

/// The `gltf` crate's validation less the one rule glTF 2.0 does not have: gltf-json 1.4
/// reports `accessors[i].bufferView: Missing data` for an accessor with neither `bufferView`
/// nor `sparse`, yet the specification (3.6.2.1, "Accessors") says such an accessor is all
/// zeros — Ready Player Me avatars have hundreds of them, as morph targets. Those are read as
/// zeros ([`super::accessor`]); every other problem is reported, the first
/// [`ImportError::MAX_LISTED`] of them and the count.
fn validate(file: &str, doc: &gltf::Document) -> Result<(), ImportError> {
    use gltf::json::validation::{Error, Validate};
    let root = doc.as_json();
    let viewless: std::collections::HashSet<String> = root
        .accessors
        .iter()
        .enumerate()
        .filter(|(_, a)| a.buffer_view.is_none())
        .map(|(i, _)| format!("accessors[{i}].bufferView"))
        .collect();
    let mut problems = Vec::new();
    root.validate(root, gltf::json::Path::new, &mut |path, error| {
        let path = path();
        if matches!(error, Error::Missing) && viewless.contains(path.as_str()) {
            return;
        }
        problems.push(format!("{path}: {error}"));
    });
    if problems.is_empty() {
        return Ok(());
    }
    let count = problems.len();
    problems.truncate(ImportError::MAX_LISTED);
    Err(ImportError::GltfInvalid {
        file: file.to_owned(),
        problems,
        count,
    })
}

/// gltf-json 1.4 does not validate animation channel targets, and `Target::node` unwraps.
fn check_channel_targets(file: &str, doc: &gltf::Document) -> Result<(), ImportError> {
    let nodes = doc.nodes().len();
    for (a, anim) in doc.as_json().animations.iter().enumerate() {
        for (c, ch) in anim.channels.iter().enumerate() {
            let node = ch.target.node.value();
            if node >= nodes {
                return Err(ImportError::Node {
                    file: file.to_owned(),
                    node,
                    message: format!(
                        "animation {a} channel {c} targets a node that does not exist"
                    ),
                });
            }
        }
    }
    Ok(())
}

/// What the file's extensions say about its rigs.
#[derive(Clone, Copy)]
struct Source<'a> {
    /// A VRM's humanoid bone map.
    vrm: Option<&'a vrm::Humanoid>,
    /// A VRM's expressions.
    expressions: Option<&'a vrm_expressions::Defined>,
    /// A VRM animation's extension: the file is read as one ([`vrma`]).
    animation: Option<&'a vrma::VrmAnimation>,
}

fn import_document(
    name: &str,
    doc: &gltf::Document,
    blob: Option<Cow<'_, [u8]>>,
    base: Option<External<'_>>,
    source: Source<'_>,
    with_meshes: bool,
) -> Result<Vec<Asset>, ImportError> {
    let buffers = Buffers {
        file: name,
        data: load_buffers(name, doc, blob, base)?,
    };
    let nodes = Nodes::new(name, doc)?;
    let skins: Vec<gltf::Skin<'_>> = doc.skins().collect();
    if skins.is_empty() && source.animation.is_none() {
        return Err(ImportError::Unsupported {
            file: name.to_owned(),
            message: "no skins: posecast imports skinned rigs (and VRM animations)".to_owned(),
        });
    }
    let stem = name.rsplit_once('.').map_or(name, |(s, _)| s);
    let mut animated = vec![false; nodes.local.len()];
    for a in doc.animations() {
        for c in a.channels() {
            if c.target().property() != Property::MorphTargetWeights
                && let Some(x) = animated.get_mut(c.target().node().index())
            {
                *x = true;
            }
        }
    }
    let ctx = Context {
        file: name,
        doc,
        buffers: &buffers,
        nodes: &nodes,
        animated: &animated,
        vrm: source.vrm,
        expressions: source.expressions,
        with_meshes,
    };
    if let Some(animation) = source.animation {
        return Ok(vec![ctx.animation_rig(animation, stem.to_owned())?]);
    }
    let groups = ctx.skin_groups(&skins)?;
    let single = groups.len() == 1;
    groups
        .iter()
        .map(|group| {
            let asset_name = match group.skins.first() {
                _ if single => stem.to_owned(),
                Some(skin) => match skin.name() {
                    Some(n) if !n.is_empty() => format!("{stem}#{n}"),
                    _ => format!("{stem}#skin{}", skin.index()),
                },
                None => stem.to_owned(),
            };
            ctx.skin_group(group, asset_name)
        })
        .collect()
}

fn load_buffers<'a>(
    file: &str,
    doc: &gltf::Document,
    mut blob: Option<Cow<'a, [u8]>>,
    base: Option<External<'_>>,
) -> Result<Vec<Cow<'a, [u8]>>, ImportError> {
    let err = |buffer: usize, message: String| ImportError::Buffer {
        file: file.to_owned(),
        buffer,
        message,
    };
    let mut out = Vec::new();
    for buffer in doc.buffers() {
        let i = buffer.index();
        let data = match buffer.source() {
            gltf::buffer::Source::Bin => blob
                .take()
                .ok_or_else(|| err(i, "refers to a GLB binary chunk the file lacks".into()))?,
            gltf::buffer::Source::Uri(uri) => {
                if let Some(rest) = uri.strip_prefix("data:") {
                    let (_, data) = rest
                        .split_once(";base64,")
                        .ok_or_else(|| err(i, "data URI is not base64".into()))?;
                    Cow::Owned(
                        base64::engine::general_purpose::STANDARD
                            .decode(data)
                            .map_err(|e| err(i, format!("bad base64: {e}")))?,
                    )
                } else if let Some(base) = base {
                    let relative = Path::new(uri);
                    let safe = !uri.contains(':')
                        && relative.components().all(|c| {
                            matches!(
                                c,
                                std::path::Component::Normal(_) | std::path::Component::CurDir
                            )
                        });
                    if !safe {
                        return Err(err(i, format!("URI {uri:?} is not a plain relative path")));
                    }
                    Cow::Owned(base(&uri.replace("%20", " "))?)
                } else {
                    return Err(err(
                        i,
                        format!("external file {uri:?} cannot be read when importing from bytes"),
                    ));
                }
            }
        };
        if data.len() < buffer.length() {
            return Err(err(
                i,
                format!("has {} bytes, declares {}", data.len(), buffer.length()),
            ));
        }
        out.push(data);
    }
    Ok(out)
}

/// Every node's parent and local transform.
struct Nodes {
    parent: Vec<Option<usize>>,
    local: Vec<Transform>,
    names: Vec<String>,
}

impl Nodes {
    fn new(file: &str, doc: &gltf::Document) -> Result<Self, ImportError> {
        let count = doc.nodes().len();
        let err = |node: usize, message: String| ImportError::Node {
            file: file.to_owned(),
            node,
            message,
        };
        let mut parent = vec![None; count];
        let mut local = Vec::with_capacity(count);
        let mut names = Vec::with_capacity(count);
        for node in doc.nodes() {
            let n = node.index();
            for child in node.children() {
                let c = child.index();
                if c == n || parent[c].is_some() {
                    return Err(err(c, "has more than one parent".into()));
                }
                parent[c] = Some(n);
            }
            let t = match node.transform() {
                gltf::scene::Transform::Matrix { matrix } => {
                    Transform::try_from_mat4(&Mat4::from_cols_array_2d(&matrix))
                        .map_err(|e| err(n, format!("matrix: {e}")))?
                }
                gltf::scene::Transform::Decomposed {
                    translation,
                    rotation,
                    scale,
                } => Transform {
                    translation: Vec3::from(translation),
                    rotation: Quat::from_array(rotation),
                    scale: Vec3::from(scale),
                },
            };
            let len = t.rotation.length();
            if !t.is_finite() || len < 1e-6 {
                return Err(err(
                    n,
                    "transform is not finite or has a zero rotation".into(),
                ));
            }
            local.push(Transform {
                rotation: t.rotation / len,
                ..t
            });
            names.push(match node.name() {
                Some(s) if !s.is_empty() => s.to_owned(),
                _ => format!("node{n}"),
            });
        }
        Ok(Self {
            parent,
            local,
            names,
        })
    }

    /// Global matrix of `node`'s parent (the product of its ancestors' locals).
    fn parent_global(&self, node: usize) -> Mat4 {
        let mut m = Mat4::IDENTITY;
        let mut cur = self.parent.get(node).copied().flatten();
        let mut steps = 0;
        while let Some(p) = cur {
            if steps > self.parent.len() {
                break;
            }
            m = self.local[p].to_mat4() * m;
            cur = self.parent[p];
            steps += 1;
        }
        m
    }
}

/// Up to [`ImportError::MAX_LISTED`] names, then how many more: notes stay short on rigs
/// with hundreds of joints.
pub(super) fn listed(names: &[String]) -> String {
    let shown = names.len().min(ImportError::MAX_LISTED);
    let mut s = names[..shown].join(", ");
    if names.len() > shown {
        s.push_str(&format!(" and {} more", names.len() - shown));
    }
    s
}

/// `a · b` for a rigid `a` (unit scale), exact in TRS form.
fn compose_rigid(a: &Transform, b: &Transform) -> Transform {
    Transform {
        translation: a.translation + a.rotation * b.translation,
        rotation: (a.rotation * b.rotation).normalize(),
        scale: b.scale,
    }
}

fn is_rigid(t: &Transform) -> bool {
    (t.scale - Vec3::ONE).abs().max_element() < 1e-6
}

#[derive(Clone, Copy)]
struct Context<'a> {
    file: &'a str,
    doc: &'a gltf::Document,
    buffers: &'a Buffers<'a>,
    nodes: &'a Nodes,
    animated: &'a [bool],
    vrm: Option<&'a vrm::Humanoid>,
    expressions: Option<&'a vrm_expressions::Defined>,
    /// Whether to read the meshes ([`skeletons_and_clips`] does not).
    with_meshes: bool,
}

impl Context<'_> {
    fn node_err(&self, node: usize, message: impl Into<String>) -> ImportError {
        ImportError::Node {
            file: self.file.to_owned(),
            node,
            message: message.into(),
        }
    }

    /// What a skin's asset leaves out: the materials of its meshes (posecast serves geometry),
    /// and meshes on nodes that hang from no joint of any skin (scenery: not part of a rig).
    fn unimported_notes(&self, group: &skins::SkinGroup<'_>) -> Vec<String> {
        let joints = &group.joints;
        let all_joints: Vec<usize> = self
            .doc
            .skins()
            .flat_map(|s| s.joints().map(|n| n.index()).collect::<Vec<_>>())
            .collect();
        let hangs_from = |node: usize, set: &[usize]| {
            let mut cur = Some(node);
            let mut steps = 0;
            while let Some(n) = cur {
                if set.contains(&n) || steps > self.nodes.parent.len() {
                    return set.contains(&n);
                }
                cur = self.nodes.parent[n];
                steps += 1;
            }
            false
        };
        let mut materials = std::collections::BTreeSet::new();
        let mut loose = Vec::new();
        // (targets, primitives, mesh names, targets with tangents) of the morph targets on
        // this skin's meshes.
        let mut morphs = (0usize, 0usize, std::collections::BTreeSet::new(), 0usize);
        for node in self.doc.nodes() {
            let Some(mesh) = node.mesh() else { continue };
            let ours = match node.skin() {
                Some(s) => group.skins.iter().any(|g| g.index() == s.index()),
                None => hangs_from(node.index(), joints),
            };
            if node.skin().is_none() && !hangs_from(node.index(), &all_joints) {
                loose.push(self.nodes.names[node.index()].clone());
            }
            if ours {
                for prim in mesh.primitives() {
                    let targets = prim.morph_targets().len();
                    if targets > 0 {
                        morphs.0 += targets;
                        morphs.1 += 1;
                        morphs.3 += prim
                            .morph_targets()
                            .filter(|t| t.tangents().is_some())
                            .count();
                        morphs.2.insert(
                            mesh.name()
                                .map_or(format!("mesh{}", mesh.index()), str::to_owned),
                        );
                    }
                    let m = prim.material();
                    if let Some(i) = m.index() {
                        materials.insert(m.name().map_or(format!("material{i}"), str::to_owned));
                    }
                }
            }
        }
        let mut notes = Vec::new();
        if !materials.is_empty() {
            let list: Vec<String> = materials.into_iter().collect();
            notes.push(format!(
                "{} materials not imported (posecast serves geometry only): {}",
                list.len(),
                listed(&list)
            ));
        }
        if morphs.0 > 0 {
            let list: Vec<String> = morphs.2.into_iter().collect();
            notes.push(format!(
                "{} morph targets on {} primitives imported (positions and normals): {}",
                morphs.0,
                morphs.1,
                listed(&list)
            ));
        }
        if morphs.3 > 0 {
            notes.push(format!(
                "{} morph targets' TANGENT displacements not imported (posecast serves no \
                 tangents)",
                morphs.3
            ));
        }
        if !loose.is_empty() {
            notes.push(format!(
                "{} meshes on nodes that hang from no joint not imported: {}",
                loose.len(),
                listed(&loose)
            ));
        }
        let skins = self.doc.skins().len();
        if skins > group.skins.len() {
            notes.push(format!(
                "the file has {skins} skins: this asset holds {} of them, the others (other \
                 skeletons) are assets of their own",
                group.skins.len()
            ));
        }
        notes
    }

    /// The asset of a set of joint nodes (non-empty): the skeleton of the joints and their
    /// ancestors (folded where static and rigid, see the module docs), the clips that move
    /// them, and, with a group of skins ([`skins`]), their inverse binds and meshes. Without
    /// one (a VRM animation) every joint is bound at rest.
    fn rig(
        &self,
        joints: &[usize],
        group: Option<&skins::SkinGroup<'_>>,
        name: String,
    ) -> Result<Asset, ImportError> {
        let nodes = self.nodes;
        let node_count = nodes.local.len();
        let mut skin_index_of: HashMap<usize, usize> = HashMap::with_capacity(joints.len());
        for (k, &j) in joints.iter().enumerate() {
            if j >= node_count {
                return Err(self.node_err(j, "is not a node of the file"));
            }
            if skin_index_of.insert(j, k).is_some() {
                return Err(self.node_err(j, "listed twice"));
            }
        }
        // The joints and all their ancestors.
        let mut in_set = vec![false; node_count];
        for &j in joints {
            let mut cur = Some(j);
            while let Some(x) = cur {
                if in_set[x] {
                    break;
                }
                in_set[x] = true;
                cur = nodes.parent[x];
            }
        }
        let members: Vec<usize> = (0..node_count).filter(|&n| in_set[n]).collect();
        let mut member_of = vec![usize::MAX; node_count];
        for (i, &n) in members.iter().enumerate() {
            member_of[n] = i;
        }
        let member_parent: Vec<Option<usize>> = members
            .iter()
            .map(|&n| nodes.parent[n].map(|p| member_of[p]))
            .collect();
        let order = topological_order(&member_parent)
            .map_err(|e| self.node_err(members.first().copied().unwrap_or(0), e.to_string()))?;

        // Fold static rigid non-joint nodes into their children.
        let m = members.len();
        let mut kept = vec![false; m];
        let mut prefix = vec![Transform::IDENTITY; m];
        let mut kept_parent: Vec<Option<usize>> = vec![None; m]; // nearest kept ancestor
        let mut skel_index = vec![usize::MAX; m];
        let mut skel_nodes = Vec::new();
        let mut skel_parents = Vec::new();
        let mut rest = Vec::new();
        let mut maps = Vec::new();
        let mut helpers = Vec::new();
        for &i in &order {
            let n = members[i];
            let local = &nodes.local[n];
            let (pre, up) = match member_parent[i] {
                None => (Transform::IDENTITY, None),
                Some(p) if kept[p] => (Transform::IDENTITY, Some(p)),
                Some(p) => (
                    compose_rigid(&prefix[p], &nodes.local[members[p]]),
                    kept_parent[p],
                ),
            };
            prefix[i] = pre;
            kept_parent[i] = up;
            let is_joint = skin_index_of.contains_key(&n);
            if !is_joint && !self.animated[n] && is_rigid(local) {
                continue;
            }
            kept[i] = true;
            skel_index[i] = skel_nodes.len();
            if !is_joint {
                helpers.push(skel_nodes.len());
            }
            skel_nodes.push(n);
            skel_parents.push(up.map(|u| skel_index[u]));
            rest.push(compose_rigid(&pre, local));
            maps.push(ChannelMap {
                rot_pre: pre.rotation,
                trans_rot: pre.rotation,
                trans_offset: pre.translation,
                ..ChannelMap::IDENTITY
            });
        }
        let count = skel_nodes.len();
        let mut skel_of_node: HashMap<usize, usize> = HashMap::with_capacity(count);
        for (s, &n) in skel_nodes.iter().enumerate() {
            skel_of_node.insert(n, s);
        }
        // Inverse binds: the skins' (merged, see [`skins`]), or bound at rest for helpers.
        let mut world = vec![Mat4::IDENTITY; count];
        for s in 0..count {
            let l = rest[s].to_mat4();
            world[s] = match skel_parents[s] {
                Some(p) => world[p] * l,
                None => l,
            };
        }
        let mut inverse_bind: Vec<Mat4> = world.iter().map(Mat4::inverse).collect();
        let mut notes = Vec::new();
        if let Some(group) = group {
            for (node, b) in &group.binds {
                if let Some(&s) = skel_of_node.get(node) {
                    inverse_bind[s] = *b;
                }
            }
            notes.extend(group.notes.iter().cloned());
        }
        let names = unique_names(skel_nodes.iter().map(|&n| nodes.names[n].clone()));
        notes.extend(renamed_note(
            skel_nodes.iter().map(|&n| nodes.names[n].as_str()),
            &names,
        ));
        let skeleton =
            Skeleton::new(names, skel_parents, rest, inverse_bind).map_err(|source| {
                ImportError::Skeleton {
                    file: self.file.to_owned(),
                    source,
                }
            })?;

        let mut meshes = Vec::new();
        let mut rigid = Vec::new();
        if let Some(group) = group.filter(|_| self.with_meshes) {
            for (skin, bake) in group.skins.iter().zip(&group.bakes) {
                // skin joint k -> skeleton joint
                let skin_to_skel: Vec<usize> = skin
                    .joints()
                    .map(|j| skel_of_node.get(&j.index()).copied().unwrap_or(0))
                    .collect();
                meshes.extend(self.meshes(skin, &skin_to_skel, *bake, count, &mut notes)?);
            }
            rigid = self.rigid_meshes(
                &group.joints,
                &skel_of_node,
                skeleton.inverse_bind(),
                &mut notes,
            )?;
        }
        if !rigid.is_empty() {
            notes.push(format!(
                "{} mesh primitive(s) parented to joints imported rigidly skinned (weight 1)",
                rigid.len()
            ));
        }
        meshes.extend(rigid);
        if !meshes.is_empty() {
            let mut used = vec![false; count];
            for m in &meshes {
                for (j, w) in m.mesh.joints().iter().zip(m.mesh.weights()) {
                    if *w > 0.0
                        && let Some(u) = used.get_mut(usize::from(*j))
                    {
                        *u = true;
                    }
                }
            }
            let idle: Vec<String> = (0..count)
                .filter(|&j| !used[j])
                .map(|j| skeleton.names()[j].clone())
                .collect();
            if !idle.is_empty() {
                notes.push(format!(
                    "{} of {count} joints move no vertex (kept: they place their children, and \
                     clips may drive them): {}",
                    idle.len(),
                    listed(&idle)
                ));
            }
        }
        let clips = self.clips(&skel_of_node, &maps, count, &mut notes)?;
        if let Some(group) = group {
            notes.extend(self.unimported_notes(group));
        }

        let mut source = SourceInfo::new(SourceFormat::Gltf);
        if let Some(h) = self.vrm {
            let names = skeleton.names();
            let map: std::collections::BTreeMap<String, String> = h
                .bones
                .iter()
                .filter_map(|(node, _, hanim)| {
                    skel_of_node
                        .get(node)
                        .map(|&s| (names[s].clone(), hanim.clone()))
                })
                .collect();
            if !map.is_empty() {
                notes.push(format!(
                    "VRM {} humanoid: {} bones named by the file",
                    match h.version {
                        vrm::Version::V0 => "0.x",
                        vrm::Version::V1 => "1.0",
                    },
                    map.len()
                ));
                source.bone_map = Some(map);
            }
        }
        let expressions = self.expressions_of(&meshes, &mut notes);
        source.helper_joints = helpers;
        source.notes = notes;
        // The frame the joints hang in: a Z-up authoring frame maps +Z to +Y.
        let root = order
            .iter()
            .map(|&i| members[i])
            .find(|n| skin_index_of.contains_key(n))
            .or_else(|| joints.first().copied())
            .unwrap_or(0);
        let above = nodes.parent_global(root);
        if above
            .transform_vector3(Vec3::Z)
            .normalize_or_zero()
            .dot(Vec3::Y)
            > 0.99
        {
            source.up_axis = UpAxis::Z;
        }
        Ok(Asset {
            name,
            skeleton,
            meshes,
            clips,
            source,
            boxes: None,
            expressions,
        })
    }

    /// The file's VRM expressions over this rig's morph channels: binds to channels the rig's
    /// meshes lack (another rig's meshes, or meshes not read) dropped, expressions left with
    /// no bind dropped, each with a note.
    fn expressions_of(
        &self,
        meshes: &[crate::asset::AssetMesh],
        notes: &mut Vec<String>,
    ) -> Vec<posecast_proto::expressions::Expression> {
        let Some(defined) = self.expressions else {
            return Vec::new();
        };
        notes.extend(defined.notes.iter().cloned());
        let channels: std::collections::HashSet<String> =
            posecast_proto::morph::channels(meshes.iter().map(|m| &m.mesh))
                .into_iter()
                .collect();
        let mut elsewhere = 0;
        let mut empty = Vec::new();
        let kept: Vec<_> = defined
            .expressions
            .iter()
            .cloned()
            .filter_map(|mut e| {
                let before = e.binds.len();
                e.binds.retain(|b| channels.contains(&b.channel));
                elsewhere += before - e.binds.len();
                if e.binds.is_empty() {
                    empty.push(e.name);
                    None
                } else {
                    Some(e)
                }
            })
            .collect();
        if !kept.is_empty() {
            let names: Vec<String> = kept.iter().map(|e| e.name.clone()).collect();
            notes.push(format!(
                "VRM {} expressions: {} kept ({})",
                defined.version,
                kept.len(),
                listed(&names)
            ));
        }
        if elsewhere > 0 {
            notes.push(format!(
                "VRM {} expressions: {elsewhere} morph bind(s) to targets outside this rig's \
                 meshes dropped",
                defined.version
            ));
        }
        if !empty.is_empty() {
            notes.push(format!(
                "VRM {} expressions without a morph bind dropped: {}",
                defined.version,
                listed(&empty)
            ));
        }
        kept
    }
}
