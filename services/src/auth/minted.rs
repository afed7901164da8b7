//! Minted tokens (issue 39): an app's back end asks for a token when a user joins
//! (`POST /api/tokens` with an admin token) and hands it to that user's browser or headset.
//!
//! A minted token is self-contained and signed: `pc1.` + base64url(its claims as JSON) + `.` +
//! base64url(HMAC-SHA256 over the first two parts). Any server holding the same key accepts
//! it without a shared token file; the key comes from `--token-key`, else from
//! `--cluster-secret` (so a signed cluster accepts its own tokens everywhere), else from
//! `DATA/token-key` (made on the first start, mode 0600), else from memory (tokens then die
//! with the process). What the server keeps is the claims of the tokens it minted (for
//! `GET /api/tokens`) and the ids of revoked ones, in `DATA/tokens.json`, pruned of expired
//! entries; a revoked or expired token is refused at once, and connections holding it are
//! closed (`service::ws`).

use crate::store::atomic::write_atomic;
use base64::Engine as _;
use base64::engine::general_purpose::URL_SAFE_NO_PAD;
use posecast_core::error::Error;
use posecast_proto::tokens::{
    DEFAULT_TTL_S, MAX_LISTED, MAX_NAME_CHARS, MAX_TTL_S, MintRequest, MintedToken, TokenInfo,
};
use ring::hmac;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::{Mutex, MutexGuard, PoisonError, RwLock};
use std::time::{SystemTime, UNIX_EPOCH};
use tokio::sync::watch;

use super::Secret;

/// What every minted token starts with (and the version of its format).
pub const PREFIX: &str = "pc1.";
/// Longest token text looked at: longer ones are refused before any decoding.
pub const MAX_TOKEN_CHARS: usize = 8192;
/// Shortest `--token-key`.
pub const MIN_KEY_CHARS: usize = 32;

/// Where the signing key came from (logged at start).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum KeySource {
    /// `--token-key`.
    Flag,
    /// Derived from `--cluster-secret`.
    ClusterSecret,
    /// `DATA/token-key`.
    DataFolder,
    /// A random key for this process only.
    Memory,
}

/// Mints, checks and revokes tokens (one per server, in [`super::AccessConfig::mint`]).
pub struct Minter {
    key: RwLock<hmac::Key>,
    book: Mutex<Book>,
    file: Mutex<Option<PathBuf>>,
    /// Bumped at every revocation: connections holding a minted token wait on it.
    revoked: watch::Sender<u64>,
}

impl std::fmt::Debug for Minter {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Minter").finish_non_exhaustive()
    }
}

/// `DATA/tokens.json`.
#[derive(Debug, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct Book {
    /// Tokens minted here, by id.
    issued: BTreeMap<String, TokenInfo>,
    /// Revoked ids → when they would have expired (then the entry is dropped).
    revoked: BTreeMap<String, u64>,
}

impl Book {
    fn prune(&mut self, now: u64) {
        self.issued.retain(|_, t| t.expires_at > now);
        self.revoked.retain(|_, &mut expires| expires > now);
    }
}

impl Default for Minter {
    fn default() -> Self {
        Self::new()
    }
}

impl Minter {
    /// A minter with a random key held in memory (until [`Minter::open`]).
    #[must_use]
    pub fn new() -> Self {
        let key: [u8; 32] = rand::random();
        Self {
            key: RwLock::new(hmac::Key::new(hmac::HMAC_SHA256, &key)),
            book: Mutex::new(Book::default()),
            file: Mutex::new(None),
            revoked: watch::Sender::new(0),
        }
    }

