//! How this server authenticates to NATS and checks the NATS server: credentials in `--nats`
//! URLs — `nats://user:password@host:port` or `nats://token@host:port` (the forms the NATS
//! tools take), taken out of the URLs, and every URL the server prints or logs is
//! [`redact`]ed — or from the `--nats-creds`, `--nats-nkey`, `--nats-user`/`--nats-password`,
//! `--nats-token` flags, and TLS from `--nats-tls-ca`, `--nats-tls-cert`/`--nats-tls-key`
//! ([`NatsSecurity`]). All of them become async-nats's own connect options ([`options`]).

use crate::config::NatsSecurity;
use std::path::Path;

/// What a NATS server may ask a client for.
#[derive(Clone, PartialEq, Eq)]
pub(super) enum Auth {
    /// `--user`/`--pass` on nats-server (or `authorization { user, password }`).
    UserPassword(String, String),
    /// `--auth` on nats-server (or `authorization { token }`).
    Token(String),
}

impl std::fmt::Debug for Auth {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::UserPassword(user, _) => write!(f, "UserPassword({user}, ***)"),
            Self::Token(_) => write!(f, "Token(***)"),
        }
    }
}

/// `url` split into the URL without its user information and the credentials it held.
fn split(url: &str) -> Result<(String, Option<Auth>), String> {
    let (scheme, rest) = match url.split_once("://") {
        Some((scheme, rest)) => (Some(scheme), rest),
        None => (None, url),
    };
    // The user information ends at the last '@' before the path: a password may hold '@'
    // only percent-encoded, as in any URL, but a stray one is still not printed.
    let authority_end = rest.find(['/', '?', '#']).unwrap_or(rest.len());
    let (authority, path) = rest.split_at(authority_end);
    let Some((userinfo, host)) = authority.rsplit_once('@') else {
        return Ok((url.to_owned(), None));
    };
    let plain = match scheme {
        Some(scheme) => format!("{scheme}://{host}{path}"),
        None => format!("{host}{path}"),
    };
    let auth = match userinfo.split_once(':') {
        Some((user, password)) => Auth::UserPassword(decode(user)?, decode(password)?),
        None => Auth::Token(decode(userinfo)?),
    };
    Ok((plain, Some(auth)))
}

/// Percent-decoding (RFC 3986 §2.1) of a URL's user or password.
fn decode(s: &str) -> Result<String, String> {
    let mut out = Vec::with_capacity(s.len());
    let mut bytes = s.bytes();
    while let Some(b) = bytes.next() {
        if b == b'%' {
            let hex = [bytes.next(), bytes.next()];
            let value = match hex {
                [Some(h), Some(l)] => std::str::from_utf8(&[h, l])
                    .ok()
                    .and_then(|x| u8::from_str_radix(x, 16).ok()),
                _ => None,
            };
            out.push(
                value.ok_or("a '%' in the URL's credentials is not followed by two hex digits")?,
            );
        } else {
            out.push(b);
        }
    }
    String::from_utf8(out).map_err(|_| "the URL's credentials are not UTF-8".to_owned())
}

/// The URLs without credentials, and the one set of credentials they carry (every URL that
/// carries any must carry the same: the client sends one set to whichever server it reaches).
///
/// # Errors
/// URLs with different credentials, or credentials that do not decode; the message holds no
/// secret.
pub(super) fn take(urls: &[String]) -> Result<(Vec<String>, Option<Auth>), String> {
    let mut plain = Vec::with_capacity(urls.len());
    let mut auth: Option<Auth> = None;
    for url in urls {
        let (p, a) = split(url).map_err(|e| format!("{}: {e}", redact(url)))?;
        if let Some(a) = a {
            if auth.as_ref().is_some_and(|known| known != &a) {
                return Err(
                    "the --nats URLs carry different credentials: give every URL the same".into(),
                );
            }
            auth = Some(a);
        }
        plain.push(p);
    }
    Ok((plain, auth))
}

