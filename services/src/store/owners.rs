//! What each token holds in the data folder: bytes and count of the uploads and recordings it
//! made, so one token cannot fill the server's room for everyone (issue 37). The owner of an
//! object is stored with it (an upload's `meta.json`, a recording's `<clip>.json`), so the
//! counts are rebuilt at start from what is restored.

use std::collections::BTreeMap;

/// Bytes and objects one owner holds.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Usage {
    /// Bytes of its stored files.
    pub bytes: u64,
    /// Uploads and recordings.
    pub objects: u64,
}

/// Per owner (a token's name) what it holds; objects without an owner (made by the server
/// itself, or stored by an older version) count against no token.
#[derive(Debug, Default)]
pub struct Owners {
    by_owner: BTreeMap<String, Usage>,
}

impl Owners {
    /// What `owner` holds (nothing for `None` or an owner with nothing).
    #[must_use]
    pub fn usage(&self, owner: Option<&str>) -> Usage {
        owner
            .and_then(|o| self.by_owner.get(o))
            .copied()
            .unwrap_or_default()
    }

    /// Counts one more object of `bytes` for `owner`.
    pub fn add(&mut self, owner: Option<&str>, bytes: u64) {
        if let Some(o) = owner {
            let u = self.by_owner.entry(o.to_owned()).or_default();
            u.bytes = u.bytes.saturating_add(bytes);
            u.objects = u.objects.saturating_add(1);
        }
    }

    /// Counts `bytes` more for an object `owner` has already (clips added to an upload).
    pub fn grow(&mut self, owner: Option<&str>, bytes: u64) {
        if let Some(u) = owner.and_then(|o| self.by_owner.get_mut(o)) {
            u.bytes = u.bytes.saturating_add(bytes);
        }
    }

    /// Forgets one object of `bytes` of `owner` (it was deleted).
    pub fn remove(&mut self, owner: Option<&str>, bytes: u64) {
        if let Some(o) = owner
            && let Some(u) = self.by_owner.get_mut(o)
        {
            u.bytes = u.bytes.saturating_sub(bytes);
            u.objects = u.objects.saturating_sub(1);
            if u.objects == 0 {
                self.by_owner.remove(o);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn counts_per_owner_and_forgets_deleted_objects() {
        let mut o = Owners::default();
        o.add(Some("alice"), 100);
        o.add(Some("alice"), 50);
        o.add(Some("bob"), 7);
        o.add(None, 1_000);
        assert_eq!(
            o.usage(Some("alice")),
            Usage {
                bytes: 150,
                objects: 2
            }
        );
        assert_eq!(o.usage(None), Usage::default());
        o.remove(Some("alice"), 100);
        assert_eq!(
            o.usage(Some("alice")),
            Usage {
                bytes: 50,
                objects: 1
            }
        );
        o.remove(Some("alice"), 50);
        assert!(!o.by_owner.contains_key("alice"));
        assert_eq!(o.usage(Some("bob")).bytes, 7);
    }
}
