//! The protocol samples the type check reads, from the Rust types.

use crate::root;
use glam::Mat4;
use posecast_proto::command::{
    AssetInfo, AvatarState, ClipInfo, Command, CommandResult, DofInfo, DriveVia, Driver, FadeState,
    JointInfo, LayerState, RootMotion, SceneInfo, Viewer,
};
use posecast_proto::description::AvatarDescription;
use posecast_proto::msg::{
    Access, AvatarId, AvatarPoseJson, ClientMsg, Encoding, ErrorCode, FrameJson, ProtocolError,
    SceneId, ServerMsg,
};
use posecast_proto::placement::Placement;
use posecast_proto::subset::JointSet;
use posecast_proto::tokens::Right;
use serde_json::Value;
use std::fmt::Write as _;
fn scene(s: &str) -> SceneId {
    SceneId(s.into())
}

fn avatar(s: &str) -> AvatarId {
    AvatarId(s.into())
}

/// An avatar state with every optional field set (the listing sample) or none (the change).
fn state(full: bool) -> AvatarState {
    AvatarState {
        avatar: avatar("guest"),
        scene: scene("lobby"),
        asset: "avatar".into(),
        clip: Some("walk".into()),
        clip_asset: full.then(|| "01_01".into()),
        time: 0.5,
        speed: 1.5,
        looping: true,
        paused: false,
        overrides: vec!["l_elbow".into()],
        placement: Placement::try_new([2.0, 0.0, -1.0], [0.0, 0.383, 0.0, 0.924]).unwrap(),
        root_motion: full.then_some(RootMotion::Accumulate),
        driven: full,
        driver: full.then(|| Driver {
            name: "alice".into(),
            via: DriveVia::Websocket,
        }),
        recording: full.then(|| "take".into()),
        blend_shapes: if full {
            [("joy".to_owned(), 0.5)].into_iter().collect()
        } else {
            Default::default()
        },
        morph_weights: if full {
            [("mouthOpen".to_owned(), 0.25)].into_iter().collect()
        } else {
            Default::default()
        },
        fade: full.then(|| FadeState {
            from: "idle".into(),
            from_asset: Some("other".into()),
            elapsed: 0.1,
            duration: 0.3,
        }),
        ik_goals: if full {
            vec!["l_wrist".into()]
        } else {
            Vec::new()
        },
        looking: full,
        layers: if full {
            vec![LayerState {
                layer: "upper".into(),
                clip: "wave".into(),
                time: 0.75,
                speed: 1.0,
                additive: false,
                weight: 1.0,
                joints: 12,
            }]
        } else {
            Vec::new()
        },
    }
}

