//! The one binary glTF 2.0 writer (typed `gltf::json`): a skeleton as nodes, optionally a
//! skinned mesh, one skin, and animations ([`Model`], [`write()`]) — or several such figures and
//! animations moving any of them ([`Scene`], [`write_scene`]). It writes the built-in avatar
//! (`make-avatar`), a rig's mesh for render clients (`mesh.glb`), clip exports and takes of
//! several avatars.
//!
//! Layout, the same for every caller; figure by figure, in order (a [`Model`] is one figure):
//! - accessors: per primitive POSITION (with bounds), NORMAL, JOINTS_0 (u16), WEIGHTS_0,
//!   indices (u16 when every index fits below the primitive-restart value 65535, else u32);
//!   then the figure's inverse bind matrices;
//! - nodes: its joints in skeleton order from the figure's node offset (the node count before
//!   it; a skin joint index is its node index minus the offset), named, at their rest TRS
//!   (scale only when not 1); then the skinned mesh node, if any; then the figure's root node
//!   parenting the skeleton's roots when the figure is named, or else, for a skeleton with
//!   several roots, a plain `skeleton` node parenting them (a skin's joints must share one
//!   root);
//! - skin `f` for figure `f`; the scene's roots are each figure's top node and mesh node
//!   (a skinned mesh node stays a scene root: parent transforms do not move skinned meshes);
//! - then per animation, per part, per channel, its key times (shared by channels with equal
//!   times, with bounds) and its output, then the part's morph weights.
//!
//! One buffer view per accessor, 4-byte aligned; vertex and index views carry their buffer
//! target, inverse binds and animation data none.

use super::ExportError;
use crate::clip::Interpolation;
use glam::{Quat, Vec3};
use gltf::binary::{Glb, Header};
use gltf::json::{self, Index, validation::Checked::Valid, validation::USize64};
use posecast_proto::{Skeleton, SkinnedMesh};
use serde_json::json;
use std::borrow::Cow;
use std::collections::BTreeMap;

/// What one `.glb` holds: a skeleton, optionally a skinned mesh, and animations of its joints.
#[derive(Clone, Copy, Debug)]
pub struct Model<'a> {
    /// `asset.generator`.
    pub generator: &'a str,
    /// The skin's and the scene's name (unnamed when `None`).
    pub name: Option<&'a str>,
    /// Joint names, parents, rest transforms (local, parent space) and inverse binds.
    pub skeleton: &'a Skeleton,
    /// The skinned mesh, in bind space.
    pub mesh: Option<&'a Mesh>,
    /// Animations of the skeleton's joints.
    pub animations: &'a [Animation],
}

/// What a `.glb` of several skeletons holds ([`write_scene`]): figures, each with its own
/// joint nodes, optional skinned mesh and skin, and animations that may move any of them.
/// A [`Model`] is a scene of one unnamed figure.
#[derive(Clone, Copy, Debug)]
pub struct Scene<'a> {
    /// `asset.generator`.
    pub generator: &'a str,
    /// The scene's name (unnamed when `None`).
    pub name: Option<&'a str>,
    /// The figures, written in this order; figure `f` has skin `f`.
    pub figures: &'a [Figure<'a>],
    /// The animations, each of any figures.
    pub animations: &'a [SceneAnimation<'a>],
}

/// One skeleton of a [`Scene`] with its skin and optionally its skinned mesh.
#[derive(Clone, Copy, Debug)]
pub struct Figure<'a> {
    /// The name of a plain node parenting the skeleton's roots (the figure's root node, a root
    /// of the scene). `None`: the skeleton's root is itself a scene root, or, with several
    /// roots, a plain node named `skeleton` parents them.
    pub name: Option<&'a str>,
    /// The skin's name (unnamed when `None`).
    pub skin: Option<&'a str>,
    /// Joint names, parents, rest transforms (local, parent space) and inverse binds.
    pub skeleton: &'a Skeleton,
    /// The skinned mesh, in bind space.
    pub mesh: Option<&'a Mesh>,
}

