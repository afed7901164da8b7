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
//! - Minted tokens ([`minted`], `POST /api/tokens` with an admin token — an unlimited control
//!   token the operator configured) carry their own rights ([`Right`]), limits and expiry,
//!   signed by the server's key; a configured view token has `view`, a control token every
//!   right (`upload` only when unlimited).
//!
//! Missing, unknown, expired or revoked token: `unauthorized` (HTTP 401). A valid token
//! without the right: `forbidden` (HTTP 403).

use crate::world::command::Needs;
use posecast_core::error::Error;
use posecast_proto::command::CommandResult;
use posecast_proto::msg::{Access, AvatarId, SceneId};
use posecast_proto::tokens::{Right, TokenInfo};
use serde::Deserialize;
use std::sync::Arc;

mod file;
pub mod minted;
mod secret;

pub use file::{AccessConfigError, MIN_TOKEN_LEN};
pub use minted::{KeySource, Minter};
pub use secret::Secret;

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
    /// What the uploads and recordings this token makes may hold in all.
    pub quota: TokenQuota,
    /// A minted token's claims (its rights and expiry); `None` for a configured token.
    pub minted: Option<TokenInfo>,
}

/// A token's share of the data folder (issue 37): uploads and recordings it made, counted
/// against it as well as against the server's `upload_total_bytes`. `None`: no limit but the
/// server's.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TokenQuota {
    /// Bytes of its stored uploads and recordings.
    pub max_bytes: Option<u64>,
    /// Number of its stored uploads and recordings.
    pub max_objects: Option<u64>,
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
            quota: TokenQuota::default(),
            minted: None,
        }
    }

    /// The rule a minted token's claims make.
    #[must_use]
    pub fn from_minted(info: TokenInfo) -> Self {
        let control = info.rights.contains(&Right::Control);
        Self {
            name: info.name.clone(),
            // Never compared: minted tokens are checked by their signature.
            secret: Secret::new(String::new()),
            role: if control { Role::Control } else { Role::View },
            scenes: info.scenes.clone(),
            avatars: info.avatars.clone(),
            quota: TokenQuota {
                max_bytes: info.max_bytes,
                max_objects: info.max_objects,
            },
            minted: Some(info),
        }
    }

    /// Whether the token has `right`. A minted token has what it lists (`control` brings
    /// `drive`); a configured view token `view`; a configured control token everything, but
    /// `upload` only when unlimited.
    #[must_use]
    pub fn has(&self, right: Right) -> bool {
        match &self.minted {
            Some(info) => {
                info.rights.contains(&right)
                    || (right == Right::Drive && info.rights.contains(&Right::Control))
            }
            None => match self.role {
                Role::View => right == Right::View,
                Role::Control => right != Right::Upload || self.unlimited(),
            },
        }
    }

    /// Every right it has, in order.
    #[must_use]
    pub fn rights(&self) -> Vec<Right> {
        Right::ALL.into_iter().filter(|r| self.has(*r)).collect()
    }

    /// Whether it is limited to some scenes or avatars.
    #[must_use]
    pub fn is_limited(&self) -> bool {
        !self.unlimited()
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
    /// The name objects it makes are owned by (uploads, recordings): its token's name, none
    /// when anonymous.
    #[must_use]
    pub fn owner(&self) -> Option<&str> {
        match self {
            Self::Anonymous => None,
            Self::Token(t) => Some(&t.name),
        }
    }

    /// A minted token's claims.
    #[must_use]
    pub fn minted(&self) -> Option<&TokenInfo> {
        match self {
            Self::Token(t) => t.minted.as_ref(),
            Self::Anonymous => None,
        }
    }

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
    /// Mints and checks minted tokens; `None`: none are accepted (the server sets one up at
    /// start, `posecast_server::startup::Server::start`).
    pub mint: Option<Arc<Minter>>,
}

impl Default for AccessConfig {
    /// Open views, no tokens: nothing can be commanded until a control token is configured
    /// (the `posecast` binary generates one when none is given).
    fn default() -> Self {
        Self {
            open_view: true,
            tokens: Vec::new(),
            mint: None,
        }
    }
}

impl AccessConfig {
    /// Whether any control token is configured.
    #[must_use]
    pub fn has_control_token(&self) -> bool {
        self.tokens.iter().any(|t| t.role == Role::Control)
    }

