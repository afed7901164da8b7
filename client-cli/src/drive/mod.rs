//! `drive`: streams a BVH clip to an avatar as a live source, the way a motion-capture system
//! would: the file is imported and normalised here by the server's own pipeline, uploaded as
//! the source rig (or an existing one reused), then sampled at wall-clock time and sent as
//! binary poses that the server retargets onto the avatar in world space.
//!
//! - [`source`]: the local normalised rig and clip, and the joint order of binary poses.
//! - [`asset`]: the source rig on the server (upload or reuse).

mod asset;
mod source;

use anyhow::{Context, bail};
use clap::{Args, ValueEnum};
use posecast_client::net::Driver;
use posecast_proto::command::OnRelease;
use posecast_proto::live::MAX_RATE_HZ;
use posecast_proto::msg::{AvatarId, ProtocolError};
use source::{ClipSource, JointMap};
use std::path::PathBuf;
use std::time::{Duration, Instant};

#[derive(Debug, Args)]
pub struct DriveArgs {
    /// The BVH file to stream.
    #[arg(long, env = "POSECAST_DRIVE_BVH")]
    bvh: PathBuf,
    /// The avatar to drive.
    #[arg(long, env = "POSECAST_DRIVE_AVATAR", default_value = "avatar")]
    avatar: String,
    /// The server's websocket URL (uploads go to the same host over HTTP).
    #[arg(long, env = "POSECAST_URL", default_value = "ws://127.0.0.1:8080/ws")]
    url: String,
    /// A control token that may command the avatar (and, to upload the rig, an unlimited one).
    #[arg(long, env = "POSECAST_TOKEN")]
    token: Option<String>,
    /// The source rig's asset name on the server (default: the file stem, made a valid id).
    #[arg(long, env = "POSECAST_DRIVE_SOURCE_NAME")]
    source_name: Option<String>,
    /// Poses per second (the server accepts at most 120).
    #[arg(long, env = "POSECAST_DRIVE_RATE", default_value_t = 60.0)]
    rate: f32,
    /// Playback speed (clip seconds per wall-clock second).
    #[arg(long, env = "POSECAST_DRIVE_SPEED", default_value_t = 1.0)]
    speed: f32,
    /// Play the clip once and stop at its end (default: loop).
    #[arg(long, env = "POSECAST_DRIVE_ONCE")]
    once: bool,
    /// Stop after this many seconds (default: until Ctrl-C, or the end with --once).
    #[arg(long, env = "POSECAST_DRIVE_SECONDS")]
    seconds: Option<f32>,
    /// What the avatar does when this driver stops: play its clip again, or hold the last pose.
    #[arg(long, env = "POSECAST_DRIVE_ON_RELEASE", value_enum, default_value_t = Release::Clip)]
    on_release: Release,
}

/// `--on-release`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum Release {
    Clip,
    Hold,
}

impl From<Release> for OnRelease {
    fn from(r: Release) -> Self {
        match r {
            Release::Clip => Self::Clip,
            Release::Hold => Self::Hold,
        }
    }
}

impl DriveArgs {
    fn check(&self) -> anyhow::Result<()> {
        if !(self.rate > 0.0 && self.rate <= MAX_RATE_HZ) {
            bail!("--rate must be above 0 and at most {MAX_RATE_HZ} (the server's limit)");
        }
        if !(self.speed.is_finite() && self.speed > 0.0) {
            bail!("--speed must be a positive number");
        }
        if self.seconds.is_some_and(|s| !(s.is_finite() && s >= 0.0)) {
            bail!("--seconds must be a number of seconds");
        }
        Ok(())
    }
}

/// Why streaming stopped.
enum Stop {
    Interrupted,
    ClipEnded,
    TimeUp,
}

