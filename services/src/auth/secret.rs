//! Token secrets: hidden from `Debug`, compared in constant time (`subtle`).

use std::fmt;
use subtle::ConstantTimeEq;

/// A token's secret text. `Debug` never shows it; `==` is [`Secret::matches`].
#[derive(Clone)]
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
        self.0.as_bytes().ct_eq(presented.as_bytes()).into()
    }
}

/// Through [`Secret::matches`], so that no comparison of secrets can leak where they differ.
impl PartialEq for Secret {
    fn eq(&self, other: &Self) -> bool {
        self.matches(&other.0)
    }
}

impl Eq for Secret {}

impl fmt::Debug for Secret {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("***")
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::auth::{Caller, Role, TokenRule};
    use std::sync::Arc;

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
            assert_eq!(Secret::new(a).matches(b), a == b, "{a:?} vs {b:?}");
            assert_eq!(Secret::new(a) == Secret::new(b), a == b, "{a:?} vs {b:?}");
        }
    }

    #[test]
    fn debug_never_shows_a_token() {
        let rule = TokenRule::new("alice", Secret::new("s3cret-token"), Role::Control);
        let text = format!("{rule:?} {:?}", Caller::Token(Arc::new(rule.clone())));
        assert!(!text.contains("s3cret"), "{text}");
        assert!(text.contains("alice"));
    }
}