    /// Who presents `token`. Every configured token is compared (in constant time), so the
    /// time taken does not tell which one matched.
    ///
    /// # Errors
    /// `unauthorized` for a token that is not configured.
    pub fn identify(&self, token: Option<&str>) -> Result<Caller, Error> {
        let Some(token) = token else {
            return Ok(Caller::Anonymous);
        };
        if let Some(mint) = &self.mint
            && token.starts_with(minted::PREFIX)
        {
            let info = mint.verify(token)?;
            return Ok(Caller::Token(Arc::new(TokenRule::from_minted(info))));
        }
        let mut found = None;
        for t in &self.tokens {
            if t.secret.matches(token) && found.is_none() {
                found = Some(t.clone());
            }
        }
        found
            .map(Caller::Token)
            .ok_or_else(|| Error::Unauthorized("the token is not valid on this server".into()))
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
                view: self.open_view || t.has(Right::View),
                control: t.has(Right::Control),
                name: Some(t.name.clone()),
                scenes: t.scenes.clone(),
                avatars: t.avatars.clone(),
                rights: t.rights(),
                expires_at: t.minted.as_ref().map(|m| m.expires_at),
            },
        }
    }

    /// A minted token that expired or was revoked since it was presented is refused from then
    /// on (every check below starts here).
    ///
    /// # Errors
    /// `unauthorized`, saying which.
    pub fn still_valid(&self, caller: &Caller) -> Result<(), Error> {
        match (caller.minted(), &self.mint) {
            (Some(info), Some(mint)) => mint.check(info),
            _ => Ok(()),
        }
    }

    /// May `caller` mint, list and revoke tokens? Only a configured, unlimited control token
    /// (an *admin* token): a minted token never mints.
    ///
    /// # Errors
    /// Unauthorized without a token; Forbidden with any other token.
    pub fn authorize_admin(&self, caller: &Caller) -> Result<(), Error> {
        match caller {
            Caller::Anonymous => Err(unauthorized("minting tokens needs an admin token")),
            Caller::Token(t) if t.minted.is_none() && t.role == Role::Control && t.unlimited() => {
                Ok(())
            }
            Caller::Token(t) => Err(forbidden(format!(
                "token {} may not mint tokens: that needs an unlimited control token from the \
                 server's configuration",
                t.name
            ))),
        }
    }

    /// Whether `name` is a configured token's.
    #[must_use]
    pub fn is_configured_name(&self, name: &str) -> bool {
        self.tokens.iter().any(|t| t.name == name)
    }

    /// May `caller` watch `scene` (subscribe, or read it)?
    ///
    /// # Errors
    /// Unauthorized without a token when views are not open; Forbidden outside the token's
    /// scenes.
    pub fn authorize_view(&self, caller: &Caller, scene: &SceneId) -> Result<(), Error> {
        self.still_valid(caller)?;
        match caller {
            Caller::Anonymous if self.open_view => Ok(()),
            Caller::Anonymous => Err(unauthorized("watching needs a view token")),
            Caller::Token(t) if !self.open_view && !t.has(Right::View) => {
                Err(forbidden(format!("token {} has no view right", t.name)))
            }
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
    pub fn visible(&self, caller: &Caller, result: CommandResult) -> CommandResult {
        match result {
            CommandResult::Scenes(scenes) => CommandResult::Scenes(
                scenes
                    .into_iter()
                    .filter(|s| self.authorize_view(caller, &s.scene).is_ok())
                    .collect(),
            ),
            result => result,
        }
    }

    /// May `caller` read what is not in one scene (lists, meshes)?
    ///
    /// # Errors
    /// Unauthorized without a token when views are not open.
    pub fn authorize_read(&self, caller: &Caller) -> Result<(), Error> {
        self.still_valid(caller)?;
        match caller {
            Caller::Anonymous if !self.open_view => Err(unauthorized("reading needs a view token")),
            Caller::Token(t) if !self.open_view && !t.has(Right::View) => {
                Err(forbidden(format!("token {} has no view right", t.name)))
            }
            _ => Ok(()),
        }
    }

    /// May `caller` upload assets (needs a control token without limits)?
    ///
    /// # Errors
    /// Unauthorized without a token, Forbidden with a view or limited token.
    pub fn authorize_upload(&self, caller: &Caller) -> Result<(), Error> {
        self.still_valid(caller)?;
        match caller {
            Caller::Token(t) if t.has(Right::Upload) => Ok(()),
            Caller::Token(t) if t.minted.is_none() && t.role == Role::Control => {
                Err(forbidden(format!(
                    "token {} is limited to some scenes or avatars; uploads need an unlimited \
                     control token or a minted token with the upload right",
                    t.name
                )))
            }
            _ => token_with(caller, &[Right::Upload], "uploads").map(|_| ()),
        }
    }

    /// May `caller` delete an object (an upload, a recording) made by `owner`? An unlimited
    /// control token deletes anything; a limited one what it made itself.
    ///
    /// # Errors
    /// Unauthorized without a token, Forbidden with a view token or someone else's object.
    pub fn authorize_delete(&self, caller: &Caller, owner: Option<&str>) -> Result<(), Error> {
        self.still_valid(caller)?;
        let t = token_with(
            caller,
            &[Right::Control, Right::Upload, Right::Record],
            "deletes",
        )?;
        if (t.unlimited() && t.minted.is_none()) || owner == Some(t.name.as_str()) {
            Ok(())
        } else {
            Err(forbidden(format!(
                "token {} may delete only what it made",
                t.name
            )))
        }
    }

    /// May `caller` run a command with these `facts`? The control layer finds them
    /// (`crate::control::authorize`); a [`Grant::Limited`] command also passes its handler's
    /// rule for limited tokens there.
    ///
    /// # Errors
    /// Unauthorized / Forbidden as described in the module documentation.
    pub fn authorize(&self, caller: &Caller, facts: &CommandFacts<'_>) -> Result<Grant, Error> {
        self.still_valid(caller)?;
        if facts.read_only {
            return match facts.scene {
                Some(scene) => self.authorize_view(caller, scene),
                // Unknown avatars are reported by the command itself.
                None => self.authorize_read(caller),
            }
            .map(|()| Grant::Full);
        }
        let (rights, what) = rights(facts.needs);
        let t = token_with(caller, rights, what)?;
        if facts.needs == Needs::DeleteOwned {
            // Who made the object decides ([`AccessConfig::authorize_delete`], where it runs).
            return Ok(Grant::Full);
        }
        if t.unlimited() {
            return Ok(Grant::Full);
        }
        let scene_ok = facts.scene.is_some_and(|scene| t.allows_scene(scene));
        let avatar_ok = facts.avatar.is_some_and(|avatar| t.allows_avatar(avatar));
        if scene_ok || avatar_ok {
            Ok(Grant::Limited)
        } else {
            Err(forbidden(format!(
                "token {} may not {}",
                t.name,
                describe(facts)
            )))
        }
    }
}

/// What the access rules need to know of a command, found by the control layer
/// (`crate::control::authorize`): the rules read neither the command nor the world.
#[derive(Debug, Clone, Copy)]
pub struct CommandFacts<'a> {
    /// It only reads (`Command::is_read_only`): any token that may view its scene.
    pub read_only: bool,
    /// The right it needs when it changes something (its handler's).
    pub needs: Needs,
    /// The scene it names; else the scene of the avatar it names, when that avatar exists.
    pub scene: Option<&'a SceneId>,
    /// The avatar it names.
    pub avatar: Option<&'a AvatarId>,
}

