//! [`TestServer`]: a posecast server in this process on an ephemeral port, started in one call
//! by [`TestServerBuilder`], stopped by [`TestServer::stop`] or — when a test panics — by
//! dropping it.

use crate::KitError;
use crate::client::{ClientBuilder, TestClient};
use crate::command::op;
use crate::pose::sample_clip;
use posecast_client::net::Driver;
use posecast_proto::Transform;
use posecast_proto::command::{Command, CommandResult};
use posecast_proto::msg::{AvatarId, ProtocolError, SceneId};
use posecast_server::auth::{AccessConfig, Role, Secret, TokenRule};
use posecast_server::config::Config;
use posecast_server::rig::Rig;
use posecast_server::startup::Server;
use std::path::PathBuf;
use std::sync::Arc;

/// The unlimited control token a [`TestServer`] accepts unless
/// [`TestServerBuilder::control_token`] chose another.
pub const DEFAULT_CONTROL_TOKEN: &str = "posecast-testkit-control";

/// How to start a [`TestServer`]: the built-in avatar in scene `default` playing `idle` at
/// 60 Hz, open views, one unlimited control token ([`DEFAULT_CONTROL_TOKEN`]), everything in
/// memory (no data folder), on `127.0.0.1` at a port the system picks.
///
/// ```
/// # #[tokio::main(flavor = "current_thread")]
/// # async fn main() -> Result<(), posecast_testkit::KitError> {
/// use posecast_testkit::TestServer;
/// let server = TestServer::builder()
///     .tick_rate(30.0)
///     .scene("stage")
///     .avatar("stage", "dancer", "avatar", Some("wave"))
///     .start()
///     .await?;
/// let client = server.client_builder().subscribe("stage").connect().await?;
/// client.first_pose("dancer", std::time::Duration::from_secs(10)).await?;
/// # server.stop().await; Ok(()) }
/// ```
#[derive(Debug, Clone)]
pub struct TestServerBuilder {
    config: Config,
    control_token: String,
    tokens: Vec<TokenRule>,
    open_view: bool,
    /// Access rules given whole ([`TestServerBuilder::access`]), replacing the others.
    access: Option<AccessConfig>,
    setup: Vec<Command>,
}

impl Default for TestServerBuilder {
    fn default() -> Self {
        Self {
            config: Config {
                listen: ([127, 0, 0, 1], 0).into(),
                ..Config::default()
            },
            control_token: DEFAULT_CONTROL_TOKEN.to_owned(),
            tokens: Vec::new(),
            open_view: true,
            access: None,
            setup: Vec::new(),
        }
    }
}

impl TestServerBuilder {
    /// Pose frames per second of every scene, in `(0, 1000]` (default 60).
    ///
    /// ```
    /// # #[tokio::main(flavor = "current_thread")]
    /// # async fn main() -> Result<(), posecast_testkit::KitError> {
    /// let server = posecast_testkit::TestServer::builder().tick_rate(20.0).start().await?;
    /// assert_eq!(server.client().await?.tick_rate(), 20.0);
    /// # server.stop().await; Ok(()) }
    /// ```
    #[must_use]
    pub fn tick_rate(mut self, hz: f32) -> Self {
        self.config.tick_rate = hz;
        self
    }

    /// Loads every asset (`.glb/.vrm/.gltf/.bvh/.skel`) of folder `dir` at start, each by its
    /// file stem (repeatable; like `posecast --assets`). [`TestServer::start`] returns once
    /// they are loaded.
    ///
    /// ```
    /// # #[tokio::main(flavor = "current_thread")]
    /// # async fn main() -> Result<(), posecast_testkit::KitError> {
    /// // The repository's own assets folder holds the built-in avatar as `avatar.glb`.
    /// let assets = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../assets");
    /// let server = posecast_testkit::TestServer::builder()
    ///     .builtin(false)
    ///     .assets(assets)
    ///     .scene("s")
    ///     .avatar("s", "loaded", "avatar", Some("walk"))
    ///     .start()
    ///     .await?;
    /// assert!(server.rig("avatar").is_ok());
    /// # server.stop().await; Ok(()) }
    /// ```
    #[must_use]
    pub fn assets(mut self, dir: impl Into<PathBuf>) -> Self {
        self.config.asset_dirs.push(dir.into());
        self
    }

