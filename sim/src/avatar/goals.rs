//! An avatar's IK goals (`set_ik_goal`, `look_at`): which joints reach for what, solved by
//! [`crate::ik`] on every evaluation, after the clip and the live pose and before overrides
//! and DOF limits (seed 002: every DOF value is clamped, whatever set it).
//!
//! A goal is given in the **scene's space** (metres, Y up), or in the frame of a joint — of this
//! avatar or another of its scene (`relative_to`): the goal then follows that joint (a hand on
//! someone's shoulder). The scene resolves those frames from the avatars' poses before each
//! tick ([`Goals::references`], [`Goals::set_frame`]); the avatar turns them into its model
//! space through the inverse of its placement.
//!
//! **Chains.** A goal names its end joint (the effector). A limb end (H-Anim `l_wrist`,
//! `r_wrist`, `l_ankle`, `r_ankle`) is solved with its limb's root and middle joint
//! (`l_shoulder`/`l_elbow`, `l_hip`/`l_knee`) in closed form ([`crate::ik::two_bone`]), with a
//! pole for its swivel; any other joint with the `chain` joints up from it (3 by default:
//! itself, its parent and grandparent) by FABRIK ([`crate::ik::chain`]).

use crate::ik::{self, ChainGoal, Gaze, LimbGoal};
use glam::{Mat4, Quat, Vec3};
use posecast_proto::msg::AvatarId;
use posecast_proto::{Skeleton, Transform};
use posecast_rigs::rig::Rig;

/// Largest coordinate a goal position or pole may have, metres (as a placement's).
pub const MAX_COORDINATE: f32 = 1e6;
/// Most joints a goal's chain may have.
pub const MAX_CHAIN: usize = 32;
/// Joints a non-limb goal's chain has when the command does not say.
pub const DEFAULT_CHAIN: usize = 3;

/// A joint of an avatar of the same scene, whose frame a goal is given in.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct JointRef {
    /// The avatar (this one, or another of its scene).
    pub avatar: AvatarId,
    /// The joint's name on that avatar's rig.
    pub joint: String,
}

/// How a goal's chain is solved.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Solver {
    /// A limb: root, middle and end joint, solved in closed form.
    Limb([usize; 3]),
    /// Any chain, root first and the effector last, solved by FABRIK.
    Chain(Vec<usize>),
}

/// One IK goal of an avatar.
#[derive(Debug, Clone, PartialEq)]
pub struct IkGoal {
    /// The end joint.
    pub effector: usize,
    /// Its chain and solver.
    pub solver: Solver,
    /// Where the effector goes, in the goal's frame (metres).
    pub position: Vec3,
    /// The effector's rotation in the goal's frame, if the goal sets it.
    pub rotation: Option<Quat>,
    /// The point the limb's middle joint bends toward, in the goal's frame.
    pub pole: Option<Vec3>,
    /// How much of the solve applies, 0 to 1.
    pub weight: f32,
    /// The joint whose frame the goal is in (`None`: the scene's space).
    pub relative_to: Option<JointRef>,
    /// The chain length the command asked for (kept to store and show the goal as given).
    pub chain: Option<usize>,
    /// The goal frame's matrix in scene space, as last resolved (identity for the scene).
    pub frame: Mat4,
}

/// A gaze goal (`look_at`).
#[derive(Debug, Clone, PartialEq)]
pub struct GazeGoal {
    /// The joints that turn.
    pub joints: Gaze,
    /// The point looked at, in the goal's frame.
    pub target: Vec3,
    /// How much of the turn applies, 0 to 1.
    pub weight: f32,
    /// The joint whose frame `target` is in (`None`: the scene's space).
    pub relative_to: Option<JointRef>,
    /// That frame's matrix in scene space, as last resolved.
    pub frame: Mat4,
}

/// Why a goal was refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum GoalError {
    /// The rig has no joint of that name.
    #[error("the rig has no joint {0}")]
    UnknownJoint(String),
    /// The effector is a root: there is no chain to turn.
    #[error("joint {0} is a root: it has no chain to reach with")]
    NoChain(String),
    /// A value is out of range or not finite.
    #[error("{what}: {why}")]
    Invalid {
        /// Which value (`"position"`, `"rotation"`, `"weight"`, `"pole"`, `"chain"`, `"target"`).
        what: &'static str,
        /// What is wrong with it.
        why: String,
    },
}

