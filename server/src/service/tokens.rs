//! `/api/tokens`: minting, listing and revoking tokens for an app's users (issue 39,
//! [`crate::auth::minted`]). Every route needs an admin token
//! ([`crate::auth::AccessConfig::authorize_admin`]).

use crate::app::AppState;
use crate::auth::{Caller, Minter};
use crate::service::rest::{AppError, Bearer};
use axum::Json;
use axum::body::Bytes;
use axum::extract::{Path, State};
use axum::http::StatusCode;
use posecast_core::error::Error;
use posecast_proto::msg::{ErrorCode, ProtocolError};
use posecast_proto::tokens::{MintRequest, MintedToken, TokenInfo};
use std::sync::Arc;

/// `POST /api/tokens`: mints a token ([`MintRequest`] → 201 [`MintedToken`]).
pub async fn mint(
    State(state): State<Arc<AppState>>,
    Bearer(caller): Bearer,
    body: Bytes,
) -> Result<(StatusCode, Json<MintedToken>), AppError> {
    let minter = admin(&state, &caller, "mint")?;
    let request: MintRequest = serde_json::from_slice(&body).map_err(|e| {
        ProtocolError::new(
            ErrorCode::BadMessage,
            format!("not a valid token request: {e}"),
        )
    })?;
    let access = &state.config.access;
    let minted = minter.mint(request, |name| access.is_configured_name(name));
    audit(&caller, "mint", minted.as_ref().map(|m| &m.info));
    Ok((StatusCode::CREATED, Json(minted?)))
}

/// `GET /api/tokens`: the tokens this server minted that are neither expired nor revoked.
pub async fn list(
    State(state): State<Arc<AppState>>,
    Bearer(caller): Bearer,
) -> Result<Json<Vec<TokenInfo>>, AppError> {
    let minter = admin(&state, &caller, "list")?;
    Ok(Json(minter.list()))
}

/// `DELETE /api/tokens/{id}`: revokes a token (204). Connections holding it are closed.
pub async fn revoke(
    State(state): State<Arc<AppState>>,
    Bearer(caller): Bearer,
    Path(id): Path<String>,
) -> Result<StatusCode, AppError> {
    let minter = admin(&state, &caller, "revoke")?;
    let id = id.to_ascii_lowercase();
    let revoked = minter.revoke(&id);
    tracing::info!(
        target: "posecast::audit",
        op = "revoke_token",
        target = %id,
        caller = caller.name(),
        outcome = %match &revoked {
            Ok(Some(t)) => format!("ok: {}", t.name),
            Ok(None) => "ok: not minted here".to_owned(),
            Err(e) => e.to_string(),
        },
        "token"
    );
    revoked?;
    // Every server of a cluster refuses it before the revocation is acknowledged.
    if let (Some(cluster), Some(until)) = (state.cluster(), minter.revoked_until(&id)) {
        cluster.revoke_token(&id, until).await?;
    }
    Ok(StatusCode::NO_CONTENT)
}

fn admin<'a>(state: &'a AppState, caller: &Caller, op: &str) -> Result<&'a Minter, AppError> {
    let access = &state.config.access;
    if let Err(e) = access.authorize_admin(caller) {
        audit(caller, op, Err(&e));
        return Err(e.into());
    }
    Ok(access.mint.as_deref().ok_or_else(|| {
        Error::Unavailable("this server does not mint tokens (no signing key)".into())
    })?)
}

fn audit(caller: &Caller, op: &str, outcome: Result<&TokenInfo, &Error>) {
    tracing::info!(
        target: "posecast::audit",
        op = %format!("{op}_token"),
        caller = caller.name(),
        outcome = %match outcome {
            Ok(t) => format!("ok: {} ({}) until {}", t.id, t.name, t.expires_at),
            Err(e) => e.to_string(),
        },
        "token"
    );
}