    /// Whether to load the built-in avatar into scene `default` playing `idle` (default yes).
    ///
    /// ```
    /// # #[tokio::main(flavor = "current_thread")]
    /// # async fn main() -> Result<(), posecast_testkit::KitError> {
    /// let server = posecast_testkit::TestServer::builder().builtin(false).start().await?;
    /// assert!(server.rig("avatar").is_err());
    /// # server.stop().await; Ok(()) }
    /// ```
    #[must_use]
    pub fn builtin(mut self, builtin: bool) -> Self {
        self.config.builtin = builtin;
        self
    }

    /// Creates the empty scene `scene` at start (after the assets are loaded).
    ///
    /// ```
    /// # #[tokio::main(flavor = "current_thread")]
    /// # async fn main() -> Result<(), posecast_testkit::KitError> {
    /// let server = posecast_testkit::TestServer::builder().scene("empty").start().await?;
    /// assert!(server.state.world.scene(&posecast_proto::msg::SceneId("empty".into())).is_ok());
    /// # server.stop().await; Ok(()) }
    /// ```
    #[must_use]
    pub fn scene(self, scene: &str) -> Self {
        self.setup(Command::CreateScene {
            scene: SceneId(scene.to_owned()),
        })
    }

    /// Adds avatar `avatar` of the loaded rig `asset` to `scene` at start, playing `clip` if
    /// given (after the scenes and avatars named before it).
    ///
    /// ```
    /// # #[tokio::main(flavor = "current_thread")]
    /// # async fn main() -> Result<(), posecast_testkit::KitError> {
    /// let server = posecast_testkit::TestServer::builder()
    ///     .avatar("default", "second", "avatar", None)
    ///     .start()
    ///     .await?;
    /// assert!(server.state.world.find_avatar(&posecast_proto::msg::AvatarId("second".into())).is_ok());
    /// # server.stop().await; Ok(()) }
    /// ```
    #[must_use]
    pub fn avatar(self, scene: &str, avatar: &str, asset: &str, clip: Option<&str>) -> Self {
        self.setup(Command::AddAvatar {
            scene: SceneId(scene.to_owned()),
            asset: asset.to_owned(),
            avatar: Some(AvatarId(avatar.to_owned())),
            clip: clip.map(str::to_owned),
            position: None,
            rotation: None,
        })
    }

    /// Runs any command at start, in order with [`TestServerBuilder::scene`] and
    /// [`TestServerBuilder::avatar`] (a `play`, a `place_avatar`, …). A refused one fails the
    /// start with [`KitError::Setup`].
    ///
    /// ```
    /// # #[tokio::main(flavor = "current_thread")]
    /// # async fn main() -> Result<(), posecast_testkit::KitError> {
    /// use posecast_proto::command::Command;
    /// use posecast_proto::msg::{AvatarId, ErrorCode};
    /// let refused = posecast_testkit::TestServer::builder()
    ///     .setup(Command::Pause { avatar: AvatarId("nobody".into()) })
    ///     .start()
    ///     .await;
    /// assert_eq!(refused.unwrap_err().code(), Some(ErrorCode::UnknownAvatar));
    /// # Ok(()) }
    /// ```
    #[must_use]
    pub fn setup(mut self, command: Command) -> Self {
        self.setup.push(command);
        self
    }

    /// The unlimited control token the kit's clients and drivers use (at least 8
    /// characters; default [`DEFAULT_CONTROL_TOKEN`]).
    ///
    /// ```
    /// # #[tokio::main(flavor = "current_thread")]
    /// # async fn main() -> Result<(), posecast_testkit::KitError> {
    /// let server = posecast_testkit::TestServer::builder().control_token("my-own-secret").start().await?;
    /// assert_eq!(server.control_token(), "my-own-secret");
    /// # server.stop().await; Ok(()) }
    /// ```
    #[must_use]
    pub fn control_token(mut self, token: &str) -> Self {
        token.clone_into(&mut self.control_token);
        self
    }

