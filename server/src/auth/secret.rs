//! Token secrets: hidden from `Debug`, compared in constant time.

use std::fmt;

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
}