/// One glTF animation of a [`Scene`]: the channels of its parts, part by part.
#[derive(Clone, Debug)]
pub struct SceneAnimation<'a> {
    /// The animation's name.
    pub name: &'a str,
    /// What it does to each figure it moves.
    pub parts: Vec<Part<'a>>,
}

/// The motion of one figure within a [`SceneAnimation`].
#[derive(Clone, Copy, Debug)]
pub struct Part<'a> {
    /// The figure's index in [`Scene::figures`].
    pub figure: usize,
    /// Its channels ([`Channel::joint`] a joint of that figure's skeleton) and morph weights
    /// (of that figure's mesh node); the animation's own name is not used.
    pub animation: &'a Animation,
}

/// A skinned mesh: one glTF mesh, one primitive per part (readers such as the dashboard take
/// every primitive of mesh 0).
#[derive(Clone, Debug, PartialEq)]
pub struct Mesh {
    /// The mesh's and its node's name.
    pub name: String,
    /// Its parts, each written as one glTF primitive.
    pub primitives: Vec<Primitive>,
    /// Morph target names, written as `mesh.extras.targetNames`; every primitive has one
    /// target per name, in this order (glTF: all primitives of a mesh have the same targets),
    /// and the mesh's default weights are zeros.
    pub target_names: Vec<String>,
}

/// One morph target of a primitive: displacements per vertex.
#[derive(Clone, Debug, PartialEq)]
pub struct Target {
    /// Position displacements, one per vertex.
    pub positions: Vec<Vec3>,
    /// Normal displacements, one per vertex, or empty.
    pub normals: Vec<Vec3>,
}

/// One triangle list with four joint influences per vertex.
#[derive(Clone, Debug, PartialEq)]
pub struct Primitive {
    /// Bind-space positions.
    pub positions: Vec<Vec3>,
    /// Unit normals, one per position.
    pub normals: Vec<Vec3>,
    /// Skin joint (= skeleton joint) indices; unused slots name joint 0 with weight 0.
    pub joints: Vec<[u16; 4]>,
    /// Weights summing to one.
    pub weights: Vec<[f32; 4]>,
    /// Counter-clockwise triangles.
    pub indices: Vec<u32>,
    /// The primitive's material; `None` leaves it to the reader's default.
    pub material: Option<Material>,
    /// Morph targets, one per [`Mesh::target_names`] entry.
    pub targets: Vec<Target>,
}

impl Primitive {
    /// A [`SkinnedMesh`] as a primitive: more than four influences keep the four heaviest,
    /// renormalised; fewer are padded with zero weights on joint 0. Its morph targets follow
    /// `channels`: the mesh's target of each name, or zero displacements where it has none.
    #[must_use]
    pub fn from_skinned(mesh: &SkinnedMesh, channels: &[String]) -> Self {
        let targets = channels
            .iter()
            .map(
                |name| match mesh.targets().iter().find(|t| t.name == *name) {
                    Some(t) => Target {
                        positions: t.positions.clone(),
                        normals: t.normals.clone(),
                    },
                    None => Target {
                        positions: vec![Vec3::ZERO; mesh.vertex_count()],
                        normals: Vec::new(),
                    },
                },
            )
            .collect();
        let mesh = if mesh.influences() == 4 {
            Cow::Borrowed(mesh)
        } else {
            Cow::Owned(mesh.with_influences(4))
        };
        let mut joints = Vec::with_capacity(mesh.vertex_count());
        let mut weights = Vec::with_capacity(mesh.vertex_count());
        for (j, w) in mesh
            .joints()
            .chunks_exact(4)
            .zip(mesh.weights().chunks_exact(4))
        {
            joints.push([j[0], j[1], j[2], j[3]]);
            weights.push([w[0], w[1], w[2], w[3]]);
        }
        Self {
            positions: mesh.positions().to_vec(),
            normals: mesh.normals().to_vec(),
            joints,
            weights,
            indices: mesh.indices().to_vec(),
            material: None,
            targets,
        }
    }
}

