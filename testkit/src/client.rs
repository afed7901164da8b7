//! [`TestClient`]: the library's own [`Client`] (it derefs to one), connected for a test, with
//! waits on the pose stream and commands with typed results. [`ClientBuilder`] connects one.

use crate::KitError;
use crate::command::outcome;
use crate::pose::StreamedPose;
use posecast_client::net::{Client, ClientOptions};
use posecast_proto::Transform;
use posecast_proto::command::{Command, CommandResult};
use posecast_proto::msg::{AvatarId, Encoding, SceneId};
use std::time::Duration;
use tokio::time::Instant;

/// How often the waits look at the newest pose.
const POLL: Duration = Duration::from_millis(2);

/// How to connect a [`TestClient`]: binary frames, scene `default` unless scenes are named,
/// no reconnection (a dropped connection should fail the test, not be hidden).
///
/// ```
/// # #[tokio::main(flavor = "current_thread")]
/// # async fn main() -> Result<(), posecast_testkit::KitError> {
/// use posecast_proto::msg::Encoding;
/// let server = posecast_testkit::TestServer::builder().scene("lobby").start().await?;
/// let client = server
///     .client_builder()
///     .subscribe("lobby")
///     .encoding(Encoding::Json)
///     .connect()
///     .await?;
/// assert!(client.is_connected());
/// # server.stop().await; Ok(()) }
/// ```
#[derive(Debug, Clone)]
pub struct ClientBuilder {
    options: ClientOptions,
    named_scene: bool,
}

impl ClientBuilder {
    /// A client of the server at websocket URL `url` (e.g. a [`crate::TestServer`]'s
    /// [`ws_url`](posecast_server::startup::Server::ws_url)), with no token.
    ///
    /// ```
    /// # #[tokio::main(flavor = "current_thread")]
    /// # async fn main() -> Result<(), posecast_testkit::KitError> {
    /// let server = posecast_testkit::TestServer::start().await?;
    /// // Views are open by default: no token needed to watch.
    /// let viewer = posecast_testkit::ClientBuilder::new(server.ws_url()).connect().await?;
    /// viewer.first_pose("avatar", std::time::Duration::from_secs(10)).await?;
    /// # server.stop().await; Ok(()) }
    /// ```
    #[must_use]
    pub fn new(url: impl Into<String>) -> Self {
        let mut options = ClientOptions::new(url, "default");
        options.reconnect = false;
        options.name = "posecast-testkit".into();
        Self {
            options,
            named_scene: false,
        }
    }

    /// Subscribes to `scene` (repeatable); the first call replaces the default `default`.
    ///
    /// ```
    /// let builder = posecast_testkit::ClientBuilder::new("ws://127.0.0.1:1/ws")
    ///     .subscribe("a")
    ///     .subscribe("b");
    /// # let _ = builder;
    /// ```
    #[must_use]
    pub fn subscribe(mut self, scene: &str) -> Self {
        if !self.named_scene {
            self.options.subscriptions.clear();
            self.named_scene = true;
        }
        self.options
            .subscriptions
            .push((SceneId(scene.to_owned()), None));
        self
    }

    /// Binary (default: several times smaller, quantised within
    /// [`posecast_proto::quant::MAX_ERROR_DEGREES`]) or JSON frames.
    ///
    /// ```
    /// use posecast_proto::msg::Encoding;
    /// let builder = posecast_testkit::ClientBuilder::new("ws://127.0.0.1:1/ws").encoding(Encoding::Json);
    /// # let _ = builder;
    /// ```
    #[must_use]
    pub fn encoding(mut self, encoding: Encoding) -> Self {
        self.options.encoding = encoding;
        self
    }

    /// The token to say hello with (`None`: anonymous).
    ///
    /// ```
    /// let builder = posecast_testkit::ClientBuilder::new("ws://127.0.0.1:1/ws").token(Some("a-view-token"));
    /// # let _ = builder;
    /// ```
    #[must_use]
    pub fn token(mut self, token: Option<&str>) -> Self {
        self.options.token = token.map(str::to_owned);
        self
    }