/// How far [`AccessConfig::authorize`] allows a command.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Grant {
    /// Without limits (or a read).
    Full,
    /// Through a token limited to scenes or avatars that covers it: the command's handler may
    /// refuse it still (`add_avatar` of a huge rig).
    Limited,
}

/// The rights of which a command needs one, and what it is called in errors.
fn rights(needs: Needs) -> (&'static [Right], &'static str) {
    match needs {
        Needs::Control => (&[Right::Control], "commands"),
        Needs::Drive => (&[Right::Drive], "drive commands"),
        Needs::Record => (&[Right::Record], "recording commands"),
        Needs::DeleteOwned | Needs::Delete => {
            (&[Right::Control, Right::Upload, Right::Record], "deletes")
        }
    }
}

/// The caller's token if it has one of `rights` (`what` names the action in errors).
fn token_with<'a>(
    caller: &'a Caller,
    rights: &[Right],
    what: &str,
) -> Result<&'a TokenRule, Error> {
    match caller {
        Caller::Anonymous => Err(Error::Unauthorized(format!("{what} need a control token"))),
        Caller::Token(t) if rights.iter().any(|r| t.has(*r)) => Ok(t),
        Caller::Token(t) if t.minted.is_none() && t.role == Role::View => Err(forbidden(format!(
            "token {} is a view token; {what} need a control token",
            t.name
        ))),
        Caller::Token(t) => Err(forbidden(format!(
            "token {} may not do this: {what} need the {} right",
            t.name,
            rights
                .iter()
                .map(|r| format!("{r:?}").to_lowercase())
                .collect::<Vec<_>>()
                .join(" or ")
        ))),
    }
}

fn describe(facts: &CommandFacts<'_>) -> String {
    match (facts.scene, facts.avatar) {
        (_, Some(a)) => format!("command avatar {a}"),
        (Some(s), None) => format!("change scene {s}"),
        (None, None) => "run this command".into(),
    }
}

fn unauthorized(message: &str) -> Error {
    Error::Unauthorized(message.into())
}

fn forbidden(message: String) -> Error {
    Error::Forbidden(message)
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use posecast_proto::msg::ErrorCode;

    #[test]
    fn view_rules() {
        let mut c = AccessConfig {
            open_view: false,
            tokens: Vec::new(),
            mint: None,
        };
        let mut screen = TokenRule::new("screen", Secret::new("view-token-1"), Role::View);
        screen.scenes = Some(vec![SceneId("lobby".into())]);
        c.add(screen).unwrap();
        let lobby = SceneId("lobby".into());
        let other = SceneId("other".into());
        let screen = c.identify(Some("view-token-1")).unwrap();
        assert!(c.authorize_view(&screen, &lobby).is_ok());
        assert_eq!(
            c.authorize_view(&screen, &other).unwrap_err().code(),
            ErrorCode::Forbidden
        );
        assert_eq!(
            c.authorize_view(&Caller::Anonymous, &lobby)
                .unwrap_err()
                .code(),
            ErrorCode::Unauthorized
        );
        assert_eq!(
            c.authorize_upload(&screen).unwrap_err().code(),
            ErrorCode::Forbidden
        );
        c.open_view = true;
        assert!(c.authorize_view(&Caller::Anonymous, &other).is_ok());
        assert!(c.authorize_view(&screen, &other).is_ok());
    }
}