    /// Accepts another token too: a view token, or one limited to some scenes or avatars
    /// (see [`TokenRule`]).
    ///
    /// ```
    /// # #[tokio::main(flavor = "current_thread")]
    /// # async fn main() -> Result<(), posecast_testkit::KitError> {
    /// use posecast_proto::command::Command;
    /// use posecast_proto::msg::{AvatarId, ErrorCode};
    /// use posecast_server::auth::{Role, Secret, TokenRule};
    /// let server = posecast_testkit::TestServer::builder()
    ///     .token(TokenRule::new("watcher", Secret::new("watch-only-token"), Role::View))
    ///     .start()
    ///     .await?;
    /// let viewer = server.client_builder().token(Some("watch-only-token")).connect().await?;
    /// let refused = viewer.command(Command::Pause { avatar: AvatarId("avatar".into()) }).await;
    /// assert_eq!(refused.unwrap_err().code(), Some(ErrorCode::Forbidden));
    /// # server.stop().await; Ok(()) }
    /// ```
    #[must_use]
    pub fn token(mut self, rule: TokenRule) -> Self {
        self.tokens.push(rule);
        self
    }

    /// Whether anyone may watch without a token (default yes).
    ///
    /// ```
    /// # #[tokio::main(flavor = "current_thread")]
    /// # async fn main() -> Result<(), posecast_testkit::KitError> {
    /// let server = posecast_testkit::TestServer::builder().open_view(false).start().await?;
    /// let anonymous = posecast_testkit::ClientBuilder::new(server.ws_url()).connect().await?;
    /// let watched = anonymous.first_pose("avatar", std::time::Duration::from_millis(300)).await;
    /// assert!(watched.is_err(), "an anonymous client saw a pose");
    /// let error = anonymous.stats().last_error.map(|e| e.code);
    /// assert_eq!(error, Some(posecast_proto::msg::ErrorCode::Unauthorized));
    /// # server.stop().await; Ok(()) }
    /// ```
    #[must_use]
    pub fn open_view(mut self, open: bool) -> Self {
        self.open_view = open;
        self
    }

    /// Uses exactly these access rules, instead of [`TestServerBuilder::token`],
    /// [`TestServerBuilder::open_view`] and the kit's own control token: to test a server
    /// with no control token at all, or your own token file. The kit's clients and drivers
    /// still present [`TestServerBuilder::control_token`]; give it one of these tokens.
    ///
    /// ```
    /// # #[tokio::main(flavor = "current_thread")]
    /// # async fn main() -> Result<(), posecast_testkit::KitError> {
    /// use posecast_proto::command::Command;
    /// use posecast_proto::msg::{AvatarId, ErrorCode};
    /// use posecast_server::auth::AccessConfig;
    /// // Open views and no control token: nobody may command.
    /// let server = posecast_testkit::TestServer::builder().access(AccessConfig::default()).start().await?;
    /// let client = server.client().await?;
    /// let refused = client.command(Command::Pause { avatar: AvatarId("avatar".into()) }).await;
    /// assert_eq!(refused.unwrap_err().code(), Some(ErrorCode::Unauthorized));
    /// # server.stop().await; Ok(()) }
    /// ```
    #[must_use]
    pub fn access(mut self, access: AccessConfig) -> Self {
        self.access = Some(access);
        self
    }

    /// Keeps scenes and uploads in the data folder `dir` (default: memory only), so a test
    /// can restart a server on it.
    ///
    /// ```
    /// # #[tokio::main(flavor = "current_thread")]
    /// # async fn main() -> Result<(), posecast_testkit::KitError> {
    /// let dir = std::env::temp_dir().join(format!("posecast-testkit-doc-{}", std::process::id()));
    /// let server = posecast_testkit::TestServer::builder().data_dir(&dir).start().await?;
    /// server.stop().await;
    /// assert!(dir.join("scenes").is_dir());
    /// std::fs::remove_dir_all(&dir).ok();
    /// # Ok(()) }
    /// ```
    #[must_use]
    pub fn data_dir(mut self, dir: impl Into<PathBuf>) -> Self {
        self.config.data_dir = Some(dir.into());
        self
    }

    /// Changes anything else of the server's [`Config`] (live-drive timeout, quotas, network
    /// limits…). The access rules and listen address set here are replaced by the builder's.
    ///
    /// ```
    /// # #[tokio::main(flavor = "current_thread")]
    /// # async fn main() -> Result<(), posecast_testkit::KitError> {
    /// let server = posecast_testkit::TestServer::builder()
    ///     .configure(|c| c.drive_timeout = std::time::Duration::from_millis(500))
    ///     .start()
    ///     .await?;
    /// assert_eq!(server.state.config.drive_timeout.as_millis(), 500);
    /// # server.stop().await; Ok(()) }
    /// ```
    #[must_use]
    pub fn configure(mut self, f: impl FnOnce(&mut Config)) -> Self {
        f(&mut self.config);
        self
    }

