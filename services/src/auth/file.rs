//! The TOML access file and adding tokens (flags and environment go through [`AccessConfig::add`]).

use super::{AccessConfig, Role, Secret, TokenRule};
use posecast_proto::msg::{AvatarId, SceneId};
use serde::Deserialize;
use std::sync::Arc;

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
    /// Every token's quota unless its `[[token]]` gives its own.
    #[serde(default)]
    token_max_bytes: Option<u64>,
    #[serde(default)]
    token_max_objects: Option<u64>,
}

impl Default for FileAccess {
    fn default() -> Self {
        Self {
            open_view: true,
            token_max_bytes: None,
            token_max_objects: None,
        }
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
    max_bytes: Option<u64>,
    max_objects: Option<u64>,
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
    /// max_bytes = 104857600      # optional: bytes of the uploads and recordings it makes
    /// max_objects = 100          # optional: how many of them
    /// ```
    ///
    /// `[access]` may give `token_max_bytes` and `token_max_objects`: every token's quota
    /// unless its own entry gives one.
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
            mint: None,
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
                minted: None,
                quota: super::TokenQuota {
                    max_bytes: t.max_bytes.or(file.access.token_max_bytes),
                    max_objects: t.max_objects.or(file.access.token_max_objects),
                },
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
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use crate::auth::Caller;
    use posecast_proto::msg::ErrorCode;

    #[test]
    fn toml_file_with_env_tokens_and_limits() {
        let text = r#"
            [access]
            open_view = false
            token_max_bytes = 1000

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
            max_objects = 3
        "#;
        let c = AccessConfig::from_toml(text, |v| (v == "ALICE").then(|| "alice-token".into()))
            .unwrap();
        assert!(!c.open_view);
        assert_eq!(c.tokens.len(), 3);
        // The [access] default, and a token's own value next to it.
        assert_eq!(
            c.tokens[2].quota,
            super::super::TokenQuota {
                max_bytes: Some(1000),
                max_objects: Some(3)
            }
        );
        assert_eq!(c.tokens[0].quota.max_objects, None);
        let alice = c.identify(Some("alice-token")).unwrap();
        assert_eq!(alice.name(), "alice");
        let access = c.access(&alice);
        assert!(access.control && access.view);
        assert_eq!(access.avatars, Some(vec![AvatarId("alice".into())]));
        assert_eq!(
            c.identify(Some("alice-token2")).unwrap_err().code(),
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
}
