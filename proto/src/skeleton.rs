//! A validated joint tree: names, parents (parents before children), rest local transforms,
//! inverse bind matrices and each joint's degrees of freedom.
//!
//! All checks happen in [`Skeleton::new`], so forward kinematics and skinning can index freely
//! afterwards and never fail.

use crate::dof::JointDofs;
use crate::transform::Transform;
use glam::Mat4;
use std::collections::HashMap;

/// The most joints one skeleton may have: joint indices travel as `u16` on the wire and in
/// vertex attributes.
pub const MAX_JOINTS: usize = u16::MAX as usize;

/// Why a skeleton was refused.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum SkeletonError {
    /// The skeleton was given no joints.
    #[error("skeleton has no joints")]
    Empty,
    /// The skeleton has more joints than [`MAX_JOINTS`].
    #[error("skeleton has {count} joints, more than the limit of {MAX_JOINTS}")]
    TooManyJoints {
        /// How many joints it was given.
        count: usize,
    },
    /// A per-joint list does not have one entry per joint.
    #[error("{what} has {actual} entries, expected one per joint ({expected})")]
    Length {
        /// Which list is wrong (`"parents"`, `"rest transforms"`, `"joint DOFs"`, …).
        what: &'static str,
        /// The number of joints (the length the list should have).
        expected: usize,
        /// The list's actual length.
        actual: usize,
    },
    /// A joint's parent index is not below its own (joints must come parent first).
    #[error("joint {joint} ({name:?}) has parent {parent}, which does not come before it")]
    ParentOrder {
        /// Index of the joint.
        joint: usize,
        /// Name of the joint.
        name: String,
        /// Index of its parent, at or after `joint`.
        parent: usize,
    },
    /// A joint's parent index names no joint.
    #[error("joint {joint} has parent {parent}, but there are only {count} joints")]
    ParentOutOfRange {
        /// Index of the joint.
        joint: usize,
        /// The parent index it was given.
        parent: usize,
        /// The number of joints (valid parents are below it).
        count: usize,
    },
    /// The parent links loop, so no parent-first order exists ([`topological_order`]).
    #[error("the parent links form a cycle through joint {joint}")]
    Cycle {
        /// Index of a joint on (or below) the cycle.
        joint: usize,
    },
    /// A joint's name is the empty string.
    #[error("joint {joint} has an empty name")]
    EmptyName {
        /// Index of the unnamed joint.
        joint: usize,
    },
    /// Two joints share a name.
    #[error("joint name {name:?} is used by joints {first} and {second}")]
    DuplicateName {
        /// The shared name.
        name: String,
        /// Index of the first joint with it.
        first: usize,
        /// Index of the later joint with it.
        second: usize,
    },
    /// A joint's rest transform or inverse bind matrix has a NaN or infinite entry.
    #[error("joint {joint} ({name:?}) has a non-finite {what}")]
    NotFinite {
        /// Index of the joint.
        joint: usize,
        /// Name of the joint.
        name: String,
        /// Which value is not finite (`"rest transform"` or `"inverse bind"`).
        what: &'static str,
    },
    /// A joint's inverse bind matrix cannot be inverted (|det| < 1e-12).
    #[error("joint {joint} ({name:?}) has a singular inverse bind matrix")]
    SingularBind {
        /// Index of the joint.
        joint: usize,
        /// Name of the joint.
        name: String,
    },
}

/// A joint hierarchy stored parent-before-child, so forward kinematics is one forward loop.
#[derive(Clone, Debug, PartialEq)]
pub struct Skeleton {
    names: Vec<String>,
    parents: Vec<Option<usize>>,
    rest: Vec<Transform>,
    inverse_bind: Vec<Mat4>,
    dofs: Vec<JointDofs>,
}

