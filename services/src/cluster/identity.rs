//! Who sent a message on a scene's relay subject, and whether to believe it (issue 36).
//!
//! Every relay message (`avatars`, `frame`, `change`, `deleted`) carries the sending node's
//! name (`Posecast-Node`) and its epoch (`Posecast-Epoch`); with a cluster secret
//! (`--cluster-secret`) also an HMAC-SHA256 (`Posecast-Mac`) over the subject, kind, epoch, node and
//! payload, so a client that can publish on NATS — a compromised NATS account, a leaked
//! password — cannot speak for a node without the secret. A relay believes a message only
//! from the node that holds the scene's lease and with an epoch that lease can have made
//! (never above the lease's revision): see `relay.rs`.

use crate::auth::Secret;
use bytes::Bytes;
use ring::hmac;
use subtle::ConstantTimeEq;

/// Header with the name of the node that sent a relay message.
pub(super) const NODE: &str = "Posecast-Node";
/// Header with the message's HMAC-SHA256 under the cluster secret, lowercase hex.
pub(super) const MAC: &str = "Posecast-Mac";

/// Why a relay message was not believed (the label of
/// `posecast_cluster_relay_refused_total`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Refused {
    /// A cluster secret is set and the MAC is missing or wrong.
    Signature,
    /// Sent by a node that does not hold the scene's lease (or by nobody).
    NotOwner,
    /// An epoch the lease cannot have made (unreadable, or above its revision).
    Epoch,
    /// `deleted` while the scene is still in the cluster's bucket.
    NotDeleted,
}

impl Refused {
    /// Every reason, in the order of the counters.
    pub const ALL: [Self; 4] = [
        Self::Signature,
        Self::NotOwner,
        Self::Epoch,
        Self::NotDeleted,
    ];

    /// The label in `/metrics`.
    #[must_use]
    pub fn label(self) -> &'static str {
        match self {
            Self::Signature => "signature",
            Self::NotOwner => "not_owner",
            Self::Epoch => "epoch",
            Self::NotDeleted => "not_deleted",
        }
    }
}

/// What a relay message says of itself.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(super) struct Claim {
    pub(super) kind: String,
    pub(super) epoch: u64,
    pub(super) node: String,
}

/// Signs and checks relay messages; without a secret it only names the node.
#[derive(Clone)]
pub(super) struct Signer {
    key: Option<hmac::Key>,
}

impl std::fmt::Debug for Signer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Signer(secret: {})", self.key.is_some())
    }
}

impl Signer {
    pub(super) fn new(secret: Option<&Secret>) -> Self {
        Self {
            key: secret.map(|s| hmac::Key::new(hmac::HMAC_SHA256, s.expose().as_bytes())),
        }
    }

    fn mac(key: &hmac::Key, subject: &str, claim: &Claim, payload: &[u8]) -> hmac::Tag {
        let mut ctx = hmac::Context::with_key(key);
        for field in [
            subject.as_bytes(),
            claim.kind.as_bytes(),
            &claim.epoch.to_le_bytes(),
            claim.node.as_bytes(),
            payload,
        ] {
            // Length-prefixed, so no two different messages give the same input.
            ctx.update(&(field.len() as u64).to_le_bytes());
            ctx.update(field);
        }
        ctx.sign()
    }

    /// The headers of a relay message on `subject`: kind, epoch, node and, with a secret, MAC.
    pub(super) fn headers(
        &self,
        subject: &str,
        claim: &Claim,
        payload: &Bytes,
    ) -> async_nats::HeaderMap {
        let mut headers = async_nats::HeaderMap::new();
        headers.insert(super::KIND, claim.kind.as_str());
        headers.insert(super::EPOCH, claim.epoch.to_string().as_str());
        headers.insert(NODE, claim.node.as_str());
        if let Some(key) = &self.key {
            let tag = Self::mac(key, subject, claim, payload);
            let hex: String = tag.as_ref().iter().map(|b| format!("{b:02x}")).collect();
            headers.insert(MAC, hex.as_str());
        }
        headers
    }