    /// Any other [`ClientOptions`] (frame rate, avatar filters, reconnection, ping interval).
    ///
    /// ```
    /// let builder = posecast_testkit::ClientBuilder::new("ws://127.0.0.1:1/ws")
    ///     .options(|o| o.rate = Some(10.0));
    /// # let _ = builder;
    /// ```
    #[must_use]
    pub fn options(mut self, f: impl FnOnce(&mut ClientOptions)) -> Self {
        f(&mut self.options);
        self
    }

    /// Connects, says hello, subscribes, and waits (up to 10 s) for the welcome.
    ///
    /// A token the server does not know is no failure here: the server welcomes the client
    /// as anonymous and reports `unauthorized` right after (`stats().last_error`); its
    /// commands are then refused.
    ///
    /// # Errors
    /// [`KitError::Client`]: the connection failed, or the server refused the hello.
    ///
    /// ```
    /// # #[tokio::main(flavor = "current_thread")]
    /// # async fn main() -> Result<(), posecast_testkit::KitError> {
    /// use posecast_proto::command::Command;
    /// use posecast_proto::msg::{AvatarId, ErrorCode};
    /// let server = posecast_testkit::TestServer::start().await?;
    /// let stranger = server.client_builder().token(Some("not-a-configured-token")).connect().await?;
    /// let refused = stranger.command(Command::Pause { avatar: AvatarId("avatar".into()) }).await;
    /// assert_eq!(refused.unwrap_err().code(), Some(ErrorCode::Unauthorized));
    /// # server.stop().await; Ok(()) }
    /// ```
    pub async fn connect(self) -> Result<TestClient, KitError> {
        Ok(TestClient {
            client: Client::connect(self.options).await?,
        })
    }
}

/// A connected [`Client`] with the waits a test needs. Derefs to the [`Client`], so
/// `latest`, `avatar`, `stats`, `send`, … are there too; [`TestClient::command`] shadows
/// [`Client::command`] with typed results (the JSON one is `client.client().command`).
/// Dropping it closes the connection.
#[derive(Debug)]
pub struct TestClient {
    client: Client,
}

impl std::ops::Deref for TestClient {
    type Target = Client;
    fn deref(&self) -> &Client {
        &self.client
    }
}

impl TestClient {
    /// The underlying [`Client`].
    ///
    /// ```
    /// # #[tokio::main(flavor = "current_thread")]
    /// # async fn main() -> Result<(), posecast_testkit::KitError> {
    /// let server = posecast_testkit::TestServer::start().await?;
    /// let client = server.client().await?;
    /// assert!(client.client().tick_rate() > 0.0);
    /// # server.stop().await; Ok(()) }
    /// ```
    #[must_use]
    pub fn client(&self) -> &Client {
        &self.client
    }

    /// The underlying [`Client`], by value.
    ///
    /// ```
    /// # #[tokio::main(flavor = "current_thread")]
    /// # async fn main() -> Result<(), posecast_testkit::KitError> {
    /// let server = posecast_testkit::TestServer::start().await?;
    /// let client: posecast_client::net::Client = server.client().await?.into_inner();
    /// assert!(client.is_connected());
    /// # server.stop().await; Ok(()) }
    /// ```
    #[must_use]
    pub fn into_inner(self) -> Client {
        self.client
    }