    /// Chooses the signing key (see the module documentation) and reads `DATA/tokens.json`.
    ///
    /// # Errors
    /// The key file or the tokens file cannot be read or written, or holds something else
    /// than this module writes (the error names the file: revocations are not ignored).
    pub fn open(
        &self,
        token_key: Option<&Secret>,
        cluster_secret: Option<&Secret>,
        data_dir: Option<&Path>,
    ) -> std::io::Result<KeySource> {
        let (key, source) = if let Some(k) = token_key {
            (k.expose().as_bytes().to_vec(), KeySource::Flag)
        } else if let Some(s) = cluster_secret {
            let derive = hmac::Key::new(hmac::HMAC_SHA256, s.expose().as_bytes());
            let tag = hmac::sign(&derive, b"posecast minted-token key v1");
            (tag.as_ref().to_vec(), KeySource::ClusterSecret)
        } else if let Some(dir) = data_dir {
            (
                read_or_make_key(&dir.join("token-key"))?,
                KeySource::DataFolder,
            )
        } else {
            (rand::random::<[u8; 32]>().to_vec(), KeySource::Memory)
        };
        *self.key.write().unwrap_or_else(PoisonError::into_inner) =
            hmac::Key::new(hmac::HMAC_SHA256, &key);
        if let Some(dir) = data_dir {
            let path = dir.join("tokens.json");
            match std::fs::read(&path) {
                Ok(bytes) => {
                    let stored: Book = serde_json::from_slice(&bytes).map_err(|e| {
                        std::io::Error::new(
                            std::io::ErrorKind::InvalidData,
                            format!("{}: not a tokens file: {e}", path.display()),
                        )
                    })?;
                    // Added to what is known already: a cluster's revocations may have come
                    // first.
                    let mut book = self.book();
                    book.issued.extend(stored.issued);
                    book.revoked.extend(stored.revoked);
                    let revoked: Vec<String> = book.revoked.keys().cloned().collect();
                    for id in revoked {
                        book.issued.remove(&id);
                    }
                }
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
                Err(e) => {
                    return Err(std::io::Error::new(
                        e.kind(),
                        format!("cannot read {}: {e}", path.display()),
                    ));
                }
            }
            *self.file.lock().unwrap_or_else(PoisonError::into_inner) = Some(path);
        }
        Ok(source)
    }

    fn book(&self) -> MutexGuard<'_, Book> {
        self.book.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Writes the book (pruned) to `DATA/tokens.json`, if there is a data folder.
    fn persist(&self, book: &mut Book) -> Result<(), Error> {
        book.prune(now_s());
        let file = self.file.lock().unwrap_or_else(PoisonError::into_inner);
        let Some(path) = file.as_ref() else {
            return Ok(());
        };
        let bytes = serde_json::to_vec_pretty(&*book)
            .map_err(|e| Error::Internal(format!("tokens file: {e}")))?;
        write_atomic(path, &bytes).map_err(|e| Error::storing("storing the tokens file", &e))
    }

    /// Mints a token for `request`. `configured` tells whether a name is a configured token's
    /// (refused: a minted token must not own what an operator's token made).
    ///
    /// # Errors
    /// `invalid_value` for a request outside the limits ([`posecast_proto::tokens`]); the
    /// store's error when the tokens file cannot be written (nothing is minted then).
    pub fn mint(
        &self,
        request: MintRequest,
        configured: impl Fn(&str) -> bool,
    ) -> Result<MintedToken, Error> {
        validate(&request, &configured)?;
        let now = now_s();
        let ttl = request.ttl_s.unwrap_or(DEFAULT_TTL_S);
        let mut rights = request.rights;
        rights.sort_unstable();
        rights.dedup();
        let id_bytes: [u8; 12] = rand::random();
        let info = TokenInfo {
            id: id_bytes.iter().map(|b| format!("{b:02x}")).collect(),
            name: request.name,
            rights,
            scenes: request.scenes,
            avatars: request.avatars,
            issued_at: now,
            expires_at: now + ttl,
            max_bytes: request.max_bytes,
            max_objects: request.max_objects,
        };
        let token = self.sign(&info)?;
        if token.len() > MAX_TOKEN_CHARS {
            return Err(Error::invalid(format!(
                "the token would be {} characters, more than the {MAX_TOKEN_CHARS} a server \
                 accepts: list fewer or shorter scenes and avatars",
                token.len()
            )));
        }
        let mut book = self.book();
        book.issued.insert(info.id.clone(), info.clone());
        if let Err(e) = self.persist(&mut book) {
            book.issued.remove(&info.id);
            return Err(e);
        }
        Ok(MintedToken { token, info })
    }

    fn sign(&self, info: &TokenInfo) -> Result<String, Error> {
        let claims =
            serde_json::to_vec(info).map_err(|e| Error::Internal(format!("token claims: {e}")))?;
        let mut text = String::from(PREFIX);
        URL_SAFE_NO_PAD.encode_string(claims, &mut text);
        let tag = hmac::sign(
            &self.key.read().unwrap_or_else(PoisonError::into_inner),
            text.as_bytes(),
        );
        text.push('.');
        URL_SAFE_NO_PAD.encode_string(tag.as_ref(), &mut text);
        Ok(text)
    }