/// A metallic-roughness material with a constant colour.
#[derive(Clone, Debug, PartialEq)]
pub struct Material {
    /// The material's name in the file.
    pub name: String,
    /// Linear RGBA.
    pub base_color: [f32; 4],
    /// glTF `metallicFactor`, 0 (dielectric) to 1 (metal).
    pub metallic: f32,
    /// glTF `roughnessFactor`, 0 (mirror) to 1 (fully rough).
    pub roughness: f32,
}

/// One glTF animation.
#[derive(Clone, Debug, PartialEq)]
pub struct Animation {
    /// The animation's name (the clip's).
    pub name: String,
    /// Its channels, each one property of one joint.
    pub channels: Vec<Channel>,
    /// Morph target weights of the mesh node (a `weights` channel), if the clip animates any.
    pub weights: Option<Weights>,
}

/// A linear `weights` channel: at each key, one weight per morph target of the mesh (the
/// [`Mesh::target_names`] order).
#[derive(Clone, Debug, PartialEq)]
pub struct Weights {
    /// Key times in seconds, strictly increasing, the first ≥ 0.
    pub times: Vec<f32>,
    /// `times.len() × targets` weights, key by key.
    pub values: Vec<f32>,
}

/// One animated property of one joint.
#[derive(Clone, Debug, PartialEq)]
pub struct Channel {
    /// The skeleton joint it moves: node `joint` of a [`Model`], the figure's node offset plus
    /// `joint` in a [`Scene`].
    pub joint: usize,
    /// glTF `STEP`, `LINEAR` (slerp for rotations) or `CUBICSPLINE`.
    pub interpolation: Interpolation,
    /// Key times in seconds, strictly increasing, the first ≥ 0.
    pub times: Vec<f32>,
    /// One value per key, or for [`Interpolation::CubicSpline`] three (in-tangent, value,
    /// out-tangent; tangents per second), as glTF stores them.
    pub output: Output,
}

/// A channel's values: local translation (parent space, metres), rotation (unit
/// quaternions) or scale.
#[derive(Clone, Debug, PartialEq)]
pub enum Output {
    /// Local translations, parent space, metres.
    Translation(Vec<Vec3>),
    /// Local rotations, unit quaternions.
    Rotation(Vec<Quat>),
    /// Local per-axis scales.
    Scale(Vec<Vec3>),
}

impl Output {
    fn len(&self) -> usize {
        match self {
            Self::Translation(v) | Self::Scale(v) => v.len(),
            Self::Rotation(q) => q.len(),
        }
    }

    fn is_finite(&self) -> bool {
        match self {
            Self::Translation(v) | Self::Scale(v) => v.iter().all(|v| v.is_finite()),
            Self::Rotation(q) => q.iter().all(|q| q.is_finite()),
        }
    }
}

/// Writes `model` as `.glb` bytes: [`write_scene`] of its one unnamed figure, each animation
/// moving that figure.
///
/// # Errors
/// A channel names a joint the skeleton does not have, has no keys, times that are negative,
/// not finite or not increasing, or a value count that does not fit its times
/// ([`ExportError::Channel`]); a primitive's attribute lengths differ or an index is out of
/// range ([`ExportError::Primitive`]); the file would pass GLB's 4 GiB
/// ([`ExportError::TooLarge`]).
pub fn write(model: &Model<'_>) -> Result<Vec<u8>, ExportError> {
    let figure = Figure {
        name: None,
        skin: model.name,
        skeleton: model.skeleton,
        mesh: model.mesh,
    };
    let animations: Vec<SceneAnimation<'_>> = model
        .animations
        .iter()
        .map(|animation| SceneAnimation {
            name: &animation.name,
            parts: vec![Part {
                figure: 0,
                animation,
            }],
        })
        .collect();
    write_scene(&Scene {
        generator: model.generator,
        name: model.name,
        figures: std::slice::from_ref(&figure),
        animations: &animations,
    })
}

