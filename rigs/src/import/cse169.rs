//! Puts a CSE169 `.skel`, its optional `.skin` and any `.anim` clips together into an
//! [`Asset`].

use glam::Mat4;
use posecast_proto::Skeleton;

use super::ImportError;
use super::skel::Skel;
use super::skin::Skin;
use crate::asset::{Asset, AssetMesh, SourceFormat, SourceInfo};
use crate::clip::Clip;

/// An asset from a parsed skeleton, skin and clips. With a skin, the inverse binds are the
/// inverses of its `bindings`; without, those of the zero pose. Every clip must have one slot
/// per joint (as [`super::anim::parse`] makes them for this skeleton).
pub fn assemble(
    name: &str,
    skel: Skel,
    skin: Option<Skin>,
    clips: Vec<Clip>,
) -> Result<Asset, ImportError> {
    let mut source = SourceInfo::new(SourceFormat::Cse169);
    source.notes.extend(skel.notes.iter().cloned());
    let s = &skel.skeleton;
    if let Some(c) = clips.iter().find(|c| c.joint_count() != s.len()) {
        return Err(ImportError::Unsupported {
            file: name.to_owned(),
            message: format!(
                "clip {:?} has {} joints, the skeleton {}",
                c.name(),
                c.joint_count(),
                s.len()
            ),
        });
    }
    let (skeleton, meshes) = match skin {
        Some(skin) => {
            let inverse_bind: Vec<Mat4> = skin.bind.iter().map(Mat4::inverse).collect();
            let skeleton = Skeleton::new(
                s.names().to_vec(),
                s.parents().to_vec(),
                s.rest().to_vec(),
                inverse_bind,
            )
            .and_then(|k| k.with_dofs(s.dofs().to_vec()))
            .map_err(|source| ImportError::Skeleton {
                file: name.to_owned(),
                source,
            })?;
            if let Some((m, t)) = skin.material {
                source.notes.push(format!(
                    "material {m:?} (texture {}) not imported",
                    t.as_deref().unwrap_or("none")
                ));
            }
            let mesh = AssetMesh {
                name: name.to_owned(),
                mesh: skin.mesh,
            };
            (skeleton, vec![mesh])
        }
        None => {
            source
                .notes
                .push("no .skin: inverse binds are the zero pose's".to_owned());
            (skel.skeleton, Vec::new())
        }
    };
    Ok(Asset {
        name: name.to_owned(),
        skeleton,
        meshes,
        clips,
        source,
        boxes: Some(skel.boxes),
        expressions: Vec::new(),
    })
}