    /// The claims of `token` if it is one this server's key signed, not expired and not
    /// revoked.
    ///
    /// # Errors
    /// `unauthorized`, saying whether the token is not valid, expired or revoked.
    pub fn verify(&self, token: &str) -> Result<TokenInfo, Error> {
        let invalid = || Error::Unauthorized("the token is not valid on this server".into());
        if token.len() > MAX_TOKEN_CHARS || !token.starts_with(PREFIX) {
            return Err(invalid());
        }
        let (signed, tag) = token.rsplit_once('.').ok_or_else(invalid)?;
        let tag = URL_SAFE_NO_PAD.decode(tag).map_err(|_| invalid())?;
        hmac::verify(
            &self.key.read().unwrap_or_else(PoisonError::into_inner),
            signed.as_bytes(),
            &tag,
        )
        .map_err(|_| invalid())?;
        let claims = URL_SAFE_NO_PAD
            .decode(&signed[PREFIX.len()..])
            .map_err(|_| invalid())?;
        let info: TokenInfo = serde_json::from_slice(&claims).map_err(|_| invalid())?;
        self.check(&info)?;
        Ok(info)
    }

    /// Whether `info` is still good: not expired, not revoked.
    ///
    /// # Errors
    /// `unauthorized` naming the token and why.
    pub fn check(&self, info: &TokenInfo) -> Result<(), Error> {
        if now_s() >= info.expires_at {
            return Err(Error::Unauthorized(format!(
                "token {} ({}) expired",
                info.id, info.name
            )));
        }
        if self.is_revoked(&info.id) {
            return Err(Error::Unauthorized(format!(
                "token {} ({}) was revoked",
                info.id, info.name
            )));
        }
        Ok(())
    }

    /// Whether `id` was revoked.
    #[must_use]
    pub fn is_revoked(&self, id: &str) -> bool {
        self.book().revoked.contains_key(id)
    }

    /// Revokes the token `id` (minted here or by another server with the same key; it stays
    /// revoked until it would have expired). Returns what is known of it, if it was minted
    /// here.
    ///
    /// # Errors
    /// `invalid_value` for an id that no token can have; the store's error when the tokens
    /// file cannot be written (the token is refused from now on all the same).
    pub fn revoke(&self, id: &str) -> Result<Option<TokenInfo>, Error> {
        if id.len() != 24 || !id.bytes().all(|b| b.is_ascii_hexdigit()) {
            return Err(Error::invalid(format!(
                "{id:?} is not a token id (24 hexadecimal digits)"
            )));
        }
        let id = id.to_ascii_lowercase();
        let mut book = self.book();
        let known = book.issued.remove(&id);
        let expires = known.as_ref().map_or(now_s() + MAX_TTL_S, |t| t.expires_at);
        book.revoked.insert(id, expires);
        let stored = self.persist(&mut book);
        drop(book);
        self.revoked.send_modify(|n| *n += 1);
        stored.map(|()| known)
    }

    /// Until when `id` stays revoked (when it would have expired), if it is revoked.
    #[must_use]
    pub fn revoked_until(&self, id: &str) -> Option<u64> {
        self.book().revoked.get(id).copied()
    }

    /// Revokes `id` until `until` as another server of the cluster did (`crate::cluster`):
    /// like [`Minter::revoke`], without telling the cluster again.
    ///
    /// # Errors
    /// As [`Minter::revoke`].
    pub fn revoke_until(&self, id: &str, until: u64) -> Result<(), Error> {
        let mut book = self.book();
        if book.revoked.contains_key(id) || until <= now_s() {
            return Ok(());
        }
        book.issued.remove(id);
        book.revoked.insert(id.to_owned(), until);
        let stored = self.persist(&mut book);
        drop(book);
        self.revoked.send_modify(|n| *n += 1);
        stored
    }

    /// The tokens minted here that are neither expired nor revoked.
    #[must_use]
    pub fn list(&self) -> Vec<TokenInfo> {
        let now = now_s();
        let book = self.book();
        book.issued
            .values()
            .filter(|t| t.expires_at > now && !book.revoked.contains_key(&t.id))
            .cloned()
            .collect()
    }