    /// Sends a command over this client's websocket and waits (up to 10 s) for its answer,
    /// read as the [`CommandResult`] variant the command answers with (see
    /// [`crate::typed_result`]).
    ///
    /// # Errors
    /// [`KitError::Refused`] with the server's typed error (match on [`KitError::code`]);
    /// [`KitError::Client`] for a timeout or a closed connection.
    ///
    /// ```
    /// # #[tokio::main(flavor = "current_thread")]
    /// # async fn main() -> Result<(), posecast_testkit::KitError> {
    /// use posecast_proto::command::{Command, CommandResult};
    /// use posecast_proto::msg::{AvatarId, ErrorCode};
    /// let server = posecast_testkit::TestServer::start().await?;
    /// let client = server.client().await?;
    /// let CommandResult::Avatar(state) = client.command(Command::GetAvatar { avatar: AvatarId("avatar".into()) }).await? else {
    ///     panic!("get_avatar answers with the avatar's state");
    /// };
    /// assert_eq!(state.clip.as_deref(), Some("idle"));
    /// let refused = client.command(Command::Pause { avatar: AvatarId("nobody".into()) }).await;
    /// assert_eq!(refused.unwrap_err().code(), Some(ErrorCode::UnknownAvatar));
    /// # server.stop().await; Ok(()) }
    /// ```
    pub async fn command(&self, command: Command) -> Result<CommandResult, KitError> {
        let answer = self.client.command(command.clone()).await;
        outcome(&command, answer)
    }

    /// The newest pose of `avatar` this client holds, if any.
    ///
    /// ```
    /// # #[tokio::main(flavor = "current_thread")]
    /// # async fn main() -> Result<(), posecast_testkit::KitError> {
    /// let server = posecast_testkit::TestServer::start().await?;
    /// let client = server.client().await?;
    /// client.first_pose("avatar", std::time::Duration::from_secs(10)).await?;
    /// assert!(client.pose("avatar").is_some());
    /// assert!(client.pose("nobody").is_none());
    /// # server.stop().await; Ok(()) }
    /// ```
    #[must_use]
    pub fn pose(&self, avatar: &str) -> Option<StreamedPose> {
        let id = AvatarId(avatar.to_owned());
        let view = self.client.avatar(&id)?;
        Some(StreamedPose {
            sample: view.latest?,
            skeleton: view.skeleton,
            avatar: id,
        })
    }

    /// Waits until the newest streamed pose of `avatar` satisfies `condition`, for at most
    /// `timeout`, and returns that pose. Each new pose is checked once, as it becomes the
    /// newest (a pose that came and went between two looks, 2 ms apart, is not seen).
    ///
    /// # Errors
    /// [`KitError::Timeout`], naming the avatar and writing out the last pose seen.
    ///
    /// ```
    /// # #[tokio::main(flavor = "current_thread")]
    /// # async fn main() -> Result<(), posecast_testkit::KitError> {
    /// use std::time::Duration;
    /// let server = posecast_testkit::TestServer::start().await?;
    /// let client = server.client().await?;
    /// let first = client.first_pose("avatar", Duration::from_secs(10)).await?;
    /// // The clip plays: later ticks come.
    /// let later = client
    ///     .wait_for_pose("avatar", Duration::from_secs(10), |p| p.seq() > first.seq() + 2)
    ///     .await?;
    /// assert!(later.seq() > first.seq() + 2);
    /// // A condition that never holds fails with the avatar and its last pose.
    /// let err = client
    ///     .wait_for_pose("avatar", Duration::from_millis(100), |_| false)
    ///     .await
    ///     .unwrap_err();
    /// assert!(err.to_string().contains("avatar `avatar`"), "{err}");
    /// assert!(err.to_string().contains("l_elbow ["), "{err}");
    /// # server.stop().await; Ok(()) }
    /// ```
    pub async fn wait_for_pose(
        &self,
        avatar: &str,
        timeout: Duration,
        condition: impl FnMut(&StreamedPose) -> bool,
    ) -> Result<StreamedPose, KitError> {
        self.wait_described(
            avatar,
            timeout,
            "a pose that satisfies the condition",
            condition,
        )
        .await
    }