    /// Starts the server, waits until its assets are loaded, runs the set-up commands, and
    /// returns it listening.
    ///
    /// # Errors
    /// [`KitError::Start`] (a tick rate out of range, a short control token, a data folder it
    /// cannot write, an asset folder that failed to load); [`KitError::Setup`] for a refused
    /// set-up command. The half-started server is stopped.
    ///
    /// ```
    /// # #[tokio::main(flavor = "current_thread")]
    /// # async fn main() {
    /// let bad = posecast_testkit::TestServer::builder().tick_rate(0.0).start().await;
    /// assert!(bad.unwrap_err().to_string().contains("tick rate"));
    /// # }
    /// ```
    pub async fn start(self) -> Result<TestServer, KitError> {
        let mut config = self.config;
        let hz = config.tick_rate;
        if !(hz.is_finite() && hz > 0.0 && hz <= 1000.0) {
            return Err(KitError::Start(format!(
                "tick rate {hz} Hz is not in (0, 1000]"
            )));
        }
        config.access = match self.access {
            Some(access) => access,
            None => {
                let mut access = AccessConfig {
                    open_view: self.open_view,
                    tokens: Vec::new(),
                    mint: None,
                };
                let control = TokenRule::new(
                    "posecast-testkit",
                    Secret::new(self.control_token.clone()),
                    Role::Control,
                );
                for rule in std::iter::once(control).chain(self.tokens) {
                    access
                        .add(rule)
                        .map_err(|e| KitError::Start(e.to_string()))?;
                }
                access
            }
        };
        config.listen = ([127, 0, 0, 1], 0).into();
        let server = Server::start(config)
            .await
            .map_err(|e| KitError::Start(e.to_string()))?;
        let server = TestServer {
            server: Some(server),
            control_token: self.control_token,
        };
        server
            .ready()
            .await
            .map_err(|e| KitError::Start(e.to_string()))?;
        for command in &self.setup {
            posecast_server::control::execute_durable(&server.state, command)
                .await
                .map_err(|e| KitError::Setup {
                    op: op(command),
                    error: ProtocolError::from(e),
                })?;
        }
        Ok(server)
    }
}

/// A posecast server running in this process, on `127.0.0.1` at a port the system chose.
/// Derefs to the library's [`Server`] (`addr`, `state`, `ws_url`, …).
///
/// [`TestServer::stop`] stops it gracefully (every websocket gets its close frame).
/// Dropping it — also when a test panics — starts the same shutdown without waiting for it:
/// scenes stop, websockets are sent close frames 1001 and the listener closes, in the
/// background on the test's runtime.
///
/// ```
/// # #[tokio::main(flavor = "current_thread")]
/// # async fn main() -> Result<(), posecast_testkit::KitError> {
/// let server = posecast_testkit::TestServer::start().await?;
/// assert_eq!(server.addr.ip().to_string(), "127.0.0.1");
/// assert_ne!(server.addr.port(), 0);
/// server.stop().await;
/// # Ok(()) }
/// ```
#[derive(Debug)]
pub struct TestServer {
    /// `None` only inside `stop`, `into_server` and `drop`.
    server: Option<Server>,
    control_token: String,
}

impl std::ops::Deref for TestServer {
    type Target = Server;
    fn deref(&self) -> &Server {
        match &self.server {
            Some(s) => s,
            // Only `stop`, `into_server` and `drop` take it, and they consume the value.
            None => unreachable!("a TestServer always holds its server until it is consumed"),
        }
    }
}

impl Drop for TestServer {
    fn drop(&mut self) {
        if let Some(mut server) = self.server.take() {
            server.vmc.abort();
            if let Some(tx) = server.take_shutdown() {
                // The serve task may have ended already; then there is nothing to stop.
                tx.send(()).ok();
            }
            server.state.shutdown();
        }
    }
}

