//! CSE169 `.skin` meshes: `positions`, `normals`, optional `texcoords`, `skinweights`,
//! optional `material`, `triangles` and `bindings` (world-space bind matrices `B`, one per
//! joint in `.skel` order, each written as three axis rows then the translation row).
//!
//! Normals are directions: they are normalised on import (course files write them unnormalised,
//! `triangle.skin`'s `-1 -1 1`), so a `.morph`'s normal displacements are taken against unit
//! normals and stay right through normalisation, which renormalises rest normals only.

use glam::{Mat4, Vec2, Vec3, Vec4};
use posecast_proto::{Skeleton, SkinnedMesh};

use super::ImportError;
use super::text::Tokens;

/// A parsed `.skin`.
#[derive(Clone, Debug)]
pub struct Skin {
    /// Positions in bind (model) space, normals normalised (a zero normal stays zero); at
    /// most as many influences per vertex as the file's largest `skinweights` entry,
    /// zero-weight attachments kept as zero weights.
    pub mesh: SkinnedMesh,
    /// World bind matrices `B_j` (the file's `bindings`), one per skeleton joint.
    pub bind: Vec<Mat4>,
    /// Texture coordinates, empty when the file has none.
    pub texcoords: Vec<Vec2>,
    /// `material <name> { texture <file> }` when present: (name, texture file).
    pub material: Option<(String, Option<String>)>,
}