/// Writes `scene` as `.glb` bytes: its figures one after the other (see the module's layout),
/// then its animations.
///
/// # Errors
/// As [`write()`]; also a part naming a figure the scene does not have ([`ExportError::Channel`]).
pub fn write_scene(scene: &Scene<'_>) -> Result<Vec<u8>, ExportError> {
    let mut b = Builder {
        root: json::Root {
            asset: json::Asset {
                copyright: None,
                extensions: None,
                extras: Default::default(),
                generator: Some(scene.generator.into()),
                min_version: None,
                version: "2.0".into(),
            },
            ..Default::default()
        },
        bin: Vec::new(),
    };
    let mut placed = Vec::with_capacity(scene.figures.len());
    let mut scene_nodes = Vec::new();
    for (f, figure) in scene.figures.iter().enumerate() {
        let p = write_figure(&mut b, figure, f)?;
        scene_nodes.push(p.top);
        scene_nodes.extend(p.mesh_node);
        placed.push(p);
    }
    let root_scene = b.root.push(json::Scene {
        extensions: None,
        extras: Default::default(),
        name: scene.name.map(Into::into),
        nodes: scene_nodes,
    });
    b.root.scene = Some(root_scene);

    for animation in scene.animations {
        write_animation(&mut b, animation, &placed)?;
    }
    b.finish()
}

/// Where a written figure's nodes are.
struct Placed {
    /// Node index of its joint 0; joint `j` is node `offset + j`.
    offset: usize,
    /// Its number of joints.
    joints: usize,
    /// The node parenting its joints (its root joint when unnamed with one root).
    top: Index<json::Node>,
    /// Its skinned mesh node, if it has a mesh.
    mesh_node: Option<Index<json::Node>>,
}

/// Writes figure `f` (the `f`-th skin): its mesh's accessors, its inverse binds, its joint
/// nodes, mesh node, root node and skin.
fn write_figure(b: &mut Builder, figure: &Figure<'_>, f: usize) -> Result<Placed, ExportError> {
    let skeleton = figure.skeleton;
    let n = skeleton.len();
    let mesh = match figure.mesh {
        Some(mesh) => Some(write_mesh(b, mesh, n)?),
        None => None,
    };
    let inverse_binds: Vec<[f32; 16]> = skeleton
        .inverse_bind()
        .iter()
        .map(|m| m.to_cols_array())
        .collect();
    let inverse_binds = b.f32s(&inverse_binds, None, false);

    let offset = b.root.nodes.len();
    let node = |j: usize| node_index(offset + j);
    for (j, (name, rest)) in skeleton.names().iter().zip(skeleton.rest()).enumerate() {
        let children: Vec<Index<json::Node>> = skeleton.children(j).map(node).collect();
        b.root.push(json::Node {
            name: Some(name.clone()),
            translation: Some(rest.translation.to_array()),
            rotation: Some(json::scene::UnitQuaternion(unit(rest.rotation).to_array())),
            scale: (rest.scale != Vec3::ONE).then(|| rest.scale.to_array()),
            children: (!children.is_empty()).then_some(children),
            ..Default::default()
        });
    }
    let roots: Vec<Index<json::Node>> = skeleton.roots().map(node).collect();
    let mesh_node = mesh.map(|(mesh, name)| {
        b.root.push(json::Node {
            name: Some(name),
            mesh: Some(mesh),
            skin: Some(Index::new(f as u32)),
            ..Default::default()
        })
    });
    let top = match (figure.name, roots.as_slice()) {
        (None, [root]) => *root,
        (name, _) => b.root.push(json::Node {
            name: Some(name.unwrap_or("skeleton").into()),
            children: Some(roots),
            ..Default::default()
        }),
    };
    b.root.push(json::Skin {
        extensions: None,
        extras: Default::default(),
        inverse_bind_matrices: Some(inverse_binds),
        joints: (0..n).map(node).collect(),
        name: figure.skin.map(Into::into),
        skeleton: Some(top),
    });
    Ok(Placed {
        offset,
        joints: n,
        top,
        mesh_node,
    })
}

