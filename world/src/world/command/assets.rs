//! The commands on assets: `list_assets`, `get_asset`, and the ones that touch the files of
//! uploads and recordings, which the services run ([`Runs::Files`]): `configure_asset` and
//! `delete_asset` ([`InServices`] declarations), `delete_clip`.

use super::{Announce, Handler, InServices, Needs, Runs, SceneChange, fields};
use crate::world::World;
use posecast_core::error::Error;
use posecast_proto::command::{Command, CommandResult};

/// `list_assets`.
#[derive(Debug)]
pub struct ListAssets;

impl Handler for ListAssets {
    fn announce(&self) -> Announce {
        Announce::Nothing
    }

    fn apply(&self, world: &World, _command: &Command) -> Result<CommandResult, Error> {
        Ok(CommandResult::Assets(
            world.library.all().iter().map(|r| r.info()).collect(),
        ))
    }
}

/// `get_asset`.
#[derive(Debug)]
pub struct GetAsset;

impl Handler for GetAsset {
    fn announce(&self) -> Announce {
        Announce::Nothing
    }

    fn apply(&self, world: &World, command: &Command) -> Result<CommandResult, Error> {
        fields!(command, GetAsset { asset });
        Ok(CommandResult::Asset(Box::new(
            world.library.require(asset)?.detail(),
        )))
    }
}

/// `configure_asset`: the upload's files imported again with new options, stored before the
/// answer (`crate::ingest::configure`).
pub static CONFIGURE_ASSET: InServices = InServices {
    op: "configure_asset",
    needs: Needs::Control,
    scene_change: SceneChange::None,
    files: "an upload's files, which the world does not hold",
};

/// `delete_clip`: a recorded clip, its file and its bytes in the quotas
/// (`crate::control`'s objects).
#[derive(Debug)]
pub struct DeleteClip;

impl Handler for DeleteClip {
    fn needs(&self) -> Needs {
        Needs::DeleteOwned
    }

    fn runs(&self) -> Runs {
        Runs::Files
    }

    fn announce(&self) -> Announce {
        Announce::Nothing
    }

    /// The clip leaves its rig (avatars playing it stop); its file is the service's.
    fn apply(&self, world: &World, command: &Command) -> Result<CommandResult, Error> {
        fields!(command, DeleteClip { asset, clip });
        world.remove_clip(asset, clip, true)?;
        Ok(CommandResult::Done)
    }
}

/// `delete_asset`: an upload, its files and its bytes in the quotas.
pub static DELETE_ASSET: InServices = InServices {
    op: "delete_asset",
    needs: Needs::DeleteOwned,
    scene_change: SceneChange::None,
    files: "an upload's files, which the world does not hold",
};