/// A finite point within [`MAX_COORDINATE`] of the origin.
///
/// # Errors
/// [`GoalError::Invalid`] naming `what`.
pub fn point(what: &'static str, p: [f32; 3]) -> Result<Vec3, GoalError> {
    if p.iter().all(|v| v.is_finite() && v.abs() <= MAX_COORDINATE) {
        Ok(Vec3::from_array(p))
    } else {
        Err(GoalError::Invalid {
            what,
            why: format!("{p:?}: coordinates must be finite and within ±{MAX_COORDINATE} m"),
        })
    }
}

/// A weight: finite, in [0, 1]; 1 when absent.
///
/// # Errors
/// [`GoalError::Invalid`] for anything else.
pub fn weight(w: Option<f32>) -> Result<f32, GoalError> {
    match w {
        None => Ok(1.0),
        Some(w) if (0.0..=1.0).contains(&w) => Ok(w),
        Some(w) => Err(GoalError::Invalid {
            what: "weight",
            why: format!("{w} is not within [0, 1]"),
        }),
    }
}

/// The solver of a goal on `effector` (a joint by the rig's own name, else by its H-Anim
/// name): its limb when it is a limb end (H-Anim `l_wrist`, `r_wrist`, `l_ankle`, `r_ankle`,
/// whatever the rig calls them), else `chain` joints (default [`DEFAULT_CHAIN`]) up from it.
///
/// # Errors
/// An unknown joint, a root effector, a chain longer than the joint's ancestry allows or than
/// [`MAX_CHAIN`], or shorter than 2.
pub fn solver(
    rig: &Rig,
    effector: &str,
    chain: Option<usize>,
) -> Result<(usize, Solver), GoalError> {
    let skeleton = rig.skeleton();
    let end = rig
        .joint(effector)
        .ok_or_else(|| GoalError::UnknownJoint(effector.to_owned()))?;
    let parents = skeleton.parents();
    if parents[end].is_none() {
        return Err(GoalError::NoChain(effector.to_owned()));
    }
    let is_ancestor =
        |a: usize, of: usize| std::iter::successors(parents[of], |&p| parents[p]).any(|p| p == a);
    if chain.is_none() {
        let limb = match rig.hanim.get(end).and_then(Option::as_deref) {
            Some("l_wrist") => Some(("l_shoulder", "l_elbow")),
            Some("r_wrist") => Some(("r_shoulder", "r_elbow")),
            Some("l_ankle") => Some(("l_hip", "l_knee")),
            Some("r_ankle") => Some(("r_hip", "r_knee")),
            _ => None,
        };
        if let Some((root, middle)) = limb
            && let (Some(a), Some(b)) = (rig.hanim_joint(root), rig.hanim_joint(middle))
            && is_ancestor(b, end)
            && is_ancestor(a, b)
        {
            return Ok((end, Solver::Limb([a, b, end])));
        }
    }
    let n = chain.unwrap_or(DEFAULT_CHAIN);
    if !(2..=MAX_CHAIN).contains(&n) {
        return Err(GoalError::Invalid {
            what: "chain",
            why: format!("{n} joints: a chain has 2 to {MAX_CHAIN}"),
        });
    }
    let mut joints: Vec<usize> = std::iter::successors(Some(end), |&j| parents[j])
        .take(n)
        .collect();
    if chain.is_some() && joints.len() < n {
        return Err(GoalError::Invalid {
            what: "chain",
            why: format!(
                "joint {effector} has {} joints above it; a chain of {n} needs {}",
                joints.len() - 1,
                n - 1
            ),
        });
    }
    joints.reverse();
    Ok((end, Solver::Chain(joints)))
}

/// The gaze joints of a rig, by H-Anim name: head `skullbase` (a rig without one: its topmost
/// neck joint, `vc1` … `vc7`), neck the lowest `vc*` joint below the head, eyes
/// `l_eyeball_joint`/`r_eyeball_joint`.
///
/// # Errors
/// [`GoalError::UnknownJoint`] when the rig has neither a head nor a neck.
pub fn gaze(rig: &Rig) -> Result<Gaze, GoalError> {
    let skeleton = rig.skeleton();
    let head = rig
        .hanim_joint("skullbase")
        .or_else(|| (1..=7).find_map(|k| rig.hanim_joint(&format!("vc{k}"))))
        .ok_or_else(|| GoalError::UnknownJoint("skullbase (a head to look with)".into()))?;
    let neck = (1..=7)
        .rev()
        .filter_map(|k| rig.hanim_joint(&format!("vc{k}")))
        .find(|&n| {
            std::iter::successors(skeleton.parents()[head], |&p| skeleton.parents()[p])
                .any(|p| p == n)
        });
    Ok(Gaze {
        neck,
        head: Some(head),
        eyes: [
            rig.hanim_joint("l_eyeball_joint"),
            rig.hanim_joint("r_eyeball_joint"),
        ],
    })
}

