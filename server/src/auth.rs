//! Access control: view and control tokens, optionally limited to scenes or avatars.
//!
//! - Viewers (subscribe, list, get) need no token when views are open (the default), else a
//!   view or control token.
//! - Every command that changes state needs a control token. A token limited to `avatars`
//!   commands only those avatars; one limited to `scenes` commands those scenes and every
//!   avatar in them. Uploads need a control token without limits.
//! - Tokens come from flags/environment or a TOML file ([`AccessConfig::from_toml`]); they are
//!   compared in constant time and never logged: [`Secret`]'s `Debug` prints `***`, and logs
//!   name a token by its `name`.
//!
//! Missing or unknown token: [`ErrorCode::Unauthorized`] (HTTP 401). A valid token without the
//! right: [`ErrorCode::Forbidden`] (HTTP 403).

use crate::state::AppState;
use posecast_proto::command::Command;
use posecast_proto::msg::{Access, AvatarId, ErrorCode, ProtocolError, SceneId};
use serde::Deserialize;
use serde_json::Value;
use std::fmt;
use std::sync::Arc;

/// A token's secret text. `Debug` never shows it.
#[derive(Clone, PartialEq, Eq)]
pub struct Secret(String);

impl Secret {
    /// Wraps a token.
    #[must_use]
    pub fn new(token: impl Into<String>) -> Self {
        Self(token.into())
    }

    /// A random 128-bit token (32 hex digits).
    #[must_use]
    pub fn generate() -> Self {
        let bytes: [u8; 16] = rand::random();
        Self(bytes.iter().map(|b| format!("{b:02x}")).collect())
    }

    /// The token text (to hand to the operator once; never log it).
    #[must_use]
    pub fn expose(&self) -> &str {
        &self.0
    }

    /// Constant-time comparison: the time depends only on the lengths, never on where the
    /// texts differ.
    #[must_use]
    pub fn matches(&self, presented: &str) -> bool {
        ct_eq(self.0.as_bytes(), presented.as_bytes())
    }
}

impl fmt::Debug for Secret {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("***")
    }
}

fn ct_eq(a: &[u8], b: &[u8]) -> bool {
    let mut diff = u8::from(a.len() != b.len());
    for i in 0..a.len().max(b.len()) {
        let x = a.get(i).copied().unwrap_or(0);
        let y = b.get(i).copied().unwrap_or(0);
        diff |= x ^ y;
    }
    std::hint::black_box(diff) == 0
}

/// What a token may do.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Role {
    /// Subscribe and read.
    View,
    /// Also run commands (and upload, when not limited).
    Control,
}

/// One configured token.
#[derive(Debug, Clone)]
pub struct TokenRule {
    /// A name for logs and `welcome.access.name` (never the secret).
    pub name: String,
    /// The token.
    pub secret: Secret,
    /// View or control.
    pub role: Role,
    /// Only these scenes (and their avatars).
    pub scenes: Option<Vec<SceneId>>,
    /// Only these avatars.
    pub avatars: Option<Vec<AvatarId>>,
}

impl TokenRule {
    /// An unlimited token.
    #[must_use]
    pub fn new(name: impl Into<String>, secret: Secret, role: Role) -> Self {
        Self {
            name: name.into(),
            secret,
            role,
            scenes: None,
            avatars: None,
        }
    }

    fn unlimited(&self) -> bool {
        self.scenes.is_none() && self.avatars.is_none()
    }

    fn allows_scene(&self, scene: &SceneId) -> bool {
        self.scenes.as_ref().is_some_and(|s| s.contains(scene))
    }

    fn allows_avatar(&self, avatar: &AvatarId) -> bool {
        self.avatars.as_ref().is_some_and(|a| a.contains(avatar))
    }
}

/// Who is asking: nobody in particular, or the holder of a configured token.
#[derive(Debug, Clone, Default)]
pub enum Caller {
    /// No token.
    #[default]
    Anonymous,
    /// A valid token.
    Token(Arc<TokenRule>),
}

impl Caller {
    /// The token's name, for logs.
    #[must_use]
    pub fn name(&self) -> &str {
        match self {
            Self::Anonymous => "anonymous",
            Self::Token(t) => &t.name,
        }
    }
}

/// The server's access rules.
#[derive(Debug, Clone)]
pub struct AccessConfig {
    /// Viewers need no token.
    pub open_view: bool,
    /// Every accepted token.
    pub tokens: Vec<Arc<TokenRule>>,
}

impl Default for AccessConfig {
    /// Open views, no tokens: nothing can be commanded until a control token is configured
    /// (the `posecast` binary generates one when none is given).
    fn default() -> Self {
        Self {
            open_view: true,
            tokens: Vec::new(),
        }
    }
}

