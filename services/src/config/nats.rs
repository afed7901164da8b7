//! How a server of a cluster proves itself to NATS and checks that it talks to the right NATS
//! (`--nats-creds`, `--nats-nkey`, `--nats-user`/`--nats-password`, `--nats-token`,
//! `--nats-tls-ca`, `--nats-tls-cert`/`--nats-tls-key`; `docs/src/how-to/cluster.md`).
//! Given to async-nats as its own connect options by [`crate::cluster::connect`].

use std::path::PathBuf;

/// NATS credentials and TLS files. At most one way to authenticate: a credentials file, an
/// nkey seed file, a user and password, or a token (here or in the `--nats` URLs).
#[derive(Clone, Default, PartialEq, Eq)]
pub struct NatsSecurity {
    /// A `.creds` file (a user JWT and its nkey seed, as `nsc` writes them).
    pub creds: Option<PathBuf>,
    /// A file holding an nkey user seed (`SU…`).
    pub nkey: Option<PathBuf>,
    /// A user name, with [`Self::password`].
    pub user: Option<String>,
    /// The user's password.
    pub password: Option<String>,
    /// A token (nats-server's `authorization { token }`).
    pub token: Option<String>,
    /// CA certificates (PEM) the NATS server's certificate must chain to; turns TLS on.
    pub tls_ca: Option<PathBuf>,
    /// This server's client certificate (PEM), with [`Self::tls_key`]; turns TLS on.
    pub tls_cert: Option<PathBuf>,
    /// The client certificate's private key (PEM).
    pub tls_key: Option<PathBuf>,
}

impl std::fmt::Debug for NatsSecurity {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let secret = |s: &Option<String>| s.as_ref().map(|_| "***");
        f.debug_struct("NatsSecurity")
            .field("creds", &self.creds)
            .field("nkey", &self.nkey)
            .field("user", &self.user)
            .field("password", &secret(&self.password))
            .field("token", &secret(&self.token))
            .field("tls_ca", &self.tls_ca)
            .field("tls_cert", &self.tls_cert)
            .field("tls_key", &self.tls_key)
            .finish()
    }
}

impl NatsSecurity {
    /// Whether any TLS file is given (the connection must then be TLS).
    #[must_use]
    pub fn tls(&self) -> bool {
        self.tls_ca.is_some() || self.tls_cert.is_some() || self.tls_key.is_some()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn secrets_are_not_printed() {
        let s = NatsSecurity {
            user: Some("posecast".into()),
            password: Some("hunter2".into()),
            token: Some("t0k3n".into()),
            ..NatsSecurity::default()
        };
        let shown = format!("{s:?}");
        assert!(shown.contains("posecast"), "{shown}");
        assert!(
            !shown.contains("hunter2") && !shown.contains("t0k3n"),
            "{shown}"
        );
        assert!(!s.tls());
    }
}