/// Parses `.skin` text against `skeleton` (joint indices and the binding count are checked
/// against it). Sections may come in any order; unknown sections (`word … { … }`) are skipped.
pub fn parse(name: &str, text: &str, skeleton: &Skeleton) -> Result<Skin, ImportError> {
    let mut tokens = Tokens::new(name, text);
    let mut positions = Vec::new();
    let mut normals = Vec::new();
    let mut texcoords = Vec::new();
    let mut influences = Vec::<Vec<(u16, f32)>>::new();
    let mut indices = Vec::new();
    let mut bind: Option<Vec<Mat4>> = None;
    let mut material = None;
    let joints = skeleton.len();
    while let Ok(t) = tokens.next_token("a section") {
        match t.text.to_ascii_lowercase().as_str() {
            "positions" => positions = vec3_section(&mut tokens, "positions")?,
            "normals" => {
                normals = vec3_section(&mut tokens, "normals")?
                    .into_iter()
                    .map(Vec3::normalize_or_zero)
                    .collect();
            }
            "texcoords" => {
                let (n, line) = tokens.count("texcoord count")?;
                tokens.check_count("texcoords", n, 2, line)?;
                tokens.expect("{")?;
                texcoords = (0..n)
                    .map(|_| Ok(Vec2::new(tokens.f32("u")?, tokens.f32("v")?)))
                    .collect::<Result<_, ImportError>>()?;
                tokens.expect("}")?;
            }
            "skinweights" => {
                let (n, line) = tokens.count("skinweights count")?;
                tokens.check_count("skinweights", n, 1, line)?;
                tokens.expect("{")?;
                influences = Vec::with_capacity(n);
                for _ in 0..n {
                    let (k, line) = tokens.count("attachment count")?;
                    tokens.check_count("attachments", k, 2, line)?;
                    let mut v = Vec::with_capacity(k);
                    for _ in 0..k {
                        let jt = tokens.next_token("joint index")?;
                        let joint = jt
                            .text
                            .parse::<u16>()
                            .ok()
                            .filter(|&j| usize::from(j) < joints)
                            .ok_or_else(|| {
                                tokens.invalid(
                                    jt.line,
                                    format!(
                                        "joint index {:?} is not one of the skeleton's {joints} joints",
                                        jt.text
                                    ),
                                )
                            })?;
                        v.push((joint, tokens.f32("weight")?));
                    }
                    influences.push(v);
                }
                tokens.expect("}")?;
            }
            "triangles" => {
                let (n, line) = tokens.count("triangle count")?;
                tokens.check_count("triangles", n, 3, line)?;
                tokens.expect("{")?;
                indices = Vec::with_capacity(n * 3);
                for _ in 0..n * 3 {
                    let (i, _) = tokens.count("vertex index")?;
                    let i = u32::try_from(i)
                        .map_err(|_| tokens.invalid(tokens.line(), "vertex index too large"))?;
                    indices.push(i);
                }
                tokens.expect("}")?;
            }
            "bindings" => {
                let (n, line) = tokens.count("binding count")?;
                tokens.check_count("bindings", n, 15, line)?;
                if n != joints {
                    return Err(tokens.invalid(
                        line,
                        format!("{n} bindings for a skeleton of {joints} joints"),
                    ));
                }
                tokens.expect("{")?;
                let mut b = Vec::with_capacity(n);
                for _ in 0..n {
                    tokens.expect("matrix")?;
                    tokens.expect("{")?;
                    let line = tokens.line();
                    let mut cols = [Vec4::ZERO; 4];
                    for (c, col) in cols.iter_mut().enumerate() {
                        let w = if c == 3 { 1.0 } else { 0.0 };
                        *col = tokens.vec3("matrix entry")?.extend(w);
                    }
                    tokens.expect("}")?;
                    let m = Mat4::from_cols(cols[0], cols[1], cols[2], cols[3]);
                    if m.determinant().abs() < 1e-12 {
                        return Err(tokens.invalid(line, "binding matrix is singular"));
                    }
                    b.push(m);
                }
                tokens.expect("}")?;
                bind = Some(b);
            }
            "material" => {
                let mat_name = tokens.next_token("material name")?.text.to_owned();
                tokens.expect("{")?;
                let mut texture = None;
                loop {
                    let t = tokens.next_token("`}`")?;
                    match t.text {
                        "}" => break,
                        "texture" => {
                            texture = Some(tokens.next_token("texture file")?.text.to_owned())
                        }
                        _ => {}
                    }
                }
                material = Some((mat_name, texture));
            }
            _ => {
                // Unknown section: skip its header words and its block.
                while tokens.peek().is_some_and(|p| p.text != "{") {
                    tokens.next_token("`{`")?;
                }
                tokens.skip_block()?;
            }
        }
    }
    let n = positions.len();
    if influences.len() != n {
        return Err(ImportError::Invalid {
            file: name.to_owned(),
            line: 0,
            message: format!("{} skinweights for {n} positions", influences.len()),
        });
    }
    let bind = bind.ok_or_else(|| ImportError::Eof {
        file: name.to_owned(),
        expected: "a `bindings` section".to_owned(),
    })?;
    let k = influences.iter().map(Vec::len).max().unwrap_or(1).max(1);
    let mut joint_ids = Vec::with_capacity(n * k);
    let mut weights = Vec::with_capacity(n * k);
    for v in &influences {
        for slot in 0..k {
            let (j, w) = v.get(slot).copied().unwrap_or((0, 0.0));
            joint_ids.push(j);
            weights.push(w);
        }
    }
    let mesh = SkinnedMesh::new(positions, normals, indices, k, joint_ids, weights, joints)
        .map_err(|source| ImportError::Mesh {
            file: name.to_owned(),
            mesh: name.to_owned(),
            source,
        })?;
    Ok(Skin {
        mesh,
        bind,
        texcoords,
        material,
    })
}

fn vec3_section(tokens: &mut Tokens<'_>, what: &str) -> Result<Vec<Vec3>, ImportError> {
    let (n, line) = tokens.count(&format!("{what} count"))?;
    tokens.check_count(what, n, 3, line)?;
    tokens.expect("{")?;
    let v = (0..n)
        .map(|_| tokens.vec3(what))
        .collect::<Result<Vec<_>, _>>()?;
    tokens.expect("}")?;
    Ok(v)
}