/// A goal being let go (`clear_ik_goal … fade`): still solved, its weight falling linearly
/// from what it was to 0 over the fade, so the joints return to their clip smoothly.
#[derive(Debug, Clone, PartialEq)]
pub struct Releasing {
    /// The goal (or gaze) as it was.
    pub goal: Released,
    /// The scene clock when the fade began, seconds.
    pub started: f64,
    /// The fade's length, seconds (> 0).
    pub duration: f32,
}

/// What a [`Releasing`] lets go of.
#[derive(Debug, Clone, PartialEq)]
pub enum Released {
    /// An IK goal.
    Goal(IkGoal),
    /// The gaze.
    Gaze(GazeGoal),
}

impl Releasing {
    /// The share of the goal's own weight left at `clock`: 1 at the start, 0 at the end.
    #[must_use]
    pub fn remaining(&self, clock: f64) -> f32 {
        let t = ((clock - self.started) / f64::from(self.duration)) as f32;
        (1.0 - t).clamp(0.0, 1.0)
    }
}

/// An avatar's goals.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Goals {
    /// IK goals, by effector (one per effector), solved in the order they were set.
    pub goals: Vec<IkGoal>,
    /// The gaze, if one is set.
    pub gaze: Option<GazeGoal>,
    /// Goals being let go, fading out (solved before the others).
    pub releasing: Vec<Releasing>,
}

impl Goals {
    /// Whether there is nothing to solve.
    #[must_use]
    pub fn is_empty(&self) -> bool {
        self.goals.is_empty() && self.gaze.is_none() && self.releasing.is_empty()
    }

    /// Lets go of one effector's goal (`Some`), or of every goal and the gaze (`None`), over
    /// `fade` seconds from scene clock `clock` (at once when `fade` is 0). Whether anything was
    /// let go.
    pub fn release(&mut self, effector: Option<usize>, clock: f64, fade: f32) -> bool {
        let mut gone: Vec<Released> = Vec::new();
        self.goals.retain(|g| {
            let keep = effector.is_some_and(|e| g.effector != e);
            if !keep {
                gone.push(Released::Goal(g.clone()));
            }
            keep
        });
        if effector.is_none() {
            gone.extend(self.gaze.take().map(Released::Gaze));
        }
        let any = !gone.is_empty();
        if fade > 0.0 {
            self.releasing
                .extend(gone.into_iter().map(|goal| Releasing {
                    goal,
                    started: clock,
                    duration: fade,
                }));
        }
        any
    }

    /// Drops the fades that are over at `clock`.
    pub fn forget_released(&mut self, clock: f64) {
        self.releasing.retain(|r| r.remaining(clock) > 0.0);
    }

    /// Sets (or replaces) the goal of its effector (ending a fade-out of its last one).
    pub fn set(&mut self, goal: IkGoal) {
        self.releasing
            .retain(|r| !matches!(&r.goal, Released::Goal(g) if g.effector == goal.effector));
        match self.goals.iter_mut().find(|g| g.effector == goal.effector) {
            Some(g) => *g = goal,
            None => self.goals.push(goal),
        }
    }

    /// Sets (or replaces) the gaze; `None` ends it at once.
    pub fn set_gaze(&mut self, gaze: Option<GazeGoal>) {
        self.releasing
            .retain(|r| !matches!(r.goal, Released::Gaze(_)));
        self.gaze = gaze;
    }

    /// Lets go of the gaze over `fade` seconds from `clock`. Whether there was one.
    pub fn release_gaze(&mut self, clock: f64, fade: f32) -> bool {
        let Some(g) = self.gaze.take() else {
            return false;
        };
        if fade > 0.0 {
            self.releasing.push(Releasing {
                goal: Released::Gaze(g),
                started: clock,
                duration: fade,
            });
        }
        true
    }

    /// The joints the goals are relative to, with an index for [`Goals::set_frame`] (the
    /// gaze's is `usize::MAX`).
    pub fn references(&self) -> impl Iterator<Item = (usize, &JointRef)> {
        self.goals
            .iter()
            .enumerate()
            .filter_map(|(i, g)| g.relative_to.as_ref().map(|r| (i, r)))
            .chain(
                self.gaze
                    .as_ref()
                    .and_then(|g| g.relative_to.as_ref())
                    .map(|r| (usize::MAX, r)),
            )
    }

