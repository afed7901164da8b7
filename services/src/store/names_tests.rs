//! Names are data, not paths (issue 37): any name a client can give a scene, an avatar, an
//! upload or a recorded clip is either refused by the command's own check (`invalid_value`)
//! or stored so that a restart brings it back exactly — whatever dots, slashes, unicode, the
//! store's own prefixes and suffixes (`.upload-`, `.corrupt`, `.tmp`, `.json`, `.glb`) it
//! holds.

// Compiled for tests only (`store/mod.rs`); the attribute also tells scripts/check-layers.
#[cfg(test)]
use super::*;
use crate::config::Config;
use crate::state::Services;
use posecast_proto::msg::{AvatarId, check_id};
use proptest::prelude::*;

/// Names built from what the store itself writes, and a few strangers.
fn name() -> impl Strategy<Value = String> {
    let parts = prop::sample::select(vec![
        ".",
        "..",
        ".upload-",
        ".corrupt",
        ".corrupt.1",
        ".tmp",
        ".json",
        ".glb",
        ".hidden",
        "meta",
        "x",
        "a",
        "/",
        "\\",
        "é",
        "名",
        "%2E",
        "%",
        "-",
        "_",
        " ",
        "posecast.lock",
        "recordings",
        "~",
        "#",
    ]);
    prop_oneof![
        prop::collection::vec(parts, 1..5).prop_map(|p| p.concat()),
        "[a-zA-Z0-9._\\-/%é]{1,12}",
    ]
}

/// A state storing into `dir` with the built-in rig, as a start after restore sees it.
fn state_on(dir: &Path) -> std::sync::Arc<Services> {
    let state = Services::new(Config {
        data_dir: Some(dir.to_owned()),
        ..Config::default()
    });
    state.store.open().expect("open the data folder");
    state
        .world
        .library
        .insert(posecast_rigs::builtin::rig().expect("built-in rig"));
    state
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 24, ..ProptestConfig::default() })]

    /// Recorded clips: every name `record` accepts is a clip of its rig again after a
    /// restart, with its own samples.
    #[test]
    fn recorded_clip_names_are_refused_or_restored_exactly(names in prop::collection::btree_set(name(), 1..6)) {
        let dir = tempfile::tempdir().expect("tempdir");
        let state = state_on(dir.path());
        let rig = state.world.library.get("avatar").expect("built-in rig");
        let base = rig.clips.first().expect("a clip").as_ref().clone();
        let recordings = state.store.recordings_dir().expect("a data folder");
        let mut kept = Vec::new();
        for name in &names {
            if check_id("clip", name).is_err() {
                continue;
            }
            let mut clip = base.clone();
            clip.set_name(name.clone());
            let glb = posecast_rigs::export::clip_glb(&rig, &clip).expect("export");
            recordings::save(&recordings, &rig.name, name, &glb, Some("alice")).expect("save");
            kept.push(name.clone());
        }
        state.store.release();
        let after = state_on(dir.path());
        after.store.restore_recordings(&after.world);
        let rig = after.world.library.get("avatar").expect("built-in rig");
        for name in &kept {
            let clip = rig.clip(name);
            prop_assert!(clip.is_some(), "{:?} not restored", name);
            prop_assert_eq!(clip.map(|c| c.duration()), Some(base.duration()));
        }
        prop_assert_eq!(rig.clips.len(), base_clips() + kept.len());
        // Each counts against its owner.
        prop_assert_eq!(after.store.owners().usage(Some("alice")).objects, kept.len() as u64);
    }

    /// Scenes and their avatars: every id `create_scene`/`add_avatar` accept is back after a
    /// restart.
    #[test]
    fn scene_and_avatar_ids_are_refused_or_restored_exactly(names in prop::collection::btree_set(name(), 1..6)) {
        // Scenes start their tick tasks on the current runtime.
        let rt = tokio::runtime::Builder::new_current_thread().enable_all().build().expect("runtime");
        let _runtime = rt.enter();
        let dir = tempfile::tempdir().expect("tempdir");
        let state = state_on(dir.path());
        let mut kept = Vec::new();
        for name in &names {
            let id = SceneId(name.clone());
            match state.world.create_scene(id.clone()) {
                Ok(_) => {}
                Err(e) => {
                    prop_assert_eq!(e.code(), posecast_proto::msg::ErrorCode::InvalidValue, "{:?}: {}", name, e);
                    continue;
                }
            }
            state.world.add_avatar(&id, "avatar", Some(AvatarId(name.clone()))).expect("add");
            state.store.persist_scene_now(&state.world, &id).expect("write");
            kept.push(id);
        }
        state.store.release();
        let after = state_on(dir.path());
        after.store.restore_scenes(&after.world);
        for id in &kept {
            let scene = after.world.scene(id);
            prop_assert!(scene.is_ok(), "scene {} not restored", id);
            let info = scene.expect("restored").info();
            prop_assert_eq!(info.avatars.len(), 1);
            prop_assert_eq!(&info.avatars[0].avatar.0, &id.0);
        }
        prop_assert_eq!(after.world.scenes().len(), kept.len());
    }

    /// Uploads: every name the upload accepts is back after a restart.
    #[test]
    fn upload_names_are_refused_or_restored_exactly(names in prop::collection::btree_set(name(), 1..5)) {
        let dir = tempfile::tempdir().expect("tempdir");
        let state = state_on(dir.path());
        let assets = state.store.assets_dir().expect("a data folder");
        let mut kept = Vec::new();
        for name in &names {
            if posecast_rigs::library::check_name(name).is_err() {
                continue;
            }
            let mut set = FileSet::new();
            set.insert("model.glb", posecast_rigs::builtin::AVATAR_GLB.to_vec()).expect("insert");
            let meta = assets::AssetMeta::new(name, &set, vec![name.clone()]);
            assets::save_new(&assets, &set, &meta).expect("save");
            kept.push(name.clone());
        }
        state.store.release();
        let after = state_on(dir.path());
        for upload in after.store.stored_uploads() {
            after.store.restore_upload(&after.world, &upload);
        }
        for name in &kept {
            prop_assert!(after.world.library.get(name).is_some(), "upload {:?} not restored", name);
        }
        prop_assert_eq!(after.store.uploads().len(), kept.len());
    }
}

/// Clips the built-in rig comes with.
fn base_clips() -> usize {
    posecast_rigs::builtin::rig().map_or(0, |r| r.clips.len())
}

proptest! {
    /// The file-name encoding is injective and never makes a hidden, parent or suffixed name.
    #[test]
    fn encoded_names_decode_back_and_hold_no_dot(name in "\\PC{0,40}") {
        let stem = recordings::encode_name(&name);
        prop_assert!(!stem.contains('.') && !stem.contains('/') && !stem.contains('\\'));
        prop_assert_eq!(recordings::decode_name(&stem), Some(name));
    }
}