    async fn wait_described(
        &self,
        avatar: &str,
        timeout: Duration,
        what: &str,
        mut condition: impl FnMut(&StreamedPose) -> bool,
    ) -> Result<StreamedPose, KitError> {
        let deadline = Instant::now() + timeout;
        let mut last: Option<StreamedPose> = None;
        loop {
            if let Some(pose) = self.pose(avatar)
                && last.as_ref().is_none_or(|l| l.sample != pose.sample)
            {
                if condition(&pose) {
                    return Ok(pose);
                }
                last = Some(pose);
            }
            if Instant::now() >= deadline {
                return Err(KitError::Timeout {
                    avatar: avatar.to_owned(),
                    what: what.to_owned(),
                    waited: timeout,
                    last: last.map_or_else(|| "none".to_owned(), |p| p.describe()),
                });
            }
            tokio::time::sleep(POLL).await;
        }
    }

    /// Waits (at most `timeout`) for the first pose of `avatar`.
    ///
    /// # Errors
    /// [`KitError::Timeout`] (the avatar is not in a subscribed scene, or nothing streams).
    ///
    /// ```
    /// # #[tokio::main(flavor = "current_thread")]
    /// # async fn main() -> Result<(), posecast_testkit::KitError> {
    /// let server = posecast_testkit::TestServer::start().await?;
    /// let client = server.client().await?;
    /// let pose = client.first_pose("avatar", std::time::Duration::from_secs(10)).await?;
    /// assert_eq!(pose.locals().len(), pose.skeleton.len());
    /// let err = client.first_pose("nobody", std::time::Duration::from_millis(50)).await.unwrap_err();
    /// assert!(err.to_string().contains("last pose seen: none"), "{err}");
    /// # server.stop().await; Ok(()) }
    /// ```
    pub async fn first_pose(
        &self,
        avatar: &str,
        timeout: Duration,
    ) -> Result<StreamedPose, KitError> {
        self.wait_described(avatar, timeout, "its first pose", |_| true)
            .await
    }

    /// A pose of `avatar` computed after every command this client has had acknowledged: waits
    /// for a first pose, asks the server for the avatar's state (a second round trip, whose
    /// answer comes after every frame computed before the earlier acknowledgements), then
    /// waits for a newer tick than the newest held by then. Within `timeout` in all.
    ///
    /// # Errors
    /// [`KitError::Timeout`]; [`KitError::Refused`] (`unknown_avatar`) for an avatar the
    /// server does not have.
    ///
    /// ```
    /// # #[tokio::main(flavor = "current_thread")]
    /// # async fn main() -> Result<(), posecast_testkit::KitError> {
    /// use posecast_proto::command::Command;
    /// use posecast_proto::msg::AvatarId;
    /// let server = posecast_testkit::TestServer::start().await?;
    /// let client = server.client().await?;
    /// let avatar = AvatarId("avatar".into());
    /// client.command(Command::Pause { avatar: avatar.clone() }).await?;
    /// client.command(Command::Seek { avatar, time: 0.5 }).await?;
    /// let pose = client.fresh_pose("avatar", std::time::Duration::from_secs(10)).await?;
    /// pose.assert_near(&server.clip_pose("avatar", "idle", 0.5)?, 0.01)?;
    /// # server.stop().await; Ok(()) }
    /// ```
    pub async fn fresh_pose(
        &self,
        avatar: &str,
        timeout: Duration,
    ) -> Result<StreamedPose, KitError> {
        let deadline = Instant::now() + timeout;
        self.first_pose(avatar, timeout).await?;
        self.command(Command::GetAvatar {
            avatar: AvatarId(avatar.to_owned()),
        })
        .await?;
        let after = self.pose(avatar).map_or(0, |p| p.seq());
        let left = deadline.saturating_duration_since(Instant::now());
        self.wait_described(avatar, left, &format!("a tick after {after}"), |p| {
            p.seq() > after
        })
        .await
    }