impl TestServer {
    /// Starts a server with the defaults of [`TestServerBuilder`].
    ///
    /// # Errors
    /// As [`TestServerBuilder::start`].
    ///
    /// ```
    /// # #[tokio::main(flavor = "current_thread")]
    /// # async fn main() -> Result<(), posecast_testkit::KitError> {
    /// let server = posecast_testkit::TestServer::start().await?;
    /// assert!(server.ws_url().starts_with("ws://127.0.0.1:"));
    /// # server.stop().await; Ok(()) }
    /// ```
    pub async fn start() -> Result<Self, KitError> {
        TestServerBuilder::default().start().await
    }

    /// A builder, to choose assets, scenes, tick rate and tokens.
    ///
    /// ```
    /// let builder = posecast_testkit::TestServer::builder().tick_rate(30.0);
    /// # let _ = builder;
    /// ```
    #[must_use]
    pub fn builder() -> TestServerBuilder {
        TestServerBuilder::default()
    }

    /// The unlimited control token the kit's clients and drivers present.
    ///
    /// ```
    /// # #[tokio::main(flavor = "current_thread")]
    /// # async fn main() -> Result<(), posecast_testkit::KitError> {
    /// let server = posecast_testkit::TestServer::start().await?;
    /// assert_eq!(server.control_token(), posecast_testkit::DEFAULT_CONTROL_TOKEN);
    /// # server.stop().await; Ok(()) }
    /// ```
    #[must_use]
    pub fn control_token(&self) -> &str {
        &self.control_token
    }

    /// Mints a token as an app's back end does with `POST /api/tokens` and an admin token:
    /// limited to rights, scenes, avatars and a lifetime (see
    /// [`posecast_proto::tokens::MintRequest`]). Hand it to a client with
    /// [`ClientBuilder::token`].
    ///
    /// # Errors
    /// [`KitError::Refused`] for a request outside the limits (`invalid_value`).
    ///
    /// ```
    /// # #[tokio::main(flavor = "current_thread")]
    /// # async fn main() -> Result<(), posecast_testkit::KitError> {
    /// use posecast_proto::tokens::{MintRequest, Right};
    /// let server = posecast_testkit::TestServer::start().await?;
    /// let minted = server.mint_token(MintRequest {
    ///     name: "alice".into(),
    ///     rights: vec![Right::View, Right::Drive],
    ///     scenes: None,
    ///     avatars: Some(vec![posecast_proto::msg::AvatarId("avatar".into())]),
    ///     ttl_s: Some(600),
    ///     max_bytes: None,
    ///     max_objects: None,
    /// })?;
    /// assert_eq!(minted.info.rights, vec![Right::View, Right::Drive]);
    /// let alice = server.client_builder().token(Some(&minted.token)).connect().await?;
    /// alice.first_pose("avatar", std::time::Duration::from_secs(10)).await?;
    /// # server.stop().await; Ok(()) }
    /// ```
    pub fn mint_token(
        &self,
        request: posecast_proto::tokens::MintRequest,
    ) -> Result<posecast_proto::tokens::MintedToken, KitError> {
        let access = &self.state.config.access;
        let minter = access.mint.as_ref().ok_or_else(|| KitError::Refused {
            op: "mint_token".into(),
            error: posecast_proto::msg::ProtocolError::new(
                posecast_proto::msg::ErrorCode::Unavailable,
                "the server has no minter",
            ),
        })?;
        minter
            .mint(request, |name| access.is_configured_name(name))
            .map_err(|e| KitError::Refused {
                op: "mint_token".into(),
                error: e.into(),
            })
    }

    /// A client subscribed to scene `default`, binary frames, holding the control token.
    ///
    /// # Errors
    /// As [`ClientBuilder::connect`].
    ///
    /// ```
    /// # #[tokio::main(flavor = "current_thread")]
    /// # async fn main() -> Result<(), posecast_testkit::KitError> {
    /// let server = posecast_testkit::TestServer::start().await?;
    /// let client = server.client().await?;
    /// client.first_pose("avatar", std::time::Duration::from_secs(10)).await?;
    /// # server.stop().await; Ok(()) }
    /// ```
    pub async fn client(&self) -> Result<TestClient, KitError> {
        self.client_builder().connect().await
    }