impl Skeleton {
    /// Builds a skeleton, checking that every list has one entry per joint, that each parent
    /// comes before its child (which also rules out cycles), that names are unique and
    /// non-empty, and that every transform is finite and every inverse bind invertible.
    ///
    /// Every joint gets free [`JointDofs`]; use [`Skeleton::with_dofs`] to set limits.
    pub fn new(
        names: Vec<String>,
        parents: Vec<Option<usize>>,
        rest: Vec<Transform>,
        inverse_bind: Vec<Mat4>,
    ) -> Result<Self, SkeletonError> {
        let count = names.len();
        if count == 0 {
            return Err(SkeletonError::Empty);
        }
        if count > MAX_JOINTS {
            return Err(SkeletonError::TooManyJoints { count });
        }
        check_len("parents", count, parents.len())?;
        check_len("rest transforms", count, rest.len())?;
        check_len("inverse bind matrices", count, inverse_bind.len())?;
        let mut seen: HashMap<&str, usize> = HashMap::with_capacity(count);
        for (joint, name) in names.iter().enumerate() {
            if name.is_empty() {
                return Err(SkeletonError::EmptyName { joint });
            }
            if let Some(first) = seen.insert(name.as_str(), joint) {
                return Err(SkeletonError::DuplicateName {
                    name: name.clone(),
                    first,
                    second: joint,
                });
            }
        }
        for (joint, parent) in parents.iter().enumerate() {
            if let Some(parent) = *parent {
                if parent >= count {
                    return Err(SkeletonError::ParentOutOfRange {
                        joint,
                        parent,
                        count,
                    });
                }
                if parent >= joint {
                    let name = names[joint].clone();
                    return Err(SkeletonError::ParentOrder {
                        joint,
                        name,
                        parent,
                    });
                }
            }
        }
        for joint in 0..count {
            let name = || names[joint].clone();
            if !rest[joint].is_finite() {
                return Err(SkeletonError::NotFinite {
                    joint,
                    name: name(),
                    what: "rest transform",
                });
            }
            let ib = inverse_bind[joint];
            if !ib.is_finite() {
                return Err(SkeletonError::NotFinite {
                    joint,
                    name: name(),
                    what: "inverse bind",
                });
            }
            if ib.determinant().abs() < 1e-12 {
                return Err(SkeletonError::SingularBind {
                    joint,
                    name: name(),
                });
            }
        }
        let dofs = vec![JointDofs::default(); count];
        Ok(Self {
            names,
            parents,
            rest,
            inverse_bind,
            dofs,
        })
    }

    /// Replaces every joint's degrees of freedom (one entry per joint).
    pub fn with_dofs(mut self, dofs: Vec<JointDofs>) -> Result<Self, SkeletonError> {
        check_len("joint DOFs", self.len(), dofs.len())?;
        self.dofs = dofs;
        Ok(self)
    }

    /// Number of joints (at least one).
    #[must_use]
    pub fn len(&self) -> usize {
        self.names.len()
    }

    /// Always false: a skeleton has at least one joint. Present for clippy's `len_without_is_empty`.
    #[must_use]
    pub fn is_empty(&self) -> bool {
        self.names.is_empty()
    }

    /// Joint names, unique and non-empty, indexed by joint.
    #[must_use]
    pub fn names(&self) -> &[String] {
        &self.names
    }

    /// Parent of each joint, `None` for roots; a parent index is always below its child's.
    #[must_use]
    pub fn parents(&self) -> &[Option<usize>] {
        &self.parents
    }

    /// Rest (bind-time) local transforms `D_j`, in the parent's space.
    #[must_use]
    pub fn rest(&self) -> &[Transform] {
        &self.rest
    }

    /// Inverse bind matrices `B_j⁻¹`: model space to the joint's bind space.
    #[must_use]
    pub fn inverse_bind(&self) -> &[Mat4] {
        &self.inverse_bind
    }

    /// Degrees of freedom and limits of each joint.
    #[must_use]
    pub fn dofs(&self) -> &[JointDofs] {
        &self.dofs
    }

    /// Index of the joint with this exact name.
    #[must_use]
    pub fn find(&self, name: &str) -> Option<usize> {
        self.names.iter().position(|n| n == name)
    }

    /// Indices of the root joints (those without a parent).
    pub fn roots(&self) -> impl Iterator<Item = usize> + '_ {
        self.parents
            .iter()
            .enumerate()
            .filter(|(_, p)| p.is_none())
            .map(|(j, _)| j)
    }

    /// Indices of the direct children of `joint`.
    pub fn children(&self, joint: usize) -> impl Iterator<Item = usize> + '_ {
        self.parents
            .iter()
            .enumerate()
            .filter(move |(_, p)| **p == Some(joint))
            .map(|(j, _)| j)
    }

    /// World bind matrices `B_j` (the inverses of the inverse binds).
    #[must_use]
    pub fn bind_matrices(&self) -> Vec<Mat4> {
        self.inverse_bind.iter().map(Mat4::inverse).collect()
    }
}