    /// Waits until the streamed pose of `avatar` is within `tolerance_degrees` of `expected`
    /// on every joint (see [`StreamedPose::assert_near`]); for effects that land a tick or two
    /// after their command (a live pose, a joint rotation).
    ///
    /// # Errors
    /// [`KitError::Timeout`] naming the avatar, the worst joint of the last pose seen and its
    /// angle, and that pose.
    ///
    /// ```
    /// # #[tokio::main(flavor = "current_thread")]
    /// # async fn main() -> Result<(), posecast_testkit::KitError> {
    /// use posecast_proto::command::Command;
    /// use posecast_proto::msg::AvatarId;
    /// use std::time::Duration;
    /// let server = posecast_testkit::TestServer::start().await?;
    /// let client = server.client().await?;
    /// let avatar = AvatarId("avatar".into());
    /// client.command(Command::Pause { avatar: avatar.clone() }).await?;
    /// let q = glam::Quat::from_rotation_z(0.7);
    /// client
    ///     .command(Command::SetJointRotation { avatar, joint: "l_elbow".into(), rotation: q.to_array() })
    ///     .await?;
    /// let mut expected = client.pose("avatar").unwrap().locals().to_vec();
    /// let elbow = server.joint("avatar", "l_elbow")?;
    /// expected[elbow].rotation = q;
    /// client.wait_until_near("avatar", &expected, 0.01, Duration::from_secs(10)).await?;
    /// // Far from any pose it takes: the error names the worst joint.
    /// expected[elbow].rotation = glam::Quat::IDENTITY;
    /// let err = client.wait_until_near("avatar", &expected, 0.01, Duration::from_millis(100)).await.unwrap_err();
    /// assert!(err.to_string().contains("worst joint `l_elbow`"), "{err}");
    /// # server.stop().await; Ok(()) }
    /// ```
    pub async fn wait_until_near(
        &self,
        avatar: &str,
        expected: &[Transform],
        tolerance_degrees: f64,
        timeout: Duration,
    ) -> Result<StreamedPose, KitError> {
        let mut closest = String::from("no pose compared");
        let found = self
            .wait_described(avatar, timeout, "", |p| match p.compare(expected) {
                Ok(d) if d.degrees <= tolerance_degrees => true,
                Ok(d) => {
                    closest = format!("worst joint `{}` {:.4}° off", d.joint_name, d.degrees);
                    false
                }
                Err(e) => {
                    closest = e.to_string();
                    false
                }
            })
            .await;
        found.map_err(|e| match e {
            KitError::Timeout {
                avatar,
                waited,
                last,
                ..
            } => KitError::Timeout {
                avatar,
                what: format!(
                    "every joint within {tolerance_degrees}° of the expected pose; last: {closest}"
                ),
                waited,
                last,
            },
            other => other,
        })
    }

    /// Every distinct pose of `avatar` streamed after tick `after`, collected for `duration`
    /// (the newest pose, looked at every 2 ms: at tick rates up to a few hundred Hz, every
    /// tick).
    ///
    /// ```
    /// # #[tokio::main(flavor = "current_thread")]
    /// # async fn main() -> Result<(), posecast_testkit::KitError> {
    /// use std::time::Duration;
    /// let server = posecast_testkit::TestServer::builder().tick_rate(30.0).start().await?;
    /// let client = server.client().await?;
    /// let first = client.first_pose("avatar", Duration::from_secs(10)).await?;
    /// let poses = client.collect_poses("avatar", first.seq(), Duration::from_millis(300)).await;
    /// assert!(poses.windows(2).all(|w| w[0].seq() < w[1].seq()));
    /// # server.stop().await; Ok(()) }
    /// ```
    pub async fn collect_poses(
        &self,
        avatar: &str,
        after: u64,
        duration: Duration,
    ) -> Vec<StreamedPose> {
        let mut out: Vec<StreamedPose> = Vec::new();
        let end = Instant::now() + duration;
        while Instant::now() < end {
            if let Some(p) = self.pose(avatar)
                && p.seq() > after
                && out.last().is_none_or(|l| l.seq() != p.seq())
            {
                out.push(p);
            }
            tokio::time::sleep(POLL).await;
        }
        out
    }
}