/// Why an access configuration is refused.
#[derive(Debug, thiserror::Error)]
pub enum AccessConfigError {
    /// Not valid TOML or not the expected shape.
    #[error("access config: {0}")]
    Parse(String),
    /// A token's text is unusable.
    #[error("access config: token {name}: {message}")]
    Token {
        /// The token's name.
        name: String,
        /// What is wrong.
        message: String,
    },
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct FileConfig {
    #[serde(default)]
    access: FileAccess,
    #[serde(default, rename = "token")]
    tokens: Vec<FileToken>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct FileAccess {
    #[serde(default = "yes")]
    open_view: bool,
}

impl Default for FileAccess {
    fn default() -> Self {
        Self { open_view: true }
    }
}

fn yes() -> bool {
    true
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct FileToken {
    name: String,
    role: Role,
    token: Option<String>,
    token_env: Option<String>,
    scenes: Option<Vec<SceneId>>,
    avatars: Option<Vec<AvatarId>>,
}

/// Shortest token accepted.
pub const MIN_TOKEN_LEN: usize = 8;

impl AccessConfig {
    /// Parses a TOML access file:
    ///
    /// ```toml
    /// [access]
    /// open_view = false          # viewers need a token (default true)
    ///
    /// [[token]]
    /// name = "alice"
    /// role = "control"           # or "view"
    /// token_env = "ALICE_TOKEN"  # or token = "…"
    /// avatars = ["alice"]        # optional limit; also scenes = […]
    /// ```
    ///
    /// `env` looks up `token_env` variables (the process environment in the binary).
    ///
    /// # Errors
    /// Bad TOML, a token given both or neither way, a missing variable, a token shorter than
    /// [`MIN_TOKEN_LEN`], or the same token twice.
    pub fn from_toml(
        text: &str,
        env: impl Fn(&str) -> Option<String>,
    ) -> Result<Self, AccessConfigError> {
        let file: FileConfig =
            toml::from_str(text).map_err(|e| AccessConfigError::Parse(e.to_string()))?;
        let mut config = Self {
            open_view: file.access.open_view,
            tokens: Vec::new(),
        };
        for t in file.tokens {
            let bad = |message: &str| AccessConfigError::Token {
                name: t.name.clone(),
                message: message.into(),
            };
            let secret = match (&t.token, &t.token_env) {
                (Some(s), None) => s.clone(),
                (None, Some(var)) => {
                    env(var).ok_or_else(|| bad(&format!("environment variable {var} is unset")))?
                }
                _ => return Err(bad("give exactly one of token or token_env")),
            };
            config.add(TokenRule {
                name: t.name,
                secret: Secret::new(secret),
                role: t.role,
                scenes: t.scenes,
                avatars: t.avatars,
            })?;
        }
        Ok(config)
    }

    /// Adds a token.
    ///
    /// # Errors
    /// Too short, or equal to a token already configured.
    pub fn add(&mut self, rule: TokenRule) -> Result<(), AccessConfigError> {
        let bad = |message: &str| AccessConfigError::Token {
            name: rule.name.clone(),
            message: message.into(),
        };
        if rule.secret.expose().chars().count() < MIN_TOKEN_LEN {
            return Err(bad(&format!("shorter than {MIN_TOKEN_LEN} characters")));
        }
        if self.tokens.iter().any(|t| t.secret == rule.secret) {
            return Err(bad("the same token is configured twice"));
        }
        self.tokens.push(Arc::new(rule));
        Ok(())
    }

    /// Whether any control token is configured.
    #[must_use]
    pub fn has_control_token(&self) -> bool {
        self.tokens.iter().any(|t| t.role == Role::Control)
    }

    /// Who presents `token`. Every configured token is compared (in constant time), so the
    /// time taken does not tell which one matched.
    ///
    /// # Errors
    /// [`ErrorCode::Unauthorized`] for a token that is not configured.
    pub fn identify(&self, token: Option<&str>) -> Result<Caller, ProtocolError> {
        let Some(token) = token else {
            return Ok(Caller::Anonymous);
        };
        let mut found = None;
        for t in &self.tokens {
            if t.secret.matches(token) && found.is_none() {
                found = Some(t.clone());
            }
        }
        found.map(Caller::Token).ok_or_else(|| {
            ProtocolError::new(
                ErrorCode::Unauthorized,
                "the token is not valid on this server",
            )
        })
    }

    /// What `caller` may do, as told to clients.
    #[must_use]
    pub fn access(&self, caller: &Caller) -> Access {
        match caller {
            Caller::Anonymous => Access {
                view: self.open_view,
                ..Access::default()
            },
            Caller::Token(t) => Access {
                view: true,
                control: t.role == Role::Control,
                name: Some(t.name.clone()),
                scenes: t.scenes.clone(),
                avatars: t.avatars.clone(),
            },
        }
    }

    /// May `caller` watch `scene` (subscribe, or read it)?
    ///
    /// # Errors
    /// Unauthorized without a token when views are not open; Forbidden outside the token's
    /// scenes.
    pub fn authorize_view(&self, caller: &Caller, scene: &SceneId) -> Result<(), ProtocolError> {
        match caller {
            Caller::Anonymous if self.open_view => Ok(()),
            Caller::Anonymous => Err(unauthorized("watching needs a view token")),
            Caller::Token(t) => match &t.scenes {
                Some(s) if !s.contains(scene) && !self.open_view => Err(forbidden(format!(
                    "token {} may not watch scene {scene}",
                    t.name
                ))),
                _ => Ok(()),
            },
        }
    }

    /// `result` of `command` as `caller` may see it: a `list_scenes` result loses the scenes
    /// the caller may not watch (only possible when views are private and the token is
    /// limited to scenes); every other result is unchanged.
    #[must_use]
    pub fn visible(&self, caller: &Caller, command: &Command, result: Value) -> Value {
        match (command, result) {
            (Command::ListScenes, Value::Array(scenes)) => Value::Array(
                scenes
                    .into_iter()
                    .filter(|s| {
                        s.get("scene").and_then(Value::as_str).is_none_or(|id| {
                            self.authorize_view(caller, &SceneId(id.to_owned())).is_ok()
                        })
                    })
                    .collect(),
            ),
            (_, result) => result,
        }
    }

    /// May `caller` read what is not in one scene (lists, meshes)?
    ///
    /// # Errors
    /// Unauthorized without a token when views are not open.
    pub fn authorize_read(&self, caller: &Caller) -> Result<(), ProtocolError> {
        match caller {
            Caller::Anonymous if !self.open_view => Err(unauthorized("reading needs a view token")),
            _ => Ok(()),
        }
    }

    /// May `caller` upload assets (needs a control token without limits)?
    ///
    /// # Errors
    /// Unauthorized without a token, Forbidden with a view or limited token.
    pub fn authorize_upload(&self, caller: &Caller) -> Result<(), ProtocolError> {
        let t = control_token(caller)?;
        if t.unlimited() {
            Ok(())
        } else {
            Err(forbidden(format!(
                "token {} is limited to some scenes or avatars; uploads need an unlimited control token",
                t.name
            )))
        }
    }

    /// May `caller` run `command`? The avatar's scene is looked up in `state` for tokens
    /// limited to scenes.
    ///
    /// # Errors
    /// Unauthorized / Forbidden as described in the module documentation.
    pub fn authorize(
        &self,
        caller: &Caller,
        state: &AppState,
        command: &Command,
    ) -> Result<(), ProtocolError> {
        if command.is_read_only() {
            return match command.avatar() {
                Some(a) => match state.find_avatar(a) {
                    Ok(scene) => self.authorize_view(caller, &scene.id),
                    // Unknown avatars are reported by the command itself.
                    Err(_) => self.authorize_read(caller),
                },
                None => self.authorize_read(caller),
            };
        }
        let t = control_token(caller)?;
        if t.unlimited() {
            return Ok(());
        }
        let scene_ok = match (command.scene(), command.avatar()) {
            (Some(scene), _) => t.allows_scene(scene),
            (None, Some(avatar)) => state
                .find_avatar(avatar)
                .is_ok_and(|scene| t.allows_scene(&scene.id)),
            (None, None) => false,
        };
        // A scene-level command (create/delete scene) is not an avatar's to run, except adding
        // the token's own avatar.
        let avatar_ok = match command {
            Command::CreateScene { .. } | Command::DeleteScene { .. } => false,
            _ => command.avatar().is_some_and(|a| t.allows_avatar(a)),
        };
        if scene_ok || avatar_ok {
            Ok(())
        } else {
            Err(forbidden(format!(
                "token {} may not {}",
                t.name,
                describe(command)
            )))
        }
    }
}

fn control_token(caller: &Caller) -> Result<&TokenRule, ProtocolError> {
    match caller {
        Caller::Anonymous => Err(unauthorized("commands need a control token")),
        Caller::Token(t) if t.role == Role::Control => Ok(t),
        Caller::Token(t) => Err(forbidden(format!(
            "token {} is a view token; commands need a control token",
            t.name
        ))),
    }
}

fn describe(command: &Command) -> String {
    match (command.scene(), command.avatar()) {
        (_, Some(a)) => format!("command avatar {a}"),
        (Some(s), None) => format!("change scene {s}"),
        (None, None) => "run this command".into(),
    }
}

fn unauthorized(message: &str) -> ProtocolError {
    ProtocolError::new(ErrorCode::Unauthorized, message)
}

fn forbidden(message: String) -> ProtocolError {
    ProtocolError::new(ErrorCode::Forbidden, message)
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn constant_time_compare_is_equality() {
        for (a, b) in [
            ("", ""),
            ("abc", "abc"),
            ("abc", "abd"),
            ("abc", "ab"),
            ("ab", "abc"),
            ("", "a"),
            ("a\0", "a"),
        ] {
            assert_eq!(ct_eq(a.as_bytes(), b.as_bytes()), a == b, "{a:?} vs {b:?}");
        }
    }

    #[test]
    fn debug_never_shows_a_token() {
        let rule = TokenRule::new("alice", Secret::new("s3cret-token"), Role::Control);
        let text = format!("{rule:?} {:?}", Caller::Token(Arc::new(rule.clone())));
        assert!(!text.contains("s3cret"), "{text}");
        assert!(text.contains("alice"));
    }

    #[test]
    fn toml_file_with_env_tokens_and_limits() {
        let text = r#"
            [access]
            open_view = false

            [[token]]
            name = "admin"
            role = "control"
            token = "admin-token-1"

            [[token]]
            name = "alice"
            role = "control"
            token_env = "ALICE"
            avatars = ["alice"]

            [[token]]
            name = "screen"
            role = "view"
            token = "view-token-1"
            scenes = ["lobby"]
        "#;
        let c = AccessConfig::from_toml(text, |v| (v == "ALICE").then(|| "alice-token".into()))
            .unwrap();
        assert!(!c.open_view);
        assert_eq!(c.tokens.len(), 3);
        let alice = c.identify(Some("alice-token")).unwrap();
        assert_eq!(alice.name(), "alice");
        let access = c.access(&alice);
        assert!(access.control && access.view);
        assert_eq!(access.avatars, Some(vec![AvatarId("alice".into())]));
        assert_eq!(
            c.identify(Some("alice-token2")).unwrap_err().code,
            ErrorCode::Unauthorized
        );
        assert!(matches!(c.identify(None).unwrap(), Caller::Anonymous));
        assert!(!c.access(&Caller::Anonymous).view);
    }

    #[test]
    fn bad_files_are_refused_with_the_reason() {
        let env = |_: &str| None;
        for (text, needle) in [
            ("[[token]]\nname='a'\nrole='control'", "exactly one"),
            (
                "[[token]]\nname='a'\nrole='control'\ntoken_env='NOPE'",
                "NOPE is unset",
            ),
            (
                "[[token]]\nname='a'\nrole='control'\ntoken='short'",
                "shorter",
            ),
            (
                "[[token]]\nname='a'\nrole='boss'\ntoken='long-enough'",
                "boss",
            ),
            (
                "[[token]]\nname='a'\nrole='view'\ntoken='long-enough'\n[[token]]\nname='b'\nrole='view'\ntoken='long-enough'",
                "twice",
            ),
            ("[acess]\nopen_view=true", "acess"),
        ] {
            let e = AccessConfig::from_toml(text, env).unwrap_err().to_string();
            assert!(e.contains(needle), "{text}: {e}");
            assert!(!e.contains("long-enough"), "error shows the token: {e}");
        }
    }

    #[test]
    fn view_rules() {
        let mut c = AccessConfig {
            open_view: false,
            tokens: Vec::new(),
        };
        let mut screen = TokenRule::new("screen", Secret::new("view-token-1"), Role::View);
        screen.scenes = Some(vec![SceneId("lobby".into())]);
        c.add(screen).unwrap();
        let lobby = SceneId("lobby".into());
        let other = SceneId("other".into());
        let screen = c.identify(Some("view-token-1")).unwrap();
        assert!(c.authorize_view(&screen, &lobby).is_ok());
        assert_eq!(
            c.authorize_view(&screen, &other).unwrap_err().code,
            ErrorCode::Forbidden
        );
        assert_eq!(
            c.authorize_view(&Caller::Anonymous, &lobby)
                .unwrap_err()
                .code,
            ErrorCode::Unauthorized
        );
        assert_eq!(
            c.authorize_upload(&screen).unwrap_err().code,
            ErrorCode::Forbidden
        );
        c.open_view = true;
        assert!(c.authorize_view(&Caller::Anonymous, &other).is_ok());
        assert!(c.authorize_view(&screen, &other).is_ok());
    }
}