/// The mesh and its node's name.
fn write_mesh(
    b: &mut Builder,
    mesh: &Mesh,
    joints: usize,
) -> Result<(Index<json::Mesh>, String), ExportError> {
    let array = Some(json::buffer::Target::ArrayBuffer);
    let mut primitives = Vec::with_capacity(mesh.primitives.len());
    for (p, prim) in mesh.primitives.iter().enumerate() {
        check_primitive(mesh, p, prim, joints)?;
        let positions: Vec<[f32; 3]> = prim.positions.iter().map(|v| v.to_array()).collect();
        let normals: Vec<[f32; 3]> = prim.normals.iter().map(|v| v.to_array()).collect();
        let position = b.f32s(&positions, array, true);
        let normal = b.f32s(&normals, array, false);
        let joint_bytes: Vec<u8> = prim
            .joints
            .iter()
            .flatten()
            .flat_map(|j| j.to_le_bytes())
            .collect();
        let joint_ids = b.accessor(
            &joint_bytes,
            prim.joints.len(),
            json::accessor::ComponentType::U16,
            json::accessor::Type::Vec4,
            array,
            None,
        );
        let weights = b.f32s(&prim.weights, array, false);
        // glTF forbids the primitive-restart value (all ones) in indices.
        let (index_bytes, component): (Vec<u8>, _) =
            if prim.indices.iter().all(|&i| i < u32::from(u16::MAX)) {
                let bytes = prim
                    .indices
                    .iter()
                    .flat_map(|&i| (i as u16).to_le_bytes())
                    .collect();
                (bytes, json::accessor::ComponentType::U16)
            } else {
                let bytes = prim.indices.iter().flat_map(|i| i.to_le_bytes()).collect();
                (bytes, json::accessor::ComponentType::U32)
            };
        let indices = b.accessor(
            &index_bytes,
            prim.indices.len(),
            component,
            json::accessor::Type::Scalar,
            Some(json::buffer::Target::ElementArrayBuffer),
            None,
        );
        let material = prim.material.as_ref().map(|m| {
            b.root.push(json::Material {
                name: Some(m.name.clone()),
                pbr_metallic_roughness: json::material::PbrMetallicRoughness {
                    base_color_factor: json::material::PbrBaseColorFactor(m.base_color),
                    metallic_factor: json::material::StrengthFactor(m.metallic),
                    roughness_factor: json::material::StrengthFactor(m.roughness),
                    ..Default::default()
                },
                ..Default::default()
            })
        });
        let attributes = BTreeMap::from([
            (Valid(json::mesh::Semantic::Positions), position),
            (Valid(json::mesh::Semantic::Normals), normal),
            (Valid(json::mesh::Semantic::Joints(0)), joint_ids),
            (Valid(json::mesh::Semantic::Weights(0)), weights),
        ]);
        let targets: Vec<json::mesh::MorphTarget> = prim
            .targets
            .iter()
            .map(|t| {
                let positions: Vec<[f32; 3]> = t.positions.iter().map(|v| v.to_array()).collect();
                let normals: Vec<[f32; 3]> = t.normals.iter().map(|v| v.to_array()).collect();
                json::mesh::MorphTarget {
                    positions: Some(b.f32s(&positions, array, true)),
                    normals: (!normals.is_empty()).then(|| b.f32s(&normals, array, false)),
                    tangents: None,
                }
            })
            .collect();
        primitives.push(json::mesh::Primitive {
            attributes,
            extensions: None,
            extras: Default::default(),
            indices: Some(indices),
            material,
            mode: Valid(json::mesh::Mode::Triangles),
            targets: (!targets.is_empty()).then_some(targets),
        });
    }
    let names = &mesh.target_names;
    let extras = if names.is_empty() {
        Default::default()
    } else {
        Some(serde_json::value::to_raw_value(
            &json!({ "targetNames": names }),
        )?)
    };
    let index = b.root.push(json::Mesh {
        extensions: None,
        extras,
        name: Some(mesh.name.clone()),
        primitives,
        weights: (!names.is_empty()).then(|| vec![0.0; names.len()]),
    });
    Ok((index, mesh.name.clone()))
}