    /// Sets the scene-space matrix of reference `index`'s frame (from [`Goals::references`]).
    pub fn set_frame(&mut self, index: usize, frame: Mat4) {
        if index == usize::MAX {
            if let Some(g) = &mut self.gaze {
                g.frame = frame;
            }
        } else if let Some(g) = self.goals.get_mut(index) {
            g.frame = frame;
        }
    }

    /// Solves every goal on `locals` (model space) at scene clock `clock`, the avatar standing
    /// at `placement` (its scene-space matrix); `world` is scratch space, one matrix per joint.
    /// Goals being let go come first, at their remaining share of their weight.
    pub fn solve(
        &self,
        skeleton: &Skeleton,
        placement: Mat4,
        clock: f64,
        locals: &mut [Transform],
        world: &mut [Mat4],
    ) {
        if self.is_empty() {
            return;
        }
        let to_model = placement.inverse();
        ik::update_world(skeleton, locals, world, 0);
        for r in &self.releasing {
            let share = r.remaining(clock);
            match &r.goal {
                Released::Goal(g) => {
                    let g = IkGoal {
                        weight: g.weight * share,
                        ..g.clone()
                    };
                    solve_goal(skeleton, to_model, &g, locals, world);
                }
                Released::Gaze(g) => {
                    turn_gaze(skeleton, to_model, g, g.weight * share, locals, world)
                }
            }
        }
        for g in &self.goals {
            solve_goal(skeleton, to_model, g, locals, world);
        }
        if let Some(g) = &self.gaze {
            turn_gaze(skeleton, to_model, g, g.weight, locals, world);
        }
    }
}

/// Solves one goal, its frame taken to model space by `to_model`.
fn solve_goal(
    skeleton: &Skeleton,
    to_model: Mat4,
    g: &IkGoal,
    locals: &mut [Transform],
    world: &mut [Mat4],
) {
    let frame = to_model * g.frame;
    let (_, frame_rotation, _) = frame.to_scale_rotation_translation();
    let target = frame.transform_point3(g.position);
    let rotation = g.rotation.map(|r| (frame_rotation * r).normalize());
    match &g.solver {
        Solver::Limb(limb) => {
            let goal = LimbGoal {
                target,
                rotation,
                pole: g.pole.map(|p| frame.transform_point3(p)),
                weight: g.weight,
            };
            ik::two_bone(skeleton, locals, world, *limb, &goal);
        }
        Solver::Chain(chain) => {
            let goal = ChainGoal {
                chain: chain.clone(),
                target,
                rotation,
                weight: g.weight,
            };
            ik::chain(skeleton, locals, world, &goal);
        }
    }
}

/// Turns the gaze's joints toward its target at `weight`.
fn turn_gaze(
    skeleton: &Skeleton,
    to_model: Mat4,
    g: &GazeGoal,
    weight: f32,
    locals: &mut [Transform],
    world: &mut [Mat4],
) {
    let target = (to_model * g.frame).transform_point3(g.target);
    ik::look_at(skeleton, locals, world, &g.joints, target, weight);
}

#[cfg(test)]
mod tests {
    use super::*;
    use posecast_rigs::rig::PipelineOptions;

    /// CesiumMan keeps its own joint names (`Skeleton_arm_joint_L__2_`) and has no head joint:
    /// a goal named by H-Anim or by the rig's name is solved as the limb it is, and a gaze
    /// turns its topmost neck joint.
    #[test]
    fn goals_find_limbs_and_heads_by_h_anim_names_on_any_rig() {
        let Some(dir) = posecast_proto::testing::require_testdata("gltf") else {
            return;
        };
        let path = dir.join("CesiumMan/glTF-Binary/CesiumMan.glb");
        let asset = posecast_rigs::import::load_path(&path).unwrap().remove(0);
        let rig = Rig::from_asset(asset, &PipelineOptions::default()).unwrap();
        let wrist = rig.hanim_joint("l_wrist").unwrap();
        let own = rig.skeleton().names()[wrist].clone();
        assert_ne!(own, "l_wrist");
        for name in ["l_wrist", own.as_str()] {
            let (end, solver) = solver(&rig, name, None).unwrap();
            assert_eq!(end, wrist);
            let limb = ["l_shoulder", "l_elbow"].map(|n| rig.hanim_joint(n).unwrap());
            assert_eq!(solver, Solver::Limb([limb[0], limb[1], wrist]), "{name}");
        }
        let g = gaze(&rig).unwrap();
        assert_eq!(g.head, rig.hanim_joint("vc4"), "the topmost neck joint");
        assert_eq!(g.neck, rig.hanim_joint("vc7"));
        assert_eq!(
            solver(&rig, "tail", None),
            Err(GoalError::UnknownJoint("tail".into()))
        );
    }
}
