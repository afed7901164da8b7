//! `sample_pose`: the pose of a private copy of an avatar playing a clip at a time — what
//! `posecast-client render --clip/--seek` shows — read with a view token, checked against the
//! built-in avatar's clips sampled here, and changing nothing other viewers see.

#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use common::{CONTROL, http_as, server, wait_for};
use glam::Quat;
use posecast_client::net::{Client, ClientError, ClientOptions};
use posecast_proto::command::Command;
use posecast_proto::msg::{AvatarId, AvatarPoseJson, ErrorCode};
use posecast_proto::quant::angle_between_degrees;
use serde_json::Value;

/// Worst angle between the sampled rotations and `reference`'s, degrees.
fn worst(pose: &AvatarPoseJson, reference: &[posecast_proto::Transform]) -> f64 {
    assert_eq!(pose.rotations.len(), reference.len());
    pose.rotations
        .iter()
        .zip(reference)
        .map(|(&q, r)| angle_between_degrees(Quat::from_array(q), r.rotation))
        .fold(0.0, f64::max)
}

async fn connect(server: &posecast_server::startup::Server, token: Option<&str>) -> Client {
    let mut options = ClientOptions::new(server.ws_url(), "default");
    options.reconnect = false;
    options.token = token.map(str::to_owned);
    Client::connect(options).await.unwrap()
}

async fn sample(
    client: &Client,
    clip: Option<&str>,
    time: f32,
) -> Result<AvatarPoseJson, ClientError> {
    let value = client
        .command(Command::SamplePose {
            avatar: AvatarId("avatar".into()),
            clip: clip.map(str::to_owned),
            from_asset: None,
            time,
        })
        .await?;
    Ok(serde_json::from_value(value.to_value()).unwrap())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_view_token_samples_a_private_copy_and_nobody_sees_a_change() {
    let server = server(60.0).await;
    let rig = posecast_server::builtin::rig().unwrap();
    let rest = rig.skeleton().rest().to_vec();
    let sampled = |clip: &str, t: f32| {
        let c = rig.clip(clip).unwrap();
        let mut out = rest.clone();
        c.sample(c.start() + t, &rest, &mut out);
        out
    };
    let id = AvatarId("avatar".into());
    let viewer = connect(&server, None).await;
    let control = connect(&server, Some(CONTROL)).await;
    assert!(wait_for(5.0, || viewer.latest(&id).is_some()).await);
    let before = control
        .command(Command::GetAvatar { avatar: id.clone() })
        .await
        .unwrap()
        .to_value();

    // A view-only connection (no token) samples walk at 0.25 s: exactly the clip there
    // (floats, not quantised), with the avatar's description hash.
    let walk = sample(&viewer, Some("walk"), 0.25).await.unwrap();
    let err = worst(&walk, &sampled("walk", 0.25));
    assert!(err < 1e-3, "walk at 0.25 s is {err}° off the clip");
    let view = viewer.avatar(&id).unwrap();
    assert_eq!(walk.hash, view.description.hash);
    assert!(
        view.locals_of(&walk).is_some(),
        "the pose fits the description"
    );
    assert!(
        worst(&walk, &sampled("walk", 0.6)) > 1.0,
        "the reference cannot tell times apart"
    );
    // Without a clip: the clip the avatar plays (idle), at the time asked.
    let idle = sample(&viewer, None, 0.5).await.unwrap();
    let err = worst(&idle, &sampled("idle", 0.5));
    assert!(err < 1e-3, "idle at 0.5 s is {err}° off the clip");

    // Nothing changed for anyone: same state, still playing idle, the stream still moving.
    let after = control
        .command(Command::GetAvatar { avatar: id.clone() })
        .await
        .unwrap()
        .to_value();
    for field in ["clip", "paused", "speed", "overrides", "placement"] {
        assert_eq!(before[field], after[field], "{field} changed");
    }
    assert_eq!(after["clip"], "idle");
    let seq = viewer.latest(&id).unwrap().seq;
    assert!(wait_for(2.0, || viewer.latest(&id).unwrap().seq > seq + 3).await);

    // The copy keeps the avatar's joint overrides.
    let q = Quat::from_rotation_y(0.6);
    control
        .command(Command::SetJointRotation {
            avatar: id.clone(),
            joint: "l_elbow".into(),
            rotation: q.to_array(),
        })
        .await
        .unwrap();
    let elbow = rig.skeleton().find("l_elbow").unwrap();
    let overridden = sample(&viewer, Some("walk"), 0.25).await.unwrap();
    let err = angle_between_degrees(Quat::from_array(overridden.rotations[elbow]), q);
    assert!(err < 1e-3, "the override is {err}° off");

    // Extreme but finite times are a time like any other (wrapped into the looping clip): a
    // finite pose of unit rotations, not an error or NaN.
    for time in [3e38f32, -1e19, f32::MIN_POSITIVE] {
        let pose = sample(&viewer, Some("walk"), time).await.unwrap();
        assert!(
            pose.rotations
                .iter()
                .all(|q| (Quat::from_array(*q).length() - 1.0).abs() < 1e-4)
                && pose.translations.iter().flatten().all(|v| v.is_finite()),
            "time {time}: {pose:?}"
        );
    }

    // Errors are typed, and over REST a view (no token) suffices too.
    let e = sample(&viewer, Some("fly"), 0.0).await.unwrap_err();
    assert!(
        matches!(&e, ClientError::Server(p) if p.code == ErrorCode::UnknownClip),
        "{e}"
    );
    control
        .command(Command::Stop { avatar: id.clone() })
        .await
        .unwrap();
    let e = sample(&viewer, None, 0.0).await.unwrap_err();
    assert!(
        matches!(&e, ClientError::Server(p) if p.code == ErrorCode::InvalidValue),
        "{e}"
    );
    let (status, body) = http_as(
        &server,
        None,
        "POST",
        "/api/commands",
        Some(r#"{"op":"sample_pose","avatar":"avatar","clip":"wave","time":1.0}"#),
    )
    .await;
    assert_eq!(status, 200, "{body}");
    let v: Value = serde_json::from_str(&body).unwrap();
    let wave: AvatarPoseJson = serde_json::from_value(v["result"].clone()).unwrap();
    let mut reference = sampled("wave", 1.0);
    reference[elbow].rotation = q;
    let err = worst(&wave, &reference);
    assert!(err < 1e-3, "wave at 1 s over REST is {err}° off");
    server.stop().await;
}