fn check_primitive(
    mesh: &Mesh,
    p: usize,
    prim: &Primitive,
    joints: usize,
) -> Result<(), ExportError> {
    let fail = |message: String| ExportError::Primitive {
        mesh: mesh.name.clone(),
        primitive: p,
        message,
    };
    let n = prim.positions.len();
    for (what, len) in [
        ("normals", prim.normals.len()),
        ("joint indices", prim.joints.len()),
        ("weights", prim.weights.len()),
    ] {
        if len != n {
            return Err(fail(format!("{len} {what} for {n} positions")));
        }
    }
    if !prim.indices.len().is_multiple_of(3) {
        return Err(fail(format!(
            "{} indices do not make triangles",
            prim.indices.len()
        )));
    }
    if prim.targets.len() != mesh.target_names.len() {
        return Err(fail(format!(
            "{} morph targets, the mesh names {}",
            prim.targets.len(),
            mesh.target_names.len()
        )));
    }
    for (k, t) in prim.targets.iter().enumerate() {
        let normals_ok = t.normals.is_empty() || t.normals.len() == n;
        if t.positions.len() != n || !normals_ok {
            return Err(fail(format!("morph target {k} does not have {n} vertices")));
        }
        if !t.positions.iter().chain(&t.normals).all(|v| v.is_finite()) {
            return Err(fail(format!("morph target {k} is not finite")));
        }
    }
    if let Some(i) = prim.indices.iter().find(|&&i| i as usize >= n) {
        return Err(fail(format!("index {i} with {n} vertices")));
    }
    if let Some(j) = prim
        .joints
        .iter()
        .flatten()
        .find(|&&j| usize::from(j) >= joints)
    {
        return Err(fail(format!("joint {j} with {joints} joints")));
    }
    Ok(())
}

fn write_animation(
    b: &mut Builder,
    a: &SceneAnimation<'_>,
    figures: &[Placed],
) -> Result<(), ExportError> {
    let capacity = a.parts.iter().map(|p| p.animation.channels.len() + 1).sum();
    let mut channels = Vec::with_capacity(capacity);
    let mut samplers = Vec::with_capacity(capacity);
    // Key times already written in this animation, and their accessor.
    let mut inputs: Vec<(&[f32], Index<json::Accessor>)> = Vec::new();
    for part in &a.parts {
        let Some(figure) = figures.get(part.figure) else {
            return Err(ExportError::Channel {
                animation: a.name.into(),
                channel: channels.len(),
                message: format!("moves figure {} of {}", part.figure, figures.len()),
            });
        };
        for ch in &part.animation.channels {
            check_channel(a.name, channels.len(), ch, figure.joints)?;
            let input = match inputs.iter().find(|(t, _)| *t == ch.times.as_slice()) {
                Some(&(_, input)) => input,
                None => {
                    let times: Vec<[f32; 1]> = ch.times.iter().map(|&t| [t]).collect();
                    let input = b.f32s(&times, None, true);
                    inputs.push((&ch.times, input));
                    input
                }
            };
            let (output, property) = match &ch.output {
                Output::Translation(v) => (b.vec3s(v), json::animation::Property::Translation),
                Output::Scale(v) => (b.vec3s(v), json::animation::Property::Scale),
                Output::Rotation(q) => {
                    let values: Vec<[f32; 4]> = q.iter().map(|q| q.to_array()).collect();
                    (
                        b.f32s(&values, None, false),
                        json::animation::Property::Rotation,
                    )
                }
            };
            let interpolation = match ch.interpolation {
                Interpolation::Step => json::animation::Interpolation::Step,
                Interpolation::Linear => json::animation::Interpolation::Linear,
                Interpolation::CubicSpline => json::animation::Interpolation::CubicSpline,
            };
            push_channel(
                &mut channels,
                &mut samplers,
                (input, interpolation, output),
                node_index(figure.offset + ch.joint),
                property,
            );
        }
        if let (Some(w), Some(node)) = (&part.animation.weights, figure.mesh_node) {
            let increasing = w.times.windows(2).all(|p| p[0] < p[1]);
            if w.times.is_empty()
                || !increasing
                || !w.times.iter().all(|t| t.is_finite() && *t >= 0.0)
                || !w.values.len().is_multiple_of(w.times.len())
                || !w.values.iter().all(|v| v.is_finite())
            {
                return Err(ExportError::Channel {
                    animation: a.name.into(),
                    channel: channels.len(),
                    message: format!(
                        "weights: {} times, {} values",
                        w.times.len(),
                        w.values.len()
                    ),
                });
            }
            let times: Vec<[f32; 1]> = w.times.iter().map(|&t| [t]).collect();
            let input = b.f32s(&times, None, true);
            let values: Vec<[f32; 1]> = w.values.iter().map(|&v| [v]).collect();
            let output = b.f32s(&values, None, false);
            push_channel(
                &mut channels,
                &mut samplers,
                (input, json::animation::Interpolation::Linear, output),
                node,
                json::animation::Property::MorphTargetWeights,
            );
        }
    }
    b.root.push(json::Animation {
        extensions: None,
        extras: Default::default(),
        channels,
        name: Some(a.name.into()),
        samplers,
    });
    Ok(())
}