    /// What `msg` claims, if its MAC holds (or no secret is set).
    ///
    /// # Errors
    /// [`Refused::Signature`]: a secret is set and the MAC is missing or wrong;
    /// [`Refused::Epoch`]: the epoch is not a number.
    pub(super) fn check(&self, msg: &async_nats::Message) -> Result<Claim, Refused> {
        let header = |name: &str| {
            msg.headers
                .as_ref()
                .and_then(|h| h.get(name))
                .map(|v| v.as_str().to_owned())
        };
        let claim = Claim {
            kind: header(super::KIND).unwrap_or_default(),
            epoch: header(super::EPOCH)
                .unwrap_or_default()
                .parse()
                .map_err(|_| Refused::Epoch)?,
            node: header(NODE).unwrap_or_default(),
        };
        if let Some(key) = &self.key {
            let given = header(MAC)
                .and_then(|h| unhex(&h))
                .ok_or(Refused::Signature)?;
            let expected = Self::mac(key, msg.subject.as_str(), &claim, &msg.payload);
            if !bool::from(expected.as_ref().ct_eq(given.as_slice())) {
                return Err(Refused::Signature);
            }
        }
        Ok(claim)
    }
}

fn unhex(s: &str) -> Option<Vec<u8>> {
    if !s.len().is_multiple_of(2) {
        return None;
    }
    (0..s.len())
        .step_by(2)
        .map(|i| u8::from_str_radix(s.get(i..i + 2)?, 16).ok())
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn message(
        subject: &str,
        headers: async_nats::HeaderMap,
        payload: &Bytes,
    ) -> async_nats::Message {
        async_nats::Message {
            subject: subject.into(),
            reply: None,
            payload: payload.clone(),
            headers: Some(headers),
            status: None,
            description: None,
            length: payload.len(),
        }
    }

    #[test]
    fn a_signed_message_checks_and_any_change_to_it_does_not() {
        let secret = Secret::new("cluster-secret-36");
        let signer = Signer::new(Some(&secret));
        let claim = Claim {
            kind: "frame".into(),
            epoch: 42,
            node: "a".into(),
        };
        let payload = Bytes::from_static(b"frame bytes");
        let subject = "posecast.scene.73.relay";
        let headers = signer.headers(subject, &claim, &payload);
        assert_eq!(
            signer.check(&message(subject, headers.clone(), &payload)),
            Ok(claim.clone())
        );
        // Another subject, payload, node, epoch or key: refused.
        let other = Bytes::from_static(b"frame bytez");
        assert_eq!(
            signer.check(&message(subject, headers.clone(), &other)),
            Err(Refused::Signature)
        );
        assert_eq!(
            signer.check(&message(
                "posecast.scene.74.relay",
                headers.clone(),
                &payload
            )),
            Err(Refused::Signature)
        );
        for (name, value) in [
            (NODE, "b"),
            (super::super::EPOCH, "43"),
            (super::super::KIND, "deleted"),
        ] {
            let mut forged = headers.clone();
            forged.insert(name, value);
            assert_eq!(
                signer.check(&message(subject, forged, &payload)),
                Err(Refused::Signature),
                "{name}"
            );
        }
        let stranger = Signer::new(Some(&Secret::new("guess")));
        let forged = stranger.headers(subject, &claim, &payload);
        assert_eq!(
            signer.check(&message(subject, forged, &payload)),
            Err(Refused::Signature)
        );
        // Unsigned: refused with a secret, read without one.
        let unsigned = Signer::new(None).headers(subject, &claim, &payload);
        assert!(!unsigned.iter().any(|(k, _)| k.to_string() == MAC));
        assert_eq!(
            signer.check(&message(subject, unsigned.clone(), &payload)),
            Err(Refused::Signature)
        );
        assert_eq!(
            Signer::new(None).check(&message(subject, unsigned, &payload)),
            Ok(claim)
        );
        // An epoch that is not a number.
        let mut bad = Signer::new(None).headers(
            subject,
            &Claim {
                kind: "frame".into(),
                epoch: 1,
                node: "a".into(),
            },
            &payload,
        );
        bad.insert(super::super::EPOCH, "soon");
        assert_eq!(
            Signer::new(None).check(&message(subject, bad, &payload)),
            Err(Refused::Epoch)
        );
    }
}
