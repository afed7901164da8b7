//! Issue 36: a cluster whose NATS only posecast servers can use. `nats-server` runs the
//! repository's sample configuration (`scripts/nats/cluster.conf`: an account of posecast's
//! own, users with subject permissions); one server logs in with a user and password, another
//! with an nkey seed, and they share a scene — commands forwarded, frames relayed, through
//! those permissions. A client without credentials, or with wrong ones, is refused by NATS
//! (so it can neither read a frame nor publish a command, a lease or a relay message), and a
//! posecast server without them does not start.

#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use common::CONTROL;
use common::child::{Posecast, run_to_exit};
use common::cluster::{listing, post};
use common::nats::Nats;
use futures_util::{SinkExt, StreamExt};
use posecast_proto::msg::Encoding;
use std::time::{Duration, Instant};
use tokio_tungstenite::tungstenite::Message;

const PASSWORD: &str = "p0secast-pw-36";

fn node(url: &str, name: &str, more: &[&str], env: &[(&str, &str)]) -> Posecast {
    let mut args = vec![
        "--nats",
        url,
        "--node",
        name,
        "--lease",
        "1.5",
        "--no-persist",
        "--tick-rate",
        "20",
        "--control-token",
        CONTROL,
    ];
    args.extend_from_slice(more);
    Posecast::start(&args, env)
}

