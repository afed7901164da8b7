//! CSE169 `.morph` files (UCSD CSE169, project 2 extra credit): one morph target over a
//! `.skin`'s vertices, as the new *absolute* position (and optionally normal) of each vertex it
//! moves.
//!
//! ```text
//! positions 2 {          normals 2 {
//!     5  0.1 1.2 0.0         5  0 0 1
//!     9  0.2 1.2 0.0         9  0 0 1
//! }                      }
//! ```
//!
//! - An entry is `index x y z` (sparse: listed vertices only, each once) or `x y z` (dense:
//!   then the count is the skin's vertex count and entry `i` is vertex `i`). The count decides:
//!   a block of `4·count` numbers is sparse, of `3·count` dense. Each block is read on its own,
//!   so a dense `positions` may come with sparse `normals`.
//! - `positions` is required, `normals` optional, in either order, each at most once; any
//!   other word is an error (no sections are skipped, so garbage after the last `}` is
//!   reported).
//! - Displacements are `Δpᵢ = p'ᵢ − pᵢ` and `Δnᵢ = n'ᵢ − nᵢ` against the skin's mesh as
//!   imported: its positions, and its normals normalised ([`super::skin::parse`] normalises
//!   them; a `.skin` without normals gets computed unit normals). Unlisted vertices have zero
//!   displacement. Without a `normals` block the target leaves normals alone.

use glam::Vec3;
use posecast_proto::SkinnedMesh;
use posecast_proto::morph::MorphTarget;

use super::ImportError;
use super::text::{Token, Tokens};

/// One parsed entry: the vertex, its new absolute value and the line of the entry.
#[derive(Clone, Copy, Debug)]
struct Entry {
    vertex: usize,
    value: Vec3,
    line: usize,
}

/// Parses `.morph` text over `mesh` (its `.skin`'s mesh) into a target named by the file's stem
/// (`head_smile.morph` → `head_smile`): `Δp = p_morph − p_skin`, `Δn = n_morph − n_skin`, in
/// the skin's bind (model) space.
///
/// # Errors
/// [`ImportError::Syntax`] for a word or token out of place (a missing `{` or `}`, garbage
/// after the last block, a vertex index that is not a whole number),
/// [`ImportError::Eof`] for a file that stops inside a block or has no `positions`,
/// [`ImportError::Count`] for a count larger than the file can hold, and
/// [`ImportError::Invalid`] for a count that does not match its block, a dense block that does
/// not list every vertex, an index out of range or listed twice, a non-finite number, or a
/// section given twice. Every error names the file and the line.
pub fn parse(file: &str, text: &str, mesh: &SkinnedMesh) -> Result<MorphTarget, ImportError> {
    let mut tokens = Tokens::new(file, text);
    let vertices = mesh.vertex_count();
    let mut positions: Option<Vec<Entry>> = None;
    let mut normals: Option<Vec<Entry>> = None;
    while tokens.peek().is_some() {
        let t = tokens.next_token("a section")?;
        let (what, slot) = match t.text.to_ascii_lowercase().as_str() {
            "positions" => ("positions", &mut positions),
            "normals" => ("normals", &mut normals),
            _ => return Err(tokens.syntax(t, "`positions` or `normals`")),
        };
        if slot.is_some() {
            return Err(tokens.invalid(t.line, format!("a second `{what}` section")));
        }
        *slot = Some(section(&mut tokens, what, vertices)?);
    }
    let positions = positions.ok_or_else(|| ImportError::Eof {
        file: file.to_owned(),
        expected: "a `positions` section".to_owned(),
    })?;
    let positions = displacements(&tokens, "position", &positions, mesh.positions())?;
    let normals = match normals {
        Some(entries) => displacements(&tokens, "normal", &entries, mesh.normals())?,
        None => Vec::new(),
    };
    Ok(MorphTarget {
        name: target_name(file).to_owned(),
        positions,
        normals,
    })
}

/// The target's name: the file name's last path part without its extension.
fn target_name(file: &str) -> &str {
    let base = file.rsplit(['/', '\\']).next().unwrap_or(file);
    base.rsplit_once('.').map_or(base, |(stem, _)| stem)
}