/// `(name, JSDoc type in protocol.js, value)` of every sample.
fn samples() -> Vec<(&'static str, &'static str, Value)> {
    macro_rules! v {
        ($x:expr) => {
            serde_json::to_value($x).unwrap()
        };
    }
    let description = AvatarDescription {
        id: avatar("guest"),
        num: 7,
        name: "avatar".into(),
        joint_names: vec!["root".into(), "spine".into()],
        parents: vec![-1, 0],
        rest_translations: vec![[0.0, 0.9, 0.0], [0.0, 0.1, 0.0]],
        rest_rotations: vec![[0.0, 0.0, 0.0, 1.0]; 2],
        rest_scales: vec![[1.0; 3]; 2],
        inverse_binds: vec![Mat4::IDENTITY.to_cols_array(); 2],
        translated_joints: vec![0],
        scaled_joints: vec![1],
        mesh_url: Some("/api/assets/avatar/mesh.glb".into()),
        morph_targets: vec!["mouthOpen".into(), "eyesClosed".into()],
        expressions: [("aa", "mouthOpen"), ("blink", "eyesClosed")]
            .into_iter()
            .map(|(k, v)| (k.to_owned(), v.to_owned()))
            .collect(),
        expression_binds: Vec::new(),
        clip: Some("walk".into()),
        hash: "0123456789abcdef".into(),
    };
    let command = |id: u64, command: Command| {
        v!(ClientMsg::Command {
            id,
            command,
            idempotency_key: None
        })
    };
    vec![
        (
            "welcome",
            "WelcomeMsg",
            v!(ServerMsg::Welcome {
                version: 1,
                encoding: Encoding::Json,
                server: "posecast 0.1.0".into(),
                tick_rate: 60.0,
                server_time_us: 1_763_891_000_000_000,
                access: Access {
                    view: true,
                    control: true,
                    name: Some("alice".into()),
                    scenes: Some(vec![scene("lobby")]),
                    avatars: Some(vec![avatar("alice")]),
                    rights: vec![Right::View, Right::Control, Right::Drive],
                    expires_at: Some(1_763_894_600),
                },
            }),
        ),
        (
            "subscribed",
            "SubscribedMsg",
            v!(ServerMsg::Subscribed {
                scene: scene("lobby"),
                scene_num: 2,
                rate: Some(20.0),
                joints: Some(JointSet::Depth(3)),
                precision: None,
            }),
        ),
        (
            "unsubscribed",
            "UnsubscribedMsg",
            v!(ServerMsg::Unsubscribed {
                scene: scene("lobby"),
            }),
        ),
        (
            "description",
            "DescriptionMsg",
            v!(ServerMsg::Description {
                scene: scene("lobby"),
                avatar: Box::new(description),
            }),
        ),
        (
            "avatarRemoved",
            "AvatarRemovedMsg",
            v!(ServerMsg::AvatarRemoved {
                scene: scene("lobby"),
                avatar: avatar("guest"),
            }),
        ),
        (
            "scenes",
            "ScenesMsg",
            v!(ServerMsg::Scenes {
                scenes: vec![SceneInfo {
                    scene: scene("lobby"),
                    avatars: vec![state(true)],
                    subscribers: 3,
                    owner: None,
                    viewers: vec![
                        Viewer {
                            name: Some("alice".into()),
                            connections: 2,
                        },
                        Viewer {
                            name: None,
                            connections: 1,
                        },
                    ],
                }],
            }),
        ),
        (
            "viewers",
            "ViewersMsg",
            v!(ServerMsg::Viewers {
                scene: scene("lobby"),
                viewers: vec![Viewer {
                    name: Some("alice".into()),
                    connections: 1,
                }],
            }),
        ),
        (
            "sceneCreated",
            "SceneCreatedMsg",
            v!(ServerMsg::SceneCreated {
                scene: scene("lobby"),
            }),
        ),
        (
            "sceneDeleted",
            "SceneDeletedMsg",
            v!(ServerMsg::SceneDeleted {
                scene: scene("lobby"),
            }),
        ),
        (
            "avatarChanged",
            "AvatarChangedMsg",
            v!(ServerMsg::AvatarChanged {
                scene: scene("lobby"),
                seq: 5120,
                avatar: Box::new(state(false)),
            }),
        ),
        (
            "pong",
            "PongMsg",
            v!(ServerMsg::Pong {
                id: 3,
                client_time_us: 1_763_891_000_000_000,
                server_time_us: 1_763_891_000_000_500,
            }),
        ),
        (
            "ack",
            "AckMsg",
            v!(ServerMsg::Ack {
                id: 4,
                result: CommandResult::AvatarAdded {
                    avatar: AvatarId("guest".into()),
                },
            }),
        ),
        (
            "ackNull",
            "AckMsg",
            v!(ServerMsg::Ack {
                id: 5,
                result: CommandResult::Done,
            }),
        ),
        (
            "frame",
            "FrameMsg",
            v!(ServerMsg::Frame(FrameJson {
                scene: scene("lobby"),
                seq: 5121,
                server_time_us: 1_763_891_000_016_667,
                avatars: vec![AvatarPoseJson {
                    avatar: avatar("guest"),
                    hash: "0123456789abcdef".into(),
                    rotations: vec![[0.0, 0.0, 0.0, 1.0]; 2],
                    translations: vec![[0.0, 0.9, 0.0]],
                    scales: vec![[1.0, 1.0, 1.0]],
                    placement: Placement::IDENTITY,
                    joints: Some(vec![0, 1]),
                    weights: [
                        ("mouthOpen".to_owned(), 0.25),
                        ("eyesClosed".to_owned(), 0.0)
                    ]
                    .into_iter()
                    .collect(),
                }],
            })),
        ),
        (
            "error",
            "ErrorMsg",
            v!(ServerMsg::Error(ProtocolError {
                code: ErrorCode::RateLimited,
                message: "too many commands: try again in 5 ms".into(),
                id: Some(12),
                retry_after_ms: Some(5),
                details: None,
            })),
        ),
        (
            "error_details",
            "ErrorMsg",
            v!(ServerMsg::Error(ProtocolError {
                code: ErrorCode::UnknownClip,
                message: "rig avatar has no clip jump".into(),
                id: Some(13),
                retry_after_ms: None,
                details: Some(Box::new(posecast_proto::msg::ErrorDetails {
                    asset: Some("avatar".into()),
                    clip: Some("jump".into()),
                    ..Default::default()
                })),
            })),
        ),
        (
            "assets",
            "AssetInfo[]",
            v!(vec![AssetInfo {
                name: "avatar".into(),
                joints: 23,
                clips: vec![ClipInfo {
                    name: "walk".into(),
                    duration: 1.0,
                }],
                pipeline: vec!["normalised".into()],
                humanoid: true,
                mapped: 23,
                notes: vec!["material skin not imported".into()],
            }]),
        ),
        (
            "joint",
            "JointInfo",
            v!(JointInfo {
                joint: "knee_r".into(),
                parent: Some("hip_r".into()),
                joint_type: Some("ball_euler".into()),
                dofs: vec![DofInfo {
                    value: -2.0,
                    min: Some(-2.0),
                    max: None,
                }],
                rotation: [-0.841, 0.0, 0.0, 0.540],
                overridden: false,
            }),
        ),
        (
            "hello",
            "ClientMsg",
            v!(ClientMsg::Hello {
                version: 1,
                encoding: Encoding::Json,
                token: Some("s3cret-control-token".into()),
                client: Some("posecast-dashboard".into()),
            }),
        ),
        (
            "subscribe",
            "ClientMsg",
            v!(ClientMsg::Subscribe {
                scene: scene("lobby"),
                avatars: Some(vec![avatar("guest")]),
                rate: Some(20.0),
                joints: Some(JointSet::Names(vec!["Head".into()])),
                morph_weights: Some(false),
                precision: Some(posecast_proto::precision::Precision {
                    degrees: Some(0.1),
                    millimetres: Some(2.0),
                    shell: None,
                    translation: Some(0.001),
                }),
            }),
        ),
        ("watchScenes", "ClientMsg", v!(ClientMsg::WatchScenes)),
        ("unwatchScenes", "ClientMsg", v!(ClientMsg::UnwatchScenes)),
        (
            "ping",
            "ClientMsg",
            v!(ClientMsg::Ping {
                id: 1,
                client_time_us: 1_763_891_000_000_000,
            }),
        ),
        (
            "addAvatar",
            "ClientMsg",
            command(
                1,
                Command::AddAvatar {
                    scene: scene("lobby"),
                    asset: "avatar".into(),
                    avatar: Some(avatar("guest")),
                    clip: Some("walk".into()),
                    position: Some([1.0, 0.0, 0.0]),
                    rotation: Some([0.0, 0.707, 0.0, 0.707]),
                },
            ),
        ),
        (
            "placeAvatar",
            "ClientMsg",
            command(
                2,
                Command::PlaceAvatar {
                    avatar: avatar("guest"),
                    position: [2.0, 0.0, 0.5],
                    rotation: [0.0, 0.0, 0.0, 1.0],
                    duration: Some(1.5),
                },
            ),
        ),
        (
            "play",
            "ClientMsg",
            command(
                3,
                Command::Play {
                    avatar: avatar("guest"),
                    clip: "walk".into(),
                    from_asset: Some("01_01".into()),
                    speed: Some(1.5),
                    looping: Some(true),
                    start: Some(0.2),
                    fade: Some(0.3),
                    root_motion: Some(RootMotion::InPlace),
                },
            ),
        ),
        (
            "setJointDofs",
            "ClientMsg",
            command(
                4,
                Command::SetJointDofs {
                    avatar: avatar("guest"),
                    joint: "knee_r".into(),
                    values: vec![0.3, 0.0, 0.0],
                },
            ),
        ),
        (
            "release",
            "ClientMsg",
            command(
                5,
                Command::Release {
                    avatar: avatar("guest"),
                    joint: Some("knee_r".into()),
                },
            ),
        ),
    ]
}