/// The connect options for `security` and the credentials `from_urls` held: one way to
/// authenticate at most, TLS when any TLS file is given. Files are read (and checked to
/// exist) here, so a wrong path fails the start with its name rather than a handshake error.
///
/// # Errors
/// Two ways to authenticate, a user without a password (or the reverse), a client
/// certificate without its key (or the reverse), a file that cannot be read or holds no
/// seed. The message names the flag and file, never a secret.
pub(super) async fn options(
    from_urls: Option<Auth>,
    security: &NatsSecurity,
) -> Result<async_nats::ConnectOptions, String> {
    let mut ways = Vec::new();
    if from_urls.is_some() {
        ways.push("credentials in the --nats URLs");
    }
    if security.creds.is_some() {
        ways.push("--nats-creds");
    }
    if security.nkey.is_some() {
        ways.push("--nats-nkey");
    }
    if security.user.is_some() || security.password.is_some() {
        ways.push("--nats-user/--nats-password");
    }
    if security.token.is_some() {
        ways.push("--nats-token");
    }
    if ways.len() > 1 {
        return Err(format!(
            "give one way to authenticate to NATS, not {}",
            ways.join(" and ")
        ));
    }
    let mut options = match (&security.user, &security.password) {
        (Some(user), Some(password)) => {
            async_nats::ConnectOptions::with_user_and_password(user.clone(), password.clone())
        }
        (Some(_), None) => return Err("--nats-user needs --nats-password".into()),
        (None, Some(_)) => return Err("--nats-password needs --nats-user".into()),
        (None, None) => async_nats::ConnectOptions::new(),
    };
    if let Some(token) = &security.token {
        options = options.token(token.clone());
    }
    match from_urls {
        Some(Auth::UserPassword(user, password)) => {
            options = options.user_and_password(user, password);
        }
        Some(Auth::Token(token)) => options = options.token(token),
        None => {}
    }
    if let Some(path) = &security.nkey {
        options = options.nkey(read_seed(path)?);
    }
    if let Some(path) = &security.creds {
        readable("--nats-creds", path)?;
        options = options
            .credentials_file(path)
            .await
            .map_err(|e| format!("--nats-creds {}: {e}", path.display()))?;
    }
    if let Some(ca) = &security.tls_ca {
        readable("--nats-tls-ca", ca)?;
        options = options.add_root_certificates(ca.clone());
    }
    match (&security.tls_cert, &security.tls_key) {
        (Some(cert), Some(key)) => {
            readable("--nats-tls-cert", cert)?;
            readable("--nats-tls-key", key)?;
            options = options.add_client_certificate(cert.clone(), key.clone());
        }
        (Some(_), None) => return Err("--nats-tls-cert needs --nats-tls-key".into()),
        (None, Some(_)) => return Err("--nats-tls-key needs --nats-tls-cert".into()),
        (None, None) => {}
    }
    if security.tls() {
        options = options.require_tls(true);
    }
    Ok(options)
}

fn readable(flag: &str, path: &Path) -> Result<(), String> {
    std::fs::File::open(path)
        .map(drop)
        .map_err(|e| format!("{flag} {}: {e}", path.display()))
}

/// The nkey seed in `path`: its first line that is not empty or a comment (`nsc` and
/// `nk -gen user` write the seed alone; a `.creds` file goes to `--nats-creds`).
fn read_seed(path: &Path) -> Result<String, String> {
    let text = std::fs::read_to_string(path)
        .map_err(|e| format!("--nats-nkey {}: {e}", path.display()))?;
    let seed = text
        .lines()
        .map(str::trim)
        .find(|l| !l.is_empty() && !l.starts_with('#') && !l.starts_with("//"))
        .ok_or_else(|| format!("--nats-nkey {}: the file holds no seed", path.display()))?;
    // A user seed is "SU" and 56 more base32 characters; anything else would only fail in
    // the handshake, with a less helpful message (and the seed is never printed).
    if !seed.starts_with("SU")
        || seed.len() != 58
        || !seed
            .bytes()
            .all(|b| b.is_ascii_uppercase() || b.is_ascii_digit())
    {
        return Err(format!(
            "--nats-nkey {}: not an nkey user seed (\"SU\" and 56 base32 characters; nk -gen user)",
            path.display()
        ));
    }
    Ok(seed.to_owned())
}

/// `url` as it may be printed: user information replaced (`nats://***@host:4222`, the user
/// name kept before a password: `nats://user:***@host:4222`).
#[must_use]
pub fn redact(url: &str) -> String {
    match split(url) {
        Ok((_, None)) => url.to_owned(),
        Ok((plain, Some(auth))) => plain_with(&plain, auth),
        Err(_) => "<a NATS URL with unreadable credentials>".into(),
    }
}