    /// A [`ClientBuilder`] for this server, holding the control token (to subscribe to other
    /// scenes, choose JSON, another token…).
    ///
    /// ```
    /// # #[tokio::main(flavor = "current_thread")]
    /// # async fn main() -> Result<(), posecast_testkit::KitError> {
    /// let server = posecast_testkit::TestServer::start().await?;
    /// let json = server.client_builder().encoding(posecast_proto::msg::Encoding::Json).connect().await?;
    /// json.first_pose("avatar", std::time::Duration::from_secs(10)).await?;
    /// # server.stop().await; Ok(()) }
    /// ```
    #[must_use]
    pub fn client_builder(&self) -> ClientBuilder {
        ClientBuilder::new(self.ws_url()).token(Some(&self.control_token))
    }

    /// A live driver ([`Driver`]) holding the control token: `drive` an avatar, then send it
    /// poses (JSON by joint name, or binary by joint index).
    ///
    /// # Errors
    /// [`KitError::Client`]: the connection failed.
    ///
    /// ```
    /// # #[tokio::main(flavor = "current_thread")]
    /// # async fn main() -> Result<(), posecast_testkit::KitError> {
    /// use posecast_proto::msg::AvatarId;
    /// use std::time::Duration;
    /// let server = posecast_testkit::TestServer::start().await?;
    /// let client = server.client().await?;
    /// let driver = server.driver().await?;
    /// let avatar = AvatarId("avatar".into());
    /// let info = driver.drive(&avatar, None, None).await?;
    /// assert!(info.joints.iter().any(|j| j == "l_elbow"));
    /// let q = glam::Quat::from_rotation_z(0.9);
    /// driver.send_pose(&avatar, [("l_elbow".to_string(), q.to_array())], None, None).await?;
    /// client
    ///     .wait_for_pose("avatar", Duration::from_secs(10), |p| {
    ///         p.rotation("l_elbow").is_some_and(|r| posecast_proto::quant::angle_between_degrees(r, q) < 0.01)
    ///     })
    ///     .await?;
    /// # server.stop().await; Ok(()) }
    /// ```
    pub async fn driver(&self) -> Result<Driver, KitError> {
        self.driver_as(Some(&self.control_token)).await
    }

    /// A live driver holding `token` (e.g. one limited to some avatars), or none.
    ///
    /// # Errors
    /// [`KitError::Client`]: the connection failed or the server refused the token.
    ///
    /// ```
    /// # #[tokio::main(flavor = "current_thread")]
    /// # async fn main() -> Result<(), posecast_testkit::KitError> {
    /// use posecast_proto::msg::{AvatarId, ErrorCode};
    /// let server = posecast_testkit::TestServer::start().await?;
    /// let anonymous = server.driver_as(None).await?;
    /// let refused = anonymous.drive(&AvatarId("avatar".into()), None, None).await;
    /// let code = posecast_testkit::KitError::from(refused.unwrap_err()).code();
    /// assert_eq!(code, Some(ErrorCode::Unauthorized));
    /// # server.stop().await; Ok(()) }
    /// ```
    pub async fn driver_as(&self, token: Option<&str>) -> Result<Driver, KitError> {
        Ok(Driver::connect(&self.ws_url(), token.map(str::to_owned)).await?)
    }

    /// Runs a command in this process — no connection, no token — through the same path as
    /// a client's (stored first when there is a data folder), and returns its typed result.
    ///
    /// # Errors
    /// [`KitError::Refused`] with the typed error a client would get.
    ///
    /// ```
    /// # #[tokio::main(flavor = "current_thread")]
    /// # async fn main() -> Result<(), posecast_testkit::KitError> {
    /// use posecast_proto::command::{Command, CommandResult};
    /// let server = posecast_testkit::TestServer::start().await?;
    /// let CommandResult::Scenes(scenes) = server.command(Command::ListScenes).await? else {
    ///     panic!("list_scenes answers with scenes");
    /// };
    /// assert_eq!(scenes[0].avatars[0].avatar.0, "avatar");
    /// # server.stop().await; Ok(()) }
    /// ```
    pub async fn command(&self, command: Command) -> Result<CommandResult, KitError> {
        posecast_server::control::execute_durable(&self.state, &command)
            .await
            .map_err(|e| KitError::Refused {
                op: op(&command),
                error: ProtocolError::from(e),
            })
    }

