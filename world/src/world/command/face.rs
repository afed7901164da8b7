//! The face commands (`set_morph_weights`, `set_expression`, issue 30):
//! every name resolved and every weight checked before anything changes, then set on the
//! avatar under its scene's lock and the pose re-evaluated at once. Names resolve as a live
//! driver's and VMC's do ([`resolve_weights`]).

use super::{Announce, Handler, Needs, fields, with_avatar};
use crate::world::World;
use posecast_core::error::{Error, Owner};
use posecast_proto::command::{Command, CommandResult};
use posecast_proto::morph;
use posecast_proto::msg::AvatarId;
use posecast_sim::avatar::Avatar;

/// `set_morph_weights`: named channels (or expressions) set, the others kept or reset.
#[derive(Debug)]
pub struct SetMorphWeights;

impl Handler for SetMorphWeights {
    fn needs(&self) -> Needs {
        Needs::Drive
    }

    fn announce(&self) -> Announce {
        Announce::Faces
    }

    fn apply(&self, world: &World, command: &Command) -> Result<CommandResult, Error> {
        fields!(
            command,
            SetMorphWeights {
                avatar,
                weights,
                reset,
            }
        );
        set_weights(
            world,
            avatar,
            weights.iter().map(|(n, w)| (n.as_str(), *w)),
            *reset,
        )
    }
}

/// `set_expression`: one standard expression (or channel) at a weight, 1 by default.
#[derive(Debug)]
pub struct SetExpression;

impl Handler for SetExpression {
    fn needs(&self) -> Needs {
        Needs::Drive
    }

    fn announce(&self) -> Announce {
        Announce::Faces
    }

    fn apply(&self, world: &World, command: &Command) -> Result<CommandResult, Error> {
        fields!(
            command,
            SetExpression {
                avatar,
                expression,
                weight,
            }
        );
        set_weights(
            world,
            avatar,
            [(expression.as_str(), weight.unwrap_or(1.0))],
            false,
        )
    }
}

/// Every name resolved and every weight checked, then the weights set under the scene's lock.
fn set_weights<'n>(
    world: &World,
    avatar: &AvatarId,
    named: impl IntoIterator<Item = (&'n str, f32)>,
    reset: bool,
) -> Result<CommandResult, Error> {
    with_avatar(world, avatar, |a| {
        let weights = resolve_weights(a, named)?;
        a.set_morph(&weights, reset);
        Ok(CommandResult::Done)
    })
}

/// `(name, weight)` pairs as `(channel, weight)`: each name one of the avatar's morph channels
/// or a standard expression its description maps (`Avatar::morph_channel`), each weight in
/// `[0, 1]`.
///
/// # Errors
/// [`Error::UnknownExpression`] for the first name the avatar lacks (or any name, when it has
/// no morph targets); [`Error::Invalid`] for a weight that is NaN, infinite or outside
/// `[0, 1]`.
pub fn resolve_weights<'n>(
    a: &Avatar,
    named: impl IntoIterator<Item = (&'n str, f32)>,
) -> Result<Vec<(usize, f32)>, Error> {
    named
        .into_iter()
        .map(|(name, w)| {
            let channel = a
                .morph_channel(name)
                .ok_or_else(|| Error::UnknownExpression {
                    owner: Owner::Avatar(a.id.clone()),
                    name: name.to_owned(),
                    has_targets: !a.description.morph_targets.is_empty(),
                })?;
            let w = morph::check_weight(name, w).map_err(|e| Error::invalid(e.to_string()))?;
            Ok((channel, w))
        })
        .collect()
}