/// `count { entries }` after the section's word, sparse or dense by the count.
fn section(
    tokens: &mut Tokens<'_>,
    what: &str,
    vertices: usize,
) -> Result<Vec<Entry>, ImportError> {
    let (count, count_line) = tokens.count(&format!("{what} count"))?;
    tokens.check_count(what, count, 3, count_line)?;
    let open = tokens.expect("{")?;
    let closing = format!("`}}` closing the {what} block of line {}", open.line);
    let mut numbers: Vec<Token<'_>> = Vec::new();
    loop {
        let t = tokens.next_token(&closing)?;
        if t.text == "}" {
            break;
        }
        // Any float syntax, `nan` and `inf` included: those are refused below with their line.
        if t.text.parse::<f64>().is_err() {
            return Err(tokens.syntax(t, &format!("a number or {closing}")));
        }
        numbers.push(t);
    }
    let per_entry = if numbers.len() == count.saturating_mul(4) {
        4
    } else if numbers.len() == count.saturating_mul(3) {
        3
    } else {
        return Err(tokens.invalid(
            count_line,
            format!(
                "{what} count {count} does not match the block's {} numbers: {} in the sparse \
                 form (index x y z), {} in the dense form (x y z)",
                numbers.len(),
                count.saturating_mul(4),
                count.saturating_mul(3)
            ),
        ));
    };
    check_layout(tokens, what, count_line, &numbers, per_entry)?;
    if per_entry == 3 && count != vertices {
        return Err(tokens.invalid(
            count_line,
            format!(
                "{what}: the dense form (x y z, no indices) lists every vertex, but the count is \
                 {count} for a skin of {vertices} vertices"
            ),
        ));
    }
    let mut first_line: Vec<Option<usize>> = vec![None; vertices];
    let mut entries = Vec::with_capacity(count);
    for (k, chunk) in numbers.chunks_exact(per_entry).enumerate() {
        let (vertex, coords) = match chunk {
            [index, coords @ ..] if per_entry == 4 => {
                let vertex = index
                    .text
                    .parse::<usize>()
                    .map_err(|_| tokens.syntax(*index, "a vertex index (a whole number)"))?;
                if vertex >= vertices {
                    return Err(tokens.invalid(
                        index.line,
                        format!(
                            "{what}: vertex index {vertex} is out of range: the skin has \
                             {vertices} vertices"
                        ),
                    ));
                }
                (vertex, coords)
            }
            _ => (k, chunk),
        };
        let line = chunk.first().map_or(count_line, |t| t.line);
        let slot = first_line.get_mut(vertex).ok_or_else(|| {
            tokens.invalid(line, format!("{what}: vertex {vertex} is out of range"))
        })?;
        if let Some(first) = *slot {
            return Err(tokens.invalid(
                line,
                format!("{what}: vertex {vertex} is listed twice (first on line {first})"),
            ));
        }
        *slot = Some(line);
        let mut value = [0.0f32; 3];
        for (v, t) in value.iter_mut().zip(coords) {
            *v = t
                .text
                .parse::<f32>()
                .ok()
                .filter(|x| x.is_finite())
                .ok_or_else(|| {
                    tokens.invalid(
                        t.line,
                        format!(
                            "{what} of vertex {vertex}: {:?} is not a finite number",
                            t.text.chars().take(40).collect::<String>()
                        ),
                    )
                })?;
        }
        entries.push(Entry {
            vertex,
            value: Vec3::from(value),
            line,
        });
    }
    Ok(entries)
}

/// When the block is written one entry a line (every line holds the same number of numbers, 3
/// or 4), that layout must agree with the form the count chose: a count that is off by the
/// right amount (12 numbers read as 4 dense entries instead of 3 sparse ones) would otherwise
/// read indices as coordinates.
fn check_layout(
    tokens: &Tokens<'_>,
    what: &str,
    count_line: usize,
    numbers: &[Token<'_>],
    per_entry: usize,
) -> Result<(), ImportError> {
    let mut per_line: Vec<usize> = Vec::new();
    let mut last_line = None;
    for t in numbers {
        if last_line == Some(t.line) {
            if let Some(n) = per_line.last_mut() {
                *n += 1;
            }
        } else {
            per_line.push(1);
            last_line = Some(t.line);
        }
    }
    let Some(&first) = per_line.first() else {
        return Ok(());
    };
    if (first == 3 || first == 4) && first != per_entry && per_line.iter().all(|&n| n == first) {
        let (form, other) = if per_entry == 4 {
            ("sparse (index x y z)", "dense (x y z)")
        } else {
            ("dense (x y z)", "sparse (index x y z)")
        };
        return Err(tokens.invalid(
            count_line,
            format!(
                "{what}: the count makes the block {form}, but every line holds {first} \
                 numbers, as in the {other} form: is the count right?"
            ),
        ));
    }
    Ok(())
}

/// `value − rest` for the listed vertices, zero elsewhere.
fn displacements(
    tokens: &Tokens<'_>,
    what: &str,
    entries: &[Entry],
    rest: &[Vec3],
) -> Result<Vec<Vec3>, ImportError> {
    let mut out = vec![Vec3::ZERO; rest.len()];
    for e in entries {
        let (Some(d), Some(r)) = (out.get_mut(e.vertex), rest.get(e.vertex)) else {
            return Err(tokens.invalid(
                e.line,
                format!("{what} of vertex {} is out of range", e.vertex),
            ));
        };
        *d = e.value - *r;
        if !d.is_finite() {
            return Err(tokens.invalid(
                e.line,
                format!(
                    "{what} of vertex {}: the displacement from the skin's {r} to {} is not \
                     finite",
                    e.vertex, e.value
                ),
            ));
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn mesh() -> SkinnedMesh {
        SkinnedMesh::new(
            vec![Vec3::ZERO, Vec3::X, Vec3::Y],
            vec![Vec3::Z; 3],
            vec![0, 1, 2],
            1,
            vec![0; 3],
            vec![1.0; 3],
            1,
        )
        .unwrap()
    }

    #[test]
    fn names_come_from_the_stem() {
        assert_eq!(target_name("head_smile.morph"), "head_smile");
        assert_eq!(target_name("dir/a.b.morph"), "a.b");
        assert_eq!(target_name("plain"), "plain");
    }

    #[test]
    fn empty_sparse_block_is_a_zero_target() {
        let t = parse("z.morph", "positions 0 { }", &mesh()).unwrap();
        assert_eq!(t.positions, vec![Vec3::ZERO; 3]);
        assert!(t.normals.is_empty());
    }

    #[test]
    fn a_count_off_by_the_other_form_is_caught_by_the_layout() {
        // 3 sparse entries (12 numbers) with a count of 4 would read as 4 dense entries.
        let m = SkinnedMesh::new(
            vec![Vec3::ZERO; 4],
            vec![Vec3::Z; 4],
            vec![],
            1,
            vec![0; 4],
            vec![1.0; 4],
            1,
        )
        .unwrap();
        let text = "positions 4 {\n0 1 1 1\n1 1 1 1\n2 1 1 1\n}\n";
        let e = parse("c.morph", text, &m).unwrap_err().to_string();
        assert!(
            e.contains("line 1") && e.contains("is the count right"),
            "{e}"
        );
    }
}