/// Appends a sampler (`input`, interpolation, `output`) and the channel that applies it to
/// `path` of `node`.
fn push_channel(
    channels: &mut Vec<json::animation::Channel>,
    samplers: &mut Vec<json::animation::Sampler>,
    (input, interpolation, output): (
        Index<json::Accessor>,
        json::animation::Interpolation,
        Index<json::Accessor>,
    ),
    node: Index<json::Node>,
    path: json::animation::Property,
) {
    channels.push(json::animation::Channel {
        sampler: Index::new(samplers.len() as u32),
        target: json::animation::Target {
            extensions: None,
            extras: Default::default(),
            node,
            path: Valid(path),
        },
        extensions: None,
        extras: Default::default(),
    });
    samplers.push(json::animation::Sampler {
        extensions: None,
        extras: Default::default(),
        input,
        interpolation: Valid(interpolation),
        output,
    });
}

fn check_channel(
    animation: &str,
    c: usize,
    ch: &Channel,
    joints: usize,
) -> Result<(), ExportError> {
    let fail = |message: String| ExportError::Channel {
        animation: animation.into(),
        channel: c,
        message,
    };
    if ch.joint >= joints {
        return Err(fail(format!("targets joint {} of {joints}", ch.joint)));
    }
    if ch.times.is_empty() {
        return Err(fail("has no keys".into()));
    }
    if !(ch.times.iter().all(|t| t.is_finite()) && ch.times[0] >= 0.0) {
        return Err(fail("has a negative or non-finite key time".into()));
    }
    if ch.times.windows(2).any(|w| w[1] <= w[0]) {
        return Err(fail("key times do not increase".into()));
    }
    let per_key = if ch.interpolation == Interpolation::CubicSpline {
        3
    } else {
        1
    };
    if ch.output.len() != ch.times.len() * per_key {
        return Err(fail(format!(
            "{} values for {} keys ({per_key} per key)",
            ch.output.len(),
            ch.times.len()
        )));
    }
    if !ch.output.is_finite() {
        return Err(fail("has a non-finite value".into()));
    }
    Ok(())
}

fn node_index(j: usize) -> Index<json::Node> {
    Index::new(j as u32)
}

/// A rotation that is unit to f32 rounding is written as stored (bit for bit what the caller
/// computed); anything further off is normalised, as glTF requires unit rotations.
fn unit(q: Quat) -> Quat {
    if (q.length_squared() - 1.0).abs() <= 1e-6 {
        q
    } else {
        q.normalize()
    }
}