fn plain_with(plain: &str, auth: Auth) -> String {
    let shown = match auth {
        Auth::UserPassword(user, _) => format!("{user}:***@"),
        Auth::Token(_) => "***@".into(),
    };
    match plain.split_once("://") {
        Some((scheme, rest)) => format!("{scheme}://{shown}{rest}"),
        None => format!("{shown}{plain}"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// User and password, a token, no credentials; percent-decoding; the printed forms never
    /// hold the secret.
    #[test]
    fn credentials_are_taken_out_and_never_printed() {
        let urls = vec![
            "nats://posecast:s%40cret@127.0.0.1:4222".to_owned(),
            "nats://posecast:s%40cret@10.0.0.2".to_owned(),
        ];
        let (plain, auth) = take(&urls).unwrap();
        assert_eq!(plain, ["nats://127.0.0.1:4222", "nats://10.0.0.2"]);
        assert_eq!(
            auth,
            Some(Auth::UserPassword("posecast".into(), "s@cret".into()))
        );
        assert_eq!(redact(&urls[0]), "nats://posecast:***@127.0.0.1:4222");
        assert!(!format!("{auth:?}").contains("cret"));

        let (plain, auth) = take(&["nats://t0k3n@host:4222/".to_owned()]).unwrap();
        assert_eq!(plain, ["nats://host:4222/"]);
        assert_eq!(auth, Some(Auth::Token("t0k3n".into())));
        assert_eq!(redact("nats://t0k3n@host:4222/"), "nats://***@host:4222/");

        let (plain, auth) = take(&["127.0.0.1:4222".to_owned()]).unwrap();
        assert_eq!((plain, auth), (vec!["127.0.0.1:4222".to_owned()], None));
        assert_eq!(redact("nats://h:1"), "nats://h:1");

        let mixed = ["nats://a:b@h".to_owned(), "nats://a:c@h".to_owned()];
        let e = take(&mixed).unwrap_err();
        assert!(!e.contains(":b") && !e.contains(":c"), "{e}");
        let bad = take(&["nats://u:pa%zzss@h".to_owned()]).unwrap_err();
        assert!(!bad.contains("pa"), "{bad}");
    }

    #[tokio::test]
    async fn one_way_to_authenticate_and_files_that_exist() {
        let dir = tempfile::tempdir().unwrap();
        let seed_file = dir.path().join("posecast.nk");
        let seed = format!("SU{}", "A".repeat(56));
        std::fs::write(&seed_file, format!("# posecast's seed\n{seed}\n")).unwrap();
        assert_eq!(read_seed(&seed_file).unwrap(), seed);
        let security = NatsSecurity {
            nkey: Some(seed_file.clone()),
            ..NatsSecurity::default()
        };
        assert!(options(None, &security).await.is_ok());
        let e = options(Some(Auth::Token("t".into())), &security)
            .await
            .err()
            .unwrap();
        assert!(e.contains("one way") && e.contains("--nats-nkey"), "{e}");

        let bad_seed = dir.path().join("bad.nk");
        std::fs::write(&bad_seed, "SAsecretsecret\n").unwrap();
        let e = read_seed(&bad_seed).unwrap_err();
        assert!(
            e.contains("not an nkey user seed") && !e.contains("secret"),
            "{e}"
        );
        std::fs::write(&bad_seed, "\n# nothing\n").unwrap();
        assert!(read_seed(&bad_seed).unwrap_err().contains("holds no seed"));

        let missing = dir.path().join("missing.pem");
        let cases: [(NatsSecurity, &str); 5] = [
            (
                NatsSecurity {
                    user: Some("u".into()),
                    ..NatsSecurity::default()
                },
                "--nats-user needs --nats-password",
            ),
            (
                NatsSecurity {
                    tls_cert: Some(seed_file.clone()),
                    ..NatsSecurity::default()
                },
                "--nats-tls-cert needs --nats-tls-key",
            ),
            (
                NatsSecurity {
                    tls_ca: Some(missing.clone()),
                    ..NatsSecurity::default()
                },
                "--nats-tls-ca",
            ),
            (
                NatsSecurity {
                    creds: Some(missing.clone()),
                    ..NatsSecurity::default()
                },
                "--nats-creds",
            ),
            (
                NatsSecurity {
                    token: Some("t0k3n".into()),
                    password: Some("hunter2".into()),
                    user: Some("u".into()),
                    ..NatsSecurity::default()
                },
                "one way",
            ),
        ];
        for (security, says) in cases {
            let e = options(None, &security).await.err().unwrap();
            assert!(e.contains(says), "{security:?}: {e}");
            assert!(!e.contains("hunter2") && !e.contains("t0k3n"), "{e}");
        }
    }
}