    /// The loaded rig (asset) named `asset`.
    ///
    /// # Errors
    /// [`KitError::UnknownAsset`].
    ///
    /// ```
    /// # #[tokio::main(flavor = "current_thread")]
    /// # async fn main() -> Result<(), posecast_testkit::KitError> {
    /// let server = posecast_testkit::TestServer::start().await?;
    /// assert!(server.rig("avatar")?.clip("walk").is_some());
    /// # server.stop().await; Ok(()) }
    /// ```
    pub fn rig(&self, asset: &str) -> Result<Arc<Rig>, KitError> {
        self.state
            .world
            .library
            .get(asset)
            .ok_or_else(|| KitError::UnknownAsset(asset.to_owned()))
    }

    /// The index of joint `joint` in rig `asset`'s skeleton (the order poses stream in).
    ///
    /// # Errors
    /// [`KitError::UnknownAsset`], [`KitError::UnknownJoint`].
    ///
    /// ```
    /// # #[tokio::main(flavor = "current_thread")]
    /// # async fn main() -> Result<(), posecast_testkit::KitError> {
    /// let server = posecast_testkit::TestServer::start().await?;
    /// let elbow = server.joint("avatar", "l_elbow")?;
    /// assert_eq!(server.rig("avatar")?.skeleton().names()[elbow], "l_elbow");
    /// assert!(server.joint("avatar", "tail").is_err());
    /// # server.stop().await; Ok(()) }
    /// ```
    pub fn joint(&self, asset: &str, joint: &str) -> Result<usize, KitError> {
        self.rig(asset)?
            .skeleton()
            .find(joint)
            .ok_or_else(|| KitError::UnknownJoint {
                asset: asset.to_owned(),
                joint: joint.to_owned(),
            })
    }

    /// The pose rig `asset`'s clip `clip` gives at `time` seconds from the clip's start, as an
    /// avatar playing it streams it ([`crate::sample_clip`]: the server's own sampling, DOF
    /// limits applied) — the reference for [`crate::StreamedPose::assert_near`].
    ///
    /// # Errors
    /// [`KitError::UnknownAsset`], [`KitError::UnknownClip`].
    ///
    /// ```
    /// # #[tokio::main(flavor = "current_thread")]
    /// # async fn main() -> Result<(), posecast_testkit::KitError> {
    /// let server = posecast_testkit::TestServer::start().await?;
    /// let walk = server.clip_pose("avatar", "walk", 0.4)?;
    /// assert_eq!(walk.len(), server.rig("avatar")?.skeleton().len());
    /// assert!(server.clip_pose("avatar", "moonwalk", 0.0).is_err());
    /// # server.stop().await; Ok(()) }
    /// ```
    pub fn clip_pose(
        &self,
        asset: &str,
        clip: &str,
        time: f32,
    ) -> Result<Vec<Transform>, KitError> {
        let rig = self.rig(asset)?;
        sample_clip(&rig, clip, time)
    }

    /// Stops the server gracefully and waits for it: scenes end, every websocket gets its
    /// close frame 1001, the listener closes, the data folder (if any) is released.
    ///
    /// ```
    /// # #[tokio::main(flavor = "current_thread")]
    /// # async fn main() -> Result<(), posecast_testkit::KitError> {
    /// let server = posecast_testkit::TestServer::start().await?;
    /// let addr = server.addr;
    /// server.stop().await;
    /// assert!(tokio::net::TcpStream::connect(addr).await.is_err());
    /// # Ok(()) }
    /// ```
    pub async fn stop(mut self) {
        if let Some(server) = self.server.take() {
            server.stop().await;
        }
    }

    /// The library's [`Server`], no longer stopped on drop (stop it with [`Server::stop`]).
    ///
    /// ```
    /// # #[tokio::main(flavor = "current_thread")]
    /// # async fn main() -> Result<(), posecast_testkit::KitError> {
    /// let server: posecast_server::startup::Server = posecast_testkit::TestServer::start().await?.into_server();
    /// server.stop().await;
    /// # Ok(()) }
    /// ```
    #[must_use]
    pub fn into_server(mut self) -> Server {
        match self.server.take() {
            Some(s) => s,
            None => unreachable!("a TestServer always holds its server until it is consumed"),
        }
    }
}
