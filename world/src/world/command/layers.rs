//! The clip-layer commands (`play_layer`, `stop_layer`, issue 29 goal 4): everything checked
//! (numbers, the clip, the mask, the layer count) before the avatar changes, then the layer
//! started, replaced or faded out under the scene's lock and the pose re-evaluated at once.

use super::{Bake, Handler, clip_for, fields, finite, with_avatar};
use crate::world::World;
use posecast_core::error::Error;
use posecast_proto::command::{Command, CommandResult, MAX_LAYERS};
use posecast_sim::avatar::layers::{ClipLayer, LayerSpec, owned_joints};
use posecast_sim::avatar::playback::{DEFAULT_FADE, Layer};

/// `play_layer`: a clip on a masked, weighted layer over the base clip, started or replaced.
#[derive(Debug)]
pub struct PlayLayer;

impl Handler for PlayLayer {
    fn bake<'c>(&self, command: &'c Command) -> Option<Bake<'c>> {
        match command {
            Command::PlayLayer {
                avatar,
                clip,
                from_asset: Some(source),
                ..
            } => Some(Bake {
                avatar,
                clip,
                source,
            }),
            _ => None,
        }
    }

    fn apply(&self, world: &World, command: &Command) -> Result<CommandResult, Error> {
        fields!(
            command,
            PlayLayer {
                avatar,
                layer,
                clip,
                from_asset,
                mask,
                additive,
                reference,
                weight,
                speed,
                looping,
                start,
                fade,
            }
        );
        posecast_proto::msg::check_id("layer", layer)
            .map_err(|e| Error::invalid_field("layer", e.message))?;
        let speed = finite("speed", speed.unwrap_or(1.0))?;
        let start = finite("start", start.unwrap_or(0.0))?;
        let fade = finite("fade", fade.unwrap_or(DEFAULT_FADE))?.max(0.0);
        let weight = finite("weight", weight.unwrap_or(1.0))?;
        if !(0.0..=1.0).contains(&weight) {
            return Err(Error::invalid_field(
                "weight",
                format!("weight {weight} is outside [0, 1]"),
            ));
        }
        let source = from_asset
            .as_ref()
            .map(|name| world.library.require(name))
            .transpose()?;
        with_avatar(world, avatar, |a| {
            let owned = owned_joints(&a.rig, mask.as_ref())
                .map_err(|e| Error::invalid(format!("mask: {e}")))?;
            let (clip, source_asset) = clip_for(world, a, clip, source.as_ref())?;
            let played = Layer::new(clip, source_asset, start, speed, looping.unwrap_or(true));
            let spec = LayerSpec {
                owned,
                mask: mask.clone(),
                additive: *additive,
                reference: *reference,
                weight,
            };
            if let Some(l) = a.layers.iter_mut().find(|l| l.name == *layer) {
                l.replace(played, spec, fade);
            } else {
                if a.layers.len() >= MAX_LAYERS {
                    return Err(Error::invalid(format!(
                        "avatar {} plays {MAX_LAYERS} layers already (stop_layer one first)",
                        a.id
                    )));
                }
                let clock = a.player.clock();
                a.layers
                    .push(ClipLayer::new(layer.clone(), played, spec, clock, fade));
            }
            a.evaluate();
            Ok(CommandResult::Done)
        })
    }
}

/// `stop_layer`: faded out, then gone.
#[derive(Debug)]
pub struct StopLayer;

impl Handler for StopLayer {
    fn apply(&self, world: &World, command: &Command) -> Result<CommandResult, Error> {
        fields!(
            command,
            StopLayer {
                avatar,
                layer,
                fade,
            }
        );
        let fade = fade.map(|f| finite("fade", f)).transpose()?;
        with_avatar(world, avatar, |a| {
            let l = a
                .layers
                .iter_mut()
                .find(|l| l.name == *layer)
                .ok_or_else(|| {
                    Error::invalid_field("layer", format!("avatar {} has no layer {layer:?}", a.id))
                })?;
            l.stop(fade);
            a.layers.retain(|l| !l.finished());
            a.evaluate();
            Ok(CommandResult::Done)
        })
    }
}
