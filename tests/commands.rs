//! Every command over both surfaces — REST (`POST /api/commands`) and the websocket — with
//! its effect checked on the pose stream right after the acknowledgement: poses are compared
//! with the built-in avatar's clips sampled independently here, within the quantisation bound.

#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use common::{CONTROL, http, server, wait_for};
use glam::Quat;
use posecast_client::net::{Client, ClientError, ClientOptions};
use posecast_proto::Transform;
use posecast_proto::command::Command;
use posecast_proto::msg::{AvatarId, ErrorCode, ProtocolError, SceneId};
use posecast_proto::quant::{MAX_ERROR_DEGREES, angle_between_degrees};
use posecast_server::startup::Server;
use serde_json::Value;

/// Where commands go.
enum Surface<'a> {
    Rest(&'a Server),
    Ws(Client),
}

impl Surface<'_> {
    async fn run(&self, command: Command) -> Result<Value, ProtocolError> {
        match self {
            Self::Rest(server) => {
                let body = serde_json::to_string(&command).unwrap();
                let (status, text) = http(server, "POST", "/api/commands", Some(&body)).await;
                let v: Value = serde_json::from_str(&text).unwrap();
                if status == 200 {
                    Ok(v["result"].clone())
                } else {
                    Err(serde_json::from_value(v).unwrap())
                }
            }
            Self::Ws(client) => client
                .command(command)
                .await
                .map(|r| r.to_value())
                .map_err(|e| match e {
                    ClientError::Server(e) => e,
                    other => panic!("websocket failed: {other}"),
                }),
        }
    }

    async fn ok(&self, command: Command) -> Value {
        let what = format!("{command:?}");
        self.run(command)
            .await
            .unwrap_or_else(|e| panic!("{what}: {e:?}"))
    }
}

/// The locals of the first frame the watcher gets from a tick after the acknowledgement (the
/// change is applied before the ack; one frame computed before it may still be in flight,
/// hence "seq > seq at ack + 1", i.e. at most two ticks later).
async fn after_ack(watcher: &Client, avatar: &AvatarId) -> Vec<Transform> {
    let seq = watcher.latest(avatar).map_or(0, |p| p.seq);
    assert!(
        wait_for(2.0, || watcher
            .latest(avatar)
            .is_some_and(|p| p.seq > seq + 1))
        .await,
        "no frame after the ack"
    );
    watcher.latest(avatar).unwrap().locals
}

fn worst_degrees(a: &[Transform], b: &[Transform]) -> f64 {
    a.iter()
        .zip(b)
        .map(|(x, y)| angle_between_degrees(x.rotation, y.rotation))
        .fold(0.0, f64::max)
}

fn play(avatar: &AvatarId, clip: &str, start: f32, speed: f32) -> Command {
    Command::Play {
        avatar: avatar.clone(),
        clip: clip.into(),
        from_asset: None,
        speed: Some(speed),
        looping: Some(true),
        start: Some(start),
        fade: Some(0.0),
        root_motion: None,
    }
}