    /// Resolves once `info` is revoked or expired, with the reason.
    pub async fn ended(&self, info: &TokenInfo) -> Error {
        let mut changes = self.revoked.subscribe();
        loop {
            if let Err(e) = self.check(info) {
                return e;
            }
            let left = info.expires_at.saturating_sub(now_s());
            tokio::select! {
                () = tokio::time::sleep(std::time::Duration::from_secs(left)) => {}
                r = changes.changed() => {
                    if r.is_err() {
                        // The minter is gone (the server stops): only the expiry is left.
                        tokio::time::sleep(std::time::Duration::from_secs(left)).await;
                    }
                }
            }
        }
    }
}

fn validate(request: &MintRequest, configured: &impl Fn(&str) -> bool) -> Result<(), Error> {
    let invalid = |m: String| Err(Error::invalid(m));
    let chars = request.name.chars().count();
    if chars == 0 || chars > MAX_NAME_CHARS || request.name.chars().any(char::is_control) {
        return invalid(format!(
            "name: 1 to {MAX_NAME_CHARS} characters, no control characters"
        ));
    }
    if configured(&request.name) {
        return invalid(format!(
            "name {:?} is a configured token's; choose another",
            request.name
        ));
    }
    if request.rights.is_empty() {
        return invalid("rights: at least one of view, control, drive, upload, record".into());
    }
    if let Some(ttl) = request.ttl_s
        && !(1..=MAX_TTL_S).contains(&ttl)
    {
        return invalid(format!("ttl_s: 1 to {MAX_TTL_S} seconds, not {ttl}"));
    }
    for (what, n) in [
        ("scenes", request.scenes.as_ref().map(Vec::len)),
        ("avatars", request.avatars.as_ref().map(Vec::len)),
    ] {
        if n.is_some_and(|n| n > MAX_LISTED) {
            return invalid(format!("{what}: at most {MAX_LISTED}"));
        }
    }
    Ok(())
}

/// Reads the key file, or makes it (32 random bytes as hex, readable by its owner only).
fn read_or_make_key(path: &Path) -> std::io::Result<Vec<u8>> {
    match std::fs::read_to_string(path) {
        Ok(text) => {
            let text = text.trim();
            if text.len() < MIN_KEY_CHARS {
                return Err(std::io::Error::new(
                    std::io::ErrorKind::InvalidData,
                    format!(
                        "{}: a token key of at least {MIN_KEY_CHARS} characters",
                        path.display()
                    ),
                ));
            }
            Ok(text.as_bytes().to_vec())
        }
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            let key = Secret::generate();
            let text = format!("{}{}\n", key.expose(), Secret::generate().expose());
            if let Some(dir) = path.parent() {
                std::fs::create_dir_all(dir)?;
            }
            write_atomic(path, text.as_bytes())
                .map_err(|e| std::io::Error::new(e.kind(), format!("{}: {e}", path.display())))?;
            #[cfg(unix)]
            {
                use std::os::unix::fs::PermissionsExt;
                std::fs::set_permissions(path, std::fs::Permissions::from_mode(0o600))?;
            }
            Ok(text.trim().as_bytes().to_vec())
        }
        Err(e) => Err(std::io::Error::new(
            e.kind(),
            format!("cannot read {}: {e}", path.display()),
        )),
    }
}