/// Connecting to `url` with `options` fails, within 30 s: NATS's answer.
async fn refused(url: &str, options: async_nats::ConnectOptions) -> String {
    let attempt = tokio::time::timeout(Duration::from_secs(30), options.connect(url))
        .await
        .expect("NATS neither accepted nor refused within 30 s");
    match attempt {
        Ok(_) => panic!("NATS accepted a client it must refuse"),
        Err(e) => e.to_string(),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn posecast_servers_log_in_to_the_sample_config_and_nobody_else_can() {
    let pair = nkeys::KeyPair::new_user();
    let seed = pair.seed().unwrap();
    let public = pair.public_key();
    let Some(nats) = Nats::start_config(&[
        ("POSECAST_NATS_PASSWORD", PASSWORD),
        ("POSECAST_NATS_NKEY_PUBLIC", &public),
    ]) else {
        return;
    };
    let url = nats.url();
    let dir = tempfile::tempdir().unwrap();
    let seed_file = dir.path().join("posecast.nk");
    std::fs::write(&seed_file, format!("{seed}\n")).unwrap();

    // One server with a user and password (the password from the environment), one with an
    // nkey seed file.
    let a = node(
        &url,
        "a",
        &["--nats-user", "posecast"],
        &[("POSECAST_NATS_PASSWORD", PASSWORD)],
    );
    let b = node(
        &url,
        "b",
        &["--nats-nkey", seed_file.to_str().unwrap()],
        &[],
    );
    let (status, body) = post(a.addr, r#"{"op":"create_scene","scene":"stage"}"#, None).await;
    assert_eq!(status, 200, "{body}");
    let deadline = Instant::now() + Duration::from_secs(30);
    while listing(b.addr).await.is_none_or(|(owner, _)| owner != "a") {
        assert!(
            Instant::now() < deadline,
            "b never learnt that a owns stage"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    // A command through b reaches the owner (a request on posecast.scene.*.req and its answer
    // on an inbox) ...
    let (status, body) = post(
        b.addr,
        r#"{"op":"add_avatar","scene":"stage","asset":"avatar","avatar":"dancer","clip":"walk"}"#,
        None,
    )
    .await;
    assert_eq!(status, 200, "{body}");
    let (_, avatars) = listing(a.addr).await.unwrap();
    assert!(avatars.contains("dancer"), "{avatars:?}");
    // ... and a viewer on b gets the owner's frames (relayed on posecast.scene.*.relay).
    let mut viewer = common::raw_at(b.addr, Encoding::Binary, None).await;
    viewer
        .send(Message::Text(
            r#"{"type":"subscribe","scene":"stage"}"#.into(),
        ))
        .await
        .unwrap();
    let deadline = tokio::time::Instant::now() + Duration::from_secs(30);
    let mut frames = 0;
    while frames < 5 {
        match tokio::time::timeout_at(deadline, viewer.next()).await {
            Ok(Some(Ok(Message::Binary(_)))) => frames += 1,
            Ok(Some(Ok(_))) => {}
            other => panic!("no relayed frames on b: {other:?}"),
        }
    }
    for server in [&a, &b] {
        let printed = server.output().join("\n");
        assert!(
            !printed.contains(PASSWORD) && !printed.contains(&seed),
            "{printed}"
        );
    }

    // Nobody else gets in: no credentials, a wrong password, a wrong token, another nkey.
    let no_credentials = refused(&url, async_nats::ConnectOptions::new()).await;
    assert!(
        no_credentials.to_lowercase().contains("authorization"),
        "{no_credentials}"
    );
    refused(
        &url,
        async_nats::ConnectOptions::with_user_and_password("posecast".into(), "guess".into()),
    )
    .await;
    refused(
        &url,
        async_nats::ConnectOptions::with_token(PASSWORD.into()),
    )
    .await;
    let stranger = nkeys::KeyPair::new_user().seed().unwrap();
    refused(&url, async_nats::ConnectOptions::with_nkey(stranger)).await;
    // Nor a posecast server without credentials.
    let (status, output) = run_to_exit(&["--nats", &url, "--no-persist"], &[]);
    assert!(!status.success(), "{output}");
    assert!(
        output.contains("cannot join the cluster through NATS"),
        "{output}"
    );

    // The servers' own user may do what a posecast server does and no more: outside its
    // subjects NATS answers with a permission violation.
    let (tx, mut errors) = tokio::sync::mpsc::channel::<String>(16);
    let client =
        async_nats::ConnectOptions::with_user_and_password("posecast".into(), PASSWORD.into())
            .event_callback(move |event| {
                let tx = tx.clone();
                async move {
                    if let async_nats::Event::ServerError(e) = event {
                        tx.send(e.to_string()).await.ok();
                    }
                }
            })
            .connect(&url)
            .await
            .unwrap();
    let _sub = client.subscribe("elsewhere.>").await.unwrap();
    client.publish("elsewhere.x", "hi".into()).await.unwrap();
    client.flush().await.unwrap();
    let mut violations = 0;
    while violations < 2 {
        let e = tokio::time::timeout(Duration::from_secs(30), errors.recv())
            .await
            .expect("no permission violation within 30 s")
            .unwrap();
        assert!(e.to_lowercase().contains("permissions violation"), "{e}");
        violations += 1;
    }
}

/// Runs `openssl` with `args` in `dir`; `false` (after a skip, a failure under CI=true) when it
/// is not installed.
fn openssl(dir: &std::path::Path, args: &[&str]) -> bool {
    match std::process::Command::new("openssl")
        .args(args)
        .current_dir(dir)
        .output()
    {
        Ok(out) => {
            assert!(
                out.status.success(),
                "openssl {args:?}: {}",
                String::from_utf8_lossy(&out.stderr)
            );
            true
        }
        Err(e) => {
            posecast_proto::testing::skip(&format!("openssl is not installed ({e})"));
            false
        }
    }
}

/// A test CA and, signed by it, a server certificate for 127.0.0.1 and a client certificate
/// (P-256 keys, PEM): `ca.pem`, `server.pem`/`server.key`, `client.pem`/`client.key`.
fn certificates(dir: &std::path::Path) -> bool {
    let ec = [
        "-newkey",
        "ec",
        "-pkeyopt",
        "ec_paramgen_curve:prime256v1",
        "-nodes",
    ];
    let mut ca = vec!["req", "-x509"];
    ca.extend_from_slice(&ec);
    ca.extend_from_slice(&[
        "-keyout",
        "ca.key",
        "-out",
        "ca.pem",
        "-days",
        "2",
        "-subj",
        "/CN=posecast test CA",
    ]);
    if !openssl(dir, &ca) {
        return false;
    }
    for (name, usage) in [
        (
            "server",
            "subjectAltName=IP:127.0.0.1\nbasicConstraints=CA:FALSE\nextendedKeyUsage=serverAuth\n",
        ),
        (
            "client",
            "subjectAltName=DNS:posecast\nbasicConstraints=CA:FALSE\nextendedKeyUsage=clientAuth\n",
        ),
    ] {
        std::fs::write(dir.join(format!("{name}.ext")), usage).unwrap();
        let (key, csr, pem, ext, subject) = (
            format!("{name}.key"),
            format!("{name}.csr"),
            format!("{name}.pem"),
            format!("{name}.ext"),
            format!("/CN={name}"),
        );
        let mut req = vec!["req"];
        req.extend_from_slice(&ec);
        req.extend_from_slice(&["-keyout", &key, "-out", &csr, "-subj", &subject]);
        assert!(openssl(dir, &req));
        assert!(openssl(
            dir,
            &[
                "x509",
                "-req",
                "-in",
                &csr,
                "-CA",
                "ca.pem",
                "-CAkey",
                "ca.key",
                "-CAcreateserial",
                "-out",
                &pem,
                "-days",
                "2",
                "-extfile",
                &ext,
            ],
        ));
    }
    true
}

/// NATS over TLS that verifies clients: a server with the CA and a client certificate joins;
/// one without the client certificate, or without the CA (the test CA is not in the system's
/// roots), does not.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn nats_over_tls_with_client_certificates() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    if !certificates(d) {
        return;
    }
    let path = |f: &str| d.join(f).to_str().unwrap().to_owned();
    let Some(nats) = Nats::start_with(&[
        "--tlsverify",
        "--tlscert",
        &path("server.pem"),
        "--tlskey",
        &path("server.key"),
        "--tlscacert",
        &path("ca.pem"),
    ]) else {
        return;
    };
    let url = nats.url();
    let (ca, cert, key) = (path("ca.pem"), path("client.pem"), path("client.key"));
    let a = node(
        &url,
        "a",
        &[
            "--nats-tls-ca",
            &ca,
            "--nats-tls-cert",
            &cert,
            "--nats-tls-key",
            &key,
        ],
        &[],
    );
    let (status, body) = post(a.addr, r#"{"op":"create_scene","scene":"stage"}"#, None).await;
    assert_eq!(status, 200, "{body}");
    assert_eq!(listing(a.addr).await.map(|(o, _)| o).as_deref(), Some("a"));

    for (what, args) in [
        ("no client certificate", vec!["--nats-tls-ca", ca.as_str()]),
        (
            "no CA",
            vec![
                "--nats-tls-cert",
                cert.as_str(),
                "--nats-tls-key",
                key.as_str(),
            ],
        ),
        ("no TLS at all", vec![]),
    ] {
        let mut all = vec!["--nats", url.as_str(), "--no-persist"];
        all.extend_from_slice(&args);
        let (status, output) = run_to_exit(&all, &[]);
        assert!(!status.success(), "{what}: {output}");
        assert!(
            output.contains("cannot join the cluster through NATS"),
            "{what}: {output}"
        );
    }
    // A missing file is named before any connection is tried.
    let (status, output) = run_to_exit(
        &[
            "--nats",
            &url,
            "--no-persist",
            "--nats-tls-ca",
            "/nonexistent/ca.pem",
        ],
        &[],
    );
    assert!(!status.success());
    assert!(
        output.contains("--nats-tls-ca /nonexistent/ca.pem"),
        "{output}"
    );
}

/// `name`'s value in `addr`'s `/metrics` (0 when absent).
async fn metric(addr: std::net::SocketAddr, name: &str) -> f64 {
    let (status, text) =
        common::http_request(addr, Some(CONTROL), "GET", "/metrics", "text/plain", b"").await;
    assert_eq!(status, 200);
    text.lines()
        .find_map(|l| l.strip_prefix(name)?.trim().parse().ok())
        .unwrap_or(0.0)
}

/// Waits (30 s at most) until `addr` counts at least `n` relay messages refused for `reason`.
async fn refused_at_least(addr: std::net::SocketAddr, reason: &str, n: f64) {
    let name = format!("posecast_cluster_relay_refused_total{{reason=\"{reason}\"}}");
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        let seen = metric(addr, &name).await;
        if seen >= n {
            return;
        }
        assert!(Instant::now() < deadline, "{name} is {seen}, expected {n}");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// Scene `stage` with a walking avatar on `owner`, relayed by `relay`; a viewer on `relay`
/// that has had its first frames.
async fn staged(owner: &Posecast, relay: &Posecast) -> common::Ws {
    for json in [
        r#"{"op":"create_scene","scene":"stage"}"#,
        r#"{"op":"add_avatar","scene":"stage","asset":"avatar","avatar":"dancer","clip":"walk"}"#,
    ] {
        let (status, body) = post(owner.addr, json, None).await;
        assert_eq!(status, 200, "{json}: {body}");
    }
    let deadline = Instant::now() + Duration::from_secs(30);
    while listing(relay.addr).await.is_none_or(|(o, _)| o != "a") {
        assert!(
            Instant::now() < deadline,
            "the relay never learnt the owner"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let mut viewer = common::raw_at(relay.addr, Encoding::Binary, None).await;
    viewer
        .send(Message::Text(
            r#"{"type":"subscribe","scene":"stage"}"#.into(),
        ))
        .await
        .unwrap();
    frames(&mut viewer, 5).await;
    viewer
}

/// Reads until `n` binary frames came (30 s at most).
async fn frames(viewer: &mut common::Ws, n: usize) {
    let deadline = tokio::time::Instant::now() + Duration::from_secs(30);
    let mut seen = 0;
    while seen < n {
        match tokio::time::timeout_at(deadline, viewer.next()).await {
            Ok(Some(Ok(Message::Binary(_)))) => seen += 1,
            Ok(Some(Ok(_))) => {}
            other => panic!("{seen} of {n} frames, then {other:?}"),
        }
    }
}

/// Publishes a message on scene `stage`'s relay subject with these headers.
async fn forge(client: &async_nats::Client, headers: &[(&str, &str)], payload: &'static [u8]) {
    let mut map = async_nats::HeaderMap::new();
    for (k, v) in headers {
        map.insert(*k, *v);
    }
    client
        .publish_with_headers("posecast.scene.7374616765.relay", map, payload.into())
        .await
        .unwrap();
    client.flush().await.unwrap();
}

/// Issue 36's injections on an open NATS: `deleted` from a node that does not hold the lease,
/// `deleted` in the owner's name while the scene is still in the bucket, a frame with epoch
/// 2^63 in the owner's name and one from another node — each dropped and counted by the
/// relaying server, which keeps the scene and keeps streaming the owner's frames. A real
/// `delete_scene` still reaches it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn forged_relay_messages_are_dropped_and_counted() {
    let Some(nats) = Nats::start() else { return };
    let url = nats.url();
    let a = node(&url, "a", &[], &[]);
    let b = node(&url, "b", &[], &[]);
    let mut viewer = staged(&a, &b).await;
    let intruder = async_nats::connect(&url).await.unwrap();
    let huge = (1u64 << 63).to_string();
    forge(
        &intruder,
        &[
            ("Posecast-Kind", "deleted"),
            ("Posecast-Epoch", "1"),
            ("Posecast-Node", "mallory"),
        ],
        b"",
    )
    .await;
    forge(
        &intruder,
        &[
            ("Posecast-Kind", "deleted"),
            ("Posecast-Epoch", "1"),
            ("Posecast-Node", "a"),
        ],
        b"",
    )
    .await;
    forge(
        &intruder,
        &[
            ("Posecast-Kind", "frame"),
            ("Posecast-Epoch", &huge),
            ("Posecast-Node", "a"),
        ],
        b"\x02garbage",
    )
    .await;
    forge(
        &intruder,
        &[
            ("Posecast-Kind", "avatars"),
            ("Posecast-Epoch", "1"),
            ("Posecast-Node", "mallory"),
        ],
        b"[]",
    )
    .await;
    refused_at_least(b.addr, "not_owner", 2.0).await;
    refused_at_least(b.addr, "not_deleted", 1.0).await;
    refused_at_least(b.addr, "epoch", 1.0).await;
    // Nothing changed on b: the scene, its avatar and the owner's frames are all there.
    let (owner, avatars) = listing(b.addr).await.expect("b dropped the scene");
    assert_eq!(owner, "a");
    assert!(avatars.contains("dancer"), "{avatars:?}");
    frames(&mut viewer, 20).await;
    assert_eq!(
        metric(
            b.addr,
            "posecast_cluster_relay_refused_total{reason=\"signature\"}"
        )
        .await,
        0.0
    );

    // The owner's own deletion is believed.
    let (status, body) = post(a.addr, r#"{"op":"delete_scene","scene":"stage"}"#, None).await;
    assert_eq!(status, 200, "{body}");
    let deadline = Instant::now() + Duration::from_secs(30);
    while listing(b.addr).await.is_some() {
        assert!(Instant::now() < deadline, "b still lists the deleted scene");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// With `--cluster-secret` the servers' relay messages are signed: the cluster relays as
/// before, and a message in the owner's name with a plausible epoch but no MAC, or a MAC
/// under another secret, is dropped (`reason="signature"`).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn with_a_cluster_secret_unsigned_relay_messages_are_dropped() {
    let Some(nats) = Nats::start() else { return };
    let url = nats.url();
    let secret = [("POSECAST_CLUSTER_SECRET", "c1uster-secret-36")];
    let a = node(&url, "a", &[], &secret);
    let b = node(&url, "b", &[], &secret);
    let mut viewer = staged(&a, &b).await;
    let intruder = async_nats::connect(&url).await.unwrap();
    forge(
        &intruder,
        &[
            ("Posecast-Kind", "deleted"),
            ("Posecast-Epoch", "1"),
            ("Posecast-Node", "a"),
        ],
        b"",
    )
    .await;
    forge(
        &intruder,
        &[
            ("Posecast-Kind", "frame"),
            ("Posecast-Epoch", "1"),
            ("Posecast-Node", "a"),
            (
                "Posecast-Mac",
                "00112233445566778899aabbccddeeff00112233445566778899aabbccddeeff",
            ),
        ],
        b"\x02garbage",
    )
    .await;
    refused_at_least(b.addr, "signature", 2.0).await;
    assert!(listing(b.addr).await.is_some(), "b dropped the scene");
    frames(&mut viewer, 20).await;
    for server in [&a, &b] {
        assert!(!server.output().join("\n").contains("c1uster-secret-36"));
    }
}
