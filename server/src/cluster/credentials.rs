//! Credentials in `--nats` URLs: `nats://user:password@host:port` or `nats://token@host:port`
//! (the forms the NATS tools take). They are taken out of the URLs and given to the client as
//! its connect options — async-nats does not read them from a URL — and every URL the server
//! prints or logs is [`redact`]ed.

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
}