pub async fn run(args: DriveArgs) -> anyhow::Result<()> {
    args.check()?;
    if args.token.is_none() {
        bail!(
            "driving needs a control token: --token or POSECAST_TOKEN (the server prints one at \
             start, or takes --control-token)"
        );
    }
    let bytes = tokio::fs::read(&args.bvh)
        .await
        .with_context(|| format!("cannot read {}", args.bvh.display()))?;
    let mut source = ClipSource::from_bvh(&args.bvh, &bytes)?;
    let skeleton = source.rig().skeleton();
    println!(
        "{}: {} joints, a {:.2} s clip; normalised: {}",
        args.bvh.display(),
        skeleton.len(),
        source.duration(),
        source.rig().pipeline.join("; ")
    );
    let name = match &args.source_name {
        Some(n) => n.clone(),
        None => asset::name_from_stem(
            &args
                .bvh
                .file_stem()
                .map(|s| s.to_string_lossy().into_owned())
                .unwrap_or_default(),
        ),
    };
    let driver = Driver::connect(&args.url, args.token.clone())
        .await
        .with_context(|| format!("cannot connect to {}", args.url))?;
    let outcome = asset::ensure(
        &driver,
        &args.url,
        args.token.as_deref(),
        &name,
        &bytes,
        skeleton.len(),
    )
    .await?;
    match outcome {
        asset::Outcome::Uploaded => println!("uploaded the source rig as asset {name}"),
        asset::Outcome::Reused => println!("reusing the server's asset {name} as the source rig"),
    }
    let avatar = AvatarId(args.avatar.clone());
    let info = driver
        .drive(&avatar, Some(&name), Some(args.on_release.into()))
        .await
        .with_context(|| format!("cannot drive avatar {avatar}"))?;
    let map = JointMap::new(skeleton.names(), &info.joints)?;
    let rate = args.rate.min(info.max_rate_hz);
    println!(
        "driving avatar {avatar} (#{}) from {} ({} joints, root {}) at {rate} Hz, speed {}{}; \
         the server releases after {} s of silence",
        info.avatar_num,
        info.source,
        info.joints.len(),
        info.root,
        args.speed,
        if args.once { ", once" } else { ", looping" },
        info.timeout
    );
    let stream = Stream {
        driver: &driver,
        map: &map,
        avatar_num: info.avatar_num,
        rate,
        speed: args.speed,
        looping: !args.once,
        seconds: args.seconds,
    };
    let (stop, sent) = stream.run(&mut source).await?;
    let why = match stop {
        Stop::Interrupted => "interrupted",
        Stop::ClipEnded => "end of the clip",
        Stop::TimeUp => "time up",
    };
    // `hold` means "keep the last pose once I am gone": closing ends the drive that way, while
    // `release_drive` would also end the held pose.
    match args.on_release {
        Release::Clip => {
            driver
                .release(&avatar)
                .await
                .with_context(|| format!("cannot release avatar {avatar}"))?;
            println!("{why}: sent {sent} poses; released {avatar}, it plays its clip again");
        }
        Release::Hold => println!("{why}: sent {sent} poses; {avatar} holds the last pose"),
    }
    driver.close().await;
    Ok(())
}

/// The pose loop's settings.
struct Stream<'a> {
    driver: &'a Driver,
    map: &'a JointMap,
    avatar_num: u32,
    rate: f32,
    speed: f32,
    looping: bool,
    seconds: Option<f32>,
}

impl Stream<'_> {
    /// Sends a pose every `1/rate` s, sampled at wall-clock time × speed, until Ctrl-C, the
    /// clip's end (not looping) or `seconds`; prints the server's errors as they come. Returns
    /// why it stopped and how many poses it sent.
    async fn run(&self, source: &mut ClipSource) -> anyhow::Result<(Stop, u64)> {
        let start = Instant::now();
        let mut ticker = tokio::time::interval(Duration::from_secs_f32(1.0 / self.rate));
        // Never catch up in a burst: the server refuses more than its rate.
        ticker.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        let ctrl_c = tokio::signal::ctrl_c();
        tokio::pin!(ctrl_c);
        let mut sent = 0u64;
        loop {
            tokio::select! {
                _ = ticker.tick() => {}
                // An hour is "until one comes"; the wait is cancelled each tick.
                Some(e) = self.driver.next_error(Duration::from_secs(3600)) => {
                    report(&e);
                    continue;
                }
                signal = &mut ctrl_c => {
                    signal.context("cannot listen for Ctrl-C")?;
                    return Ok((Stop::Interrupted, sent));
                }
            }
            let elapsed = start.elapsed().as_secs_f32();
            let played = elapsed * self.speed;
            let time = source.clip_time(played, self.looping);
            let (locals, root) = source.sample(time);
            let time_us = u64::try_from(start.elapsed().as_micros()).unwrap_or(u64::MAX);
            let pose = self.map.pose(self.avatar_num, locals, root, time_us.max(1));
            self.driver
                .send_binary_pose(&pose)
                .await
                .context("the connection to the server failed")?;
            sent += 1;
            if !self.looping && played >= source.duration() {
                return Ok((Stop::ClipEnded, sent));
            }
            if self.seconds.is_some_and(|s| elapsed >= s) {
                return Ok((Stop::TimeUp, sent));
            }
        }
    }
}

fn report(e: &ProtocolError) {
    // The code as on the wire (`rate_limited`), not its Rust name.
    let code = serde_json::to_value(e.code)
        .ok()
        .and_then(|v| v.as_str().map(str::to_owned))
        .unwrap_or_else(|| format!("{:?}", e.code));
    match e.retry_after_ms {
        Some(ms) => eprintln!("server error {code}: {} (retry after {ms} ms)", e.message),
        None => eprintln!("server error {code}: {}", e.message),
    }
}