fn now_s() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_secs())
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use posecast_proto::msg::{ErrorCode, SceneId};
    use posecast_proto::tokens::Right;

    fn request(name: &str, rights: &[Right]) -> MintRequest {
        MintRequest {
            name: name.into(),
            rights: rights.to_vec(),
            scenes: Some(vec![SceneId("lobby".into())]),
            avatars: None,
            ttl_s: Some(600),
            max_bytes: None,
            max_objects: None,
        }
    }

    #[test]
    fn minted_tokens_verify_and_tampered_ones_do_not() {
        let m = Minter::new();
        let t = m
            .mint(request("alice", &[Right::Drive, Right::View]), |_| false)
            .unwrap();
        assert!(t.token.starts_with(PREFIX));
        let info = m.verify(&t.token).unwrap();
        assert_eq!(info, t.info);
        assert_eq!(info.rights, vec![Right::View, Right::Drive]);
        assert_eq!(info.expires_at - info.issued_at, 600);

        // Claims edited (more rights, a longer life): the signature no longer matches.
        let mut forged = t.info.clone();
        forged.rights.push(Right::Upload);
        let (_, tag) = t.token.rsplit_once('.').unwrap();
        let claims = URL_SAFE_NO_PAD.encode(serde_json::to_vec(&forged).unwrap());
        let edited = format!("{PREFIX}{claims}.{tag}");
        assert_eq!(
            m.verify(&edited).unwrap_err().code(),
            ErrorCode::Unauthorized
        );
        // One character of the signature changed.
        let mut flipped = t.token.clone().into_bytes();
        let last = flipped.len() - 1;
        flipped[last] = if flipped[last] == b'A' { b'B' } else { b'A' };
        let flipped = String::from_utf8(flipped).unwrap();
        assert!(m.verify(&flipped).is_err());
        // Another server's key.
        assert!(Minter::new().verify(&t.token).is_err());
        for junk in ["", "pc1.", "pc1..", "pc1.%%%.###", "pc2.abc.def"] {
            assert!(m.verify(junk).is_err(), "{junk:?}");
        }
    }

    #[test]
    fn revoked_and_expired_tokens_are_refused() {
        let m = Minter::new();
        let t = m.mint(request("bob", &[Right::View]), |_| false).unwrap();
        assert_eq!(m.list().len(), 1);
        assert_eq!(m.revoke(&t.info.id).unwrap().unwrap().name, "bob");
        let e = m.verify(&t.token).unwrap_err();
        assert!(e.to_string().contains("revoked"), "{e}");
        assert!(m.list().is_empty());
        assert!(m.revoke("not-an-id").is_err());

        let mut old = t.info.clone();
        old.id = "00".repeat(12);
        old.expires_at = now_s();
        let token = m.sign(&old).unwrap();
        assert!(
            m.verify(&token)
                .unwrap_err()
                .to_string()
                .contains("expired")
        );
    }

    #[test]
    fn requests_outside_the_limits_are_refused() {
        let m = Minter::new();
        let configured = |n: &str| n == "admin";
        for (r, why) in [
            (request("", &[Right::View]), "name"),
            (request("a\nb", &[Right::View]), "name"),
            (request(&"x".repeat(65), &[Right::View]), "name"),
            (request("admin", &[Right::View]), "configured"),
            (request("carol", &[]), "rights"),
            (
                MintRequest {
                    scenes: Some(vec![SceneId("s".repeat(100)); MAX_LISTED]),
                    ..request("carol", &[Right::View])
                },
                "characters",
            ),
            (
                MintRequest {
                    ttl_s: Some(u64::MAX),
                    ..request("carol", &[Right::View])
                },
                "ttl_s",
            ),
            (
                MintRequest {
                    ttl_s: Some(0),
                    ..request("carol", &[Right::View])
                },
                "ttl_s",
            ),
            (
                MintRequest {
                    ttl_s: Some(MAX_TTL_S + 1),
                    ..request("carol", &[Right::View])
                },
                "ttl_s",
            ),
        ] {
            let e = m.mint(r, configured).unwrap_err();
            assert_eq!(e.code(), ErrorCode::InvalidValue);
            assert!(e.to_string().contains(why), "{e}");
        }
        assert!(m.list().is_empty());
    }

    #[test]
    fn the_book_and_the_key_survive_a_restart() {
        let dir = tempfile::tempdir().unwrap();
        let m = Minter::new();
        assert_eq!(
            m.open(None, None, Some(dir.path())).unwrap(),
            KeySource::DataFolder
        );
        let kept = m.mint(request("dan", &[Right::View]), |_| false).unwrap();
        let gone = m.mint(request("eve", &[Right::View]), |_| false).unwrap();
        m.revoke(&gone.info.id).unwrap();

        let again = Minter::new();
        again.open(None, None, Some(dir.path())).unwrap();
        assert_eq!(again.verify(&kept.token).unwrap().name, "dan");
        assert!(again.verify(&gone.token).is_err());
        assert_eq!(again.list().len(), 1);

        // The same cluster secret gives the same key on every server, without a file.
        let secret = Secret::new("a-cluster-secret-of-some-length");
        let (a, b) = (Minter::new(), Minter::new());
        a.open(None, Some(&secret), None).unwrap();
        b.open(None, Some(&secret), None).unwrap();
        let t = a.mint(request("fay", &[Right::View]), |_| false).unwrap();
        assert_eq!(b.verify(&t.token).unwrap().name, "fay");

        std::fs::write(dir.path().join("tokens.json"), b"{not json").unwrap();
        let e = Minter::new()
            .open(None, None, Some(dir.path()))
            .unwrap_err();
        assert!(e.to_string().contains("tokens.json"), "{e}");
    }
}