fn check_len(what: &'static str, expected: usize, actual: usize) -> Result<(), SkeletonError> {
    if expected == actual {
        Ok(())
    } else {
        Err(SkeletonError::Length {
            what,
            expected,
            actual,
        })
    }
}

/// Orders joints given in any order so that parents come before children.
///
/// Returns `order`, where `order[new] = old`; siblings keep their relative order and the
/// result is depth-first, which keeps chains contiguous. Errors on an out-of-range parent or a
/// cycle.
pub fn topological_order(parents: &[Option<usize>]) -> Result<Vec<usize>, SkeletonError> {
    let count = parents.len();
    let mut children: Vec<Vec<usize>> = vec![Vec::new(); count];
    let mut roots = Vec::new();
    for (joint, parent) in parents.iter().enumerate() {
        match *parent {
            Some(p) if p >= count => {
                return Err(SkeletonError::ParentOutOfRange {
                    joint,
                    parent: p,
                    count,
                });
            }
            Some(p) => children[p].push(joint),
            None => roots.push(joint),
        }
    }
    let mut order = Vec::with_capacity(count);
    let mut stack: Vec<usize> = roots.into_iter().rev().collect();
    while let Some(joint) = stack.pop() {
        order.push(joint);
        stack.extend(children[joint].iter().rev());
    }
    if order.len() != count {
        let mut placed = vec![false; count];
        for &j in &order {
            placed[j] = true;
        }
        let joint = placed.iter().position(|p| !p).unwrap_or(0);
        return Err(SkeletonError::Cycle { joint });
    }
    Ok(order)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn names(n: usize) -> Vec<String> {
        (0..n).map(|i| format!("j{i}")).collect()
    }

    fn build(parents: Vec<Option<usize>>) -> Result<Skeleton, SkeletonError> {
        let n = parents.len();
        Skeleton::new(
            names(n),
            parents,
            vec![Transform::IDENTITY; n],
            vec![Mat4::IDENTITY; n],
        )
    }

    #[test]
    fn accepts_forest() {
        let s = build(vec![None, Some(0), None, Some(2), Some(1)]).unwrap();
        assert_eq!(s.roots().collect::<Vec<_>>(), vec![0, 2]);
        assert_eq!(s.children(0).collect::<Vec<_>>(), vec![1]);
    }

    #[test]
    fn rejects_bad_input() {
        assert_eq!(build(vec![]), Err(SkeletonError::Empty));
        assert!(matches!(
            build(vec![Some(0)]),
            Err(SkeletonError::ParentOrder { .. })
        ));
        assert!(matches!(
            build(vec![None, Some(2), None]),
            Err(SkeletonError::ParentOrder { .. })
        ));
        assert!(matches!(
            build(vec![None, Some(9)]),
            Err(SkeletonError::ParentOutOfRange { .. })
        ));
        let dup = Skeleton::new(
            vec!["a".into(), "a".into()],
            vec![None, Some(0)],
            vec![Transform::IDENTITY; 2],
            vec![Mat4::IDENTITY; 2],
        );
        assert!(matches!(dup, Err(SkeletonError::DuplicateName { .. })));
        let short = Skeleton::new(names(2), vec![None], vec![], vec![]);
        assert!(matches!(short, Err(SkeletonError::Length { .. })));
        let singular = Skeleton::new(
            names(1),
            vec![None],
            vec![Transform::IDENTITY],
            vec![Mat4::ZERO],
        );
        assert!(matches!(singular, Err(SkeletonError::SingularBind { .. })));
        let mut nan = Transform::IDENTITY;
        nan.translation.x = f32::NAN;
        let nan = Skeleton::new(names(1), vec![None], vec![nan], vec![Mat4::IDENTITY]);
        assert!(matches!(nan, Err(SkeletonError::NotFinite { .. })));
    }

    #[test]
    fn topological_order_sorts_and_detects_cycles() {
        // 0 <- 2 <- 1, 3 root
        let order = topological_order(&[Some(2), None, Some(1), None]).unwrap();
        let pos = |j: usize| order.iter().position(|&o| o == j).unwrap();
        assert!(pos(1) < pos(2) && pos(2) < pos(0));
        assert_eq!(order.len(), 4);
        assert!(matches!(
            topological_order(&[Some(1), Some(0)]),
            Err(SkeletonError::Cycle { .. })
        ));
        assert!(matches!(
            topological_order(&[None, Some(5)]),
            Err(SkeletonError::ParentOutOfRange { .. })
        ));
    }
}