/// The binary chunk and the JSON root filled side by side.
struct Builder {
    root: json::Root,
    bin: Vec<u8>,
}

impl Builder {
    /// Appends `bytes` as a new buffer view, 4-byte aligned.
    fn view(
        &mut self,
        bytes: &[u8],
        target: Option<json::buffer::Target>,
    ) -> Index<json::buffer::View> {
        self.align();
        let offset = self.bin.len();
        self.bin.extend_from_slice(bytes);
        self.root.push(json::buffer::View {
            buffer: Index::new(0),
            byte_length: USize64::from(bytes.len()),
            byte_offset: Some(USize64::from(offset)),
            byte_stride: None,
            name: None,
            target: target.map(Valid),
            extensions: None,
            extras: Default::default(),
        })
    }

    fn align(&mut self) {
        while !self.bin.len().is_multiple_of(4) {
            self.bin.push(0);
        }
    }

    fn accessor(
        &mut self,
        bytes: &[u8],
        count: usize,
        component: json::accessor::ComponentType,
        kind: json::accessor::Type,
        target: Option<json::buffer::Target>,
        bounds: Option<(serde_json::Value, serde_json::Value)>,
    ) -> Index<json::Accessor> {
        let view = self.view(bytes, target);
        let (min, max) = bounds.unzip();
        self.root.push(json::Accessor {
            buffer_view: Some(view),
            byte_offset: None,
            count: USize64::from(count),
            component_type: Valid(json::accessor::GenericComponentType(component)),
            extensions: None,
            extras: Default::default(),
            type_: Valid(kind),
            min,
            max,
            name: None,
            normalized: false,
            sparse: None,
        })
    }

    fn vec3s(&mut self, values: &[Vec3]) -> Index<json::Accessor> {
        let values: Vec<[f32; 3]> = values.iter().map(|v| v.to_array()).collect();
        self.f32s(&values, None, false)
    }

    /// An accessor of `N`-component floats (1 scalar, 3 vec3, 4 vec4, 16 mat4), with
    /// per-component `min`/`max` when `bounds`.
    fn f32s<const N: usize>(
        &mut self,
        values: &[[f32; N]],
        target: Option<json::buffer::Target>,
        bounds: bool,
    ) -> Index<json::Accessor> {
        let kind = match N {
            1 => json::accessor::Type::Scalar,
            3 => json::accessor::Type::Vec3,
            4 => json::accessor::Type::Vec4,
            _ => json::accessor::Type::Mat4,
        };
        let bytes: Vec<u8> = values
            .iter()
            .flatten()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        let bounds = bounds.then(|| {
            let mut lo = [f32::INFINITY; N];
            let mut hi = [f32::NEG_INFINITY; N];
            for v in values {
                for c in 0..N {
                    lo[c] = lo[c].min(v[c]);
                    hi[c] = hi[c].max(v[c]);
                }
            }
            (json!(lo.to_vec()), json!(hi.to_vec()))
        });
        let component = json::accessor::ComponentType::F32;
        self.accessor(&bytes, values.len(), component, kind, target, bounds)
    }

    /// The buffer, the JSON and the GLB container.
    fn finish(mut self) -> Result<Vec<u8>, ExportError> {
        self.align();
        self.root.push(json::Buffer {
            byte_length: USize64::from(self.bin.len()),
            name: None,
            uri: None,
            extensions: None,
            extras: Default::default(),
        });
        let json = self.root.to_vec()?;
        // GLB lengths are u32 (and the gltf crate's writer truncates rather than refuses).
        let bytes = 12 + 8 + json.len().next_multiple_of(4) + 8 + self.bin.len();
        if u32::try_from(bytes).is_err() {
            return Err(ExportError::TooLarge { bytes });
        }
        let glb = Glb {
            header: Header {
                magic: *b"glTF",
                version: 2,
                // Recomputed by the writer.
                length: 0,
            },
            json: Cow::Owned(json),
            bin: Some(Cow::Owned(self.bin)),
        };
        Ok(glb.to_vec()?)
    }
}