fn samples_js() -> String {
    let mut out = String::from(
        "// @ts-check\n\
         // Written by tests/web/samples.rs from the Rust protocol types (POSECAST_UPDATE_WEB_SAMPLES=1\n\
         // rewrites it; the test fails when it is out of date). Each sample satisfies its JSDoc\n\
         // type in ../protocol.js: tsc (scripts/check-web) fails on a field missing, extra or of\n\
         // another type. Not served; nothing imports it.\n",
    );
    for (name, ty, value) in samples() {
        let json = serde_json::to_string_pretty(&value).unwrap();
        write!(
            out,
            "\nexport const {name} = /** @satisfies {{import(\"../protocol.js\").{ty}}} */ ({json});\n"
        )
        .unwrap();
    }
    out
}

/// The samples the type check reads are what the Rust types serialise today.
#[test]
fn the_protocol_samples_are_what_the_rust_types_serialise() {
    let path = root().join("server/web/check/samples.js");
    let want = samples_js();
    if std::env::var_os("POSECAST_UPDATE_WEB_SAMPLES").is_some() {
        std::fs::write(&path, &want).unwrap();
    }
    let have = std::fs::read_to_string(&path).unwrap_or_default();
    assert!(
        have == want,
        "{} is out of date with the Rust protocol types: rerun with POSECAST_UPDATE_WEB_SAMPLES=1, \
         then make server/web/protocol.js match (scripts/check-web)",
        path.display()
    );
}