async fn scenario(server: &Server, surface: &Surface<'_>, tag: &str) {
    let rig = posecast_server::builtin::rig().unwrap();
    let rest = rig.skeleton().rest().to_vec();
    let sampled = |clip: &str, t: f32| {
        let c = rig.clip(clip).unwrap();
        let mut out = rest.clone();
        c.sample(c.start() + t, &rest, &mut out);
        out
    };
    let scene = SceneId(format!("scene-{tag}"));
    let id = AvatarId(format!("a-{tag}"));

    // Scenes and avatars.
    let created = surface
        .ok(Command::CreateScene {
            scene: scene.clone(),
        })
        .await;
    assert_eq!(created["scene"], scene.0.as_str());
    let mut options = ClientOptions::new(server.ws_url(), &scene.0);
    options.reconnect = false;
    let watcher = Client::connect(options).await.unwrap();
    let added = surface
        .ok(Command::AddAvatar {
            scene: scene.clone(),
            asset: "avatar".into(),
            avatar: Some(id.clone()),
            clip: Some("walk".into()),
            position: None,
            rotation: None,
        })
        .await;
    assert_eq!(added["avatar"], id.0.as_str());
    assert!(
        wait_for(2.0, || watcher.latest(&id).is_some()).await,
        "{tag}: the added avatar never streamed"
    );
    let listed = surface.ok(Command::ListScenes).await;
    let mine = listed
        .as_array()
        .unwrap()
        .iter()
        .find(|s| s["scene"] == scene.0.as_str())
        .expect("the new scene is listed");
    assert_eq!(mine["avatars"][0]["clip"], "walk");
    let assets = surface.ok(Command::ListAssets).await;
    assert!(
        assets
            .as_array()
            .unwrap()
            .iter()
            .any(|a| a["name"] == "avatar" && a["clips"].as_array().unwrap().len() == 3)
    );

    // Playback: speed 0 freezes the clock at the start offset, so the pose is exactly known.
    surface.ok(play(&id, "wave", 1.0, 0.0)).await;
    let got = after_ack(&watcher, &id).await;
    let err = worst_degrees(&got, &sampled("wave", 1.0));
    assert!(err <= MAX_ERROR_DEGREES, "{tag} play: {err}°");
    surface
        .ok(Command::Seek {
            avatar: id.clone(),
            time: 0.4,
        })
        .await;
    let err = worst_degrees(&after_ack(&watcher, &id).await, &sampled("wave", 0.4));
    assert!(err <= MAX_ERROR_DEGREES, "{tag} seek: {err}°");
    // Moving, then paused, then moving again.
    surface
        .ok(Command::SetSpeed {
            avatar: id.clone(),
            speed: 1.0,
        })
        .await;
    let a = after_ack(&watcher, &id).await;
    let b = after_ack(&watcher, &id).await;
    assert!(
        worst_degrees(&a, &b) > 0.01,
        "{tag}: set_speed 1 did not move"
    );
    surface.ok(Command::Pause { avatar: id.clone() }).await;
    let a = after_ack(&watcher, &id).await;
    let b = after_ack(&watcher, &id).await;
    assert!(worst_degrees(&a, &b) < 1e-6, "{tag}: paused but moving");
    let state = surface.ok(Command::GetAvatar { avatar: id.clone() }).await;
    assert_eq!(
        (state["clip"].as_str(), state["paused"].as_bool()),
        (Some("wave"), Some(true))
    );
    surface.ok(Command::Resume { avatar: id.clone() }).await;
    let a = after_ack(&watcher, &id).await;
    let b = after_ack(&watcher, &id).await;
    assert!(worst_degrees(&a, &b) > 0.01, "{tag}: resumed but still");
    surface.ok(Command::Stop { avatar: id.clone() }).await;
    let err = worst_degrees(&after_ack(&watcher, &id).await, &rest);
    assert!(
        err <= MAX_ERROR_DEGREES,
        "{tag} stop: not the rest pose ({err}°)"
    );

    // Joint overrides on top of a frozen walk.
    surface.ok(play(&id, "walk", 0.25, 0.0)).await;
    let walk = sampled("walk", 0.25);
    let elbow = rig.skeleton().find("l_elbow").unwrap();
    let q = Quat::from_rotation_y(0.6);
    let set = surface
        .ok(Command::SetJointRotation {
            avatar: id.clone(),
            joint: "l_elbow".into(),
            rotation: q.to_array(),
        })
        .await;
    assert!(set["rotation"].is_array());
    let got = after_ack(&watcher, &id).await;
    assert!(angle_between_degrees(got[elbow].rotation, q) <= MAX_ERROR_DEGREES);
    let u = Quat::from_rotation_z(0.3);
    surface
        .ok(Command::RotateJointLocal {
            avatar: id.clone(),
            joint: "l_elbow".into(),
            rotation: u.to_array(),
        })
        .await;
    let got = after_ack(&watcher, &id).await;
    // L' = U·L (the increment is applied in the parent's frame).
    let err = angle_between_degrees(got[elbow].rotation, u * q);
    assert!(err <= MAX_ERROR_DEGREES, "{tag} local increment: {err}°");
    let joint = surface
        .ok(Command::GetJoint {
            avatar: id.clone(),
            joint: "l_elbow".into(),
        })
        .await;
    assert_eq!(joint["overridden"], true);
    let r: Vec<f32> = serde_json::from_value(joint["rotation"].clone()).unwrap();
    assert!(angle_between_degrees(Quat::from_slice(&r), u * q) < 1e-3);
    // World-space increment: the joint's world rotation becomes U·W about its own position.
    let world = |locals: &[Transform]| {
        let mut w = vec![glam::Mat4::IDENTITY; locals.len()];
        posecast_proto::fk::forward_kinematics(rig.skeleton(), locals, &mut w);
        w[elbow].to_scale_rotation_translation()
    };
    let (_, r0, p0) = world(&got);
    let uw = Quat::from_rotation_x(0.4);
    surface
        .ok(Command::RotateJointWorld {
            avatar: id.clone(),
            joint: "l_elbow".into(),
            rotation: uw.to_array(),
        })
        .await;
    let (_, r1, p1) = world(&after_ack(&watcher, &id).await);
    assert!(p0.distance(p1) < 1e-4, "{tag}: the elbow moved");
    let err = angle_between_degrees(r1, uw * r0);
    assert!(err < 0.05, "{tag} world increment: {err}°");
    surface
        .ok(Command::Release {
            avatar: id.clone(),
            joint: Some("l_elbow".into()),
        })
        .await;
    let err = worst_degrees(&after_ack(&watcher, &id).await, &walk);
    assert!(err <= MAX_ERROR_DEGREES, "{tag} release: {err}°");
    // A rig without joint types has no DOFs: a typed error, the same on both surfaces.
    let e = surface
        .run(Command::SetJointDofs {
            avatar: id.clone(),
            joint: "l_elbow".into(),
            values: vec![0.1],
        })
        .await
        .unwrap_err();
    assert_eq!(e.code, ErrorCode::InvalidValue);
    assert_eq!(e.details, None, "{tag}: an invalid value is its message");
    // A refused value of one field names the field.
    let e = surface
        .run(Command::SetJointRotation {
            avatar: id.clone(),
            joint: "l_elbow".into(),
            rotation: [0.0; 4],
        })
        .await
        .unwrap_err();
    assert_eq!(
        (e.code, e.details.and_then(|d| d.field).as_deref()),
        (ErrorCode::InvalidValue, Some("rotation")),
        "{tag}: {}",
        e.message
    );
    // What the server could not find comes as fields too (`details`), on both surfaces.
    let e = surface
        .run(play(&id, "no_such_clip", 0.0, 1.0))
        .await
        .unwrap_err();
    assert_eq!(e.code, ErrorCode::UnknownClip);
    let d = e
        .details
        .unwrap_or_else(|| panic!("{tag}: no details in {}", e.message));
    assert_eq!(
        (d.asset.as_deref(), d.clip.as_deref(), d.avatar),
        (Some("avatar"), Some("no_such_clip"), None),
        "{tag}"
    );
    let e = surface
        .run(Command::GetJoint {
            avatar: id.clone(),
            joint: "no_such_joint".into(),
        })
        .await
        .unwrap_err();
    assert_eq!(e.code, ErrorCode::UnknownJoint);
    let d = e.details.unwrap_or_default();
    assert_eq!(
        (d.joint.as_deref(), d.avatar.as_ref()),
        (Some("no_such_joint"), Some(&id)),
        "{tag}: the joint and whose"
    );
    let err = worst_degrees(&after_ack(&watcher, &id).await, &walk);
    assert!(
        err <= MAX_ERROR_DEGREES,
        "{tag}: a refused command changed the pose"
    );

    // Removal.
    surface
        .ok(Command::RemoveAvatar { avatar: id.clone() })
        .await;
    assert!(
        wait_for(2.0, || watcher.avatar(&id).is_none()).await,
        "{tag}: the watcher still holds the removed avatar"
    );
    surface
        .ok(Command::DeleteScene {
            scene: scene.clone(),
        })
        .await;
    let listed = surface.ok(Command::ListScenes).await;
    assert!(
        !listed
            .as_array()
            .unwrap()
            .iter()
            .any(|s| s["scene"] == scene.0.as_str())
    );
    let e = surface
        .run(Command::GetAvatar { avatar: id.clone() })
        .await
        .unwrap_err();
    assert_eq!(e.code, ErrorCode::UnknownAvatar);
    assert_eq!(e.details.and_then(|d| d.avatar), Some(id), "{tag}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_command_over_rest_changes_the_stream() {
    let server = server(60.0).await;
    scenario(&server, &Surface::Rest(&server), "rest").await;
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_command_over_the_websocket_changes_the_stream() {
    let server = server(60.0).await;
    let mut options = ClientOptions::new(server.ws_url(), "default");
    options.reconnect = false;
    options.token = Some(CONTROL.into());
    let client = Client::connect(options).await.unwrap();
    scenario(&server, &Surface::Ws(client), "ws").await;
    server.stop().await;
}
