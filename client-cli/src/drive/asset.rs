//! Making sure the server has the source rig: upload the BVH as an asset, or reuse an asset of
//! that name when it has the same skeleton.

use anyhow::{Context, bail};
use posecast_client::net::Driver;
use posecast_client::view_source::fetch;
use posecast_proto::command::{AssetInfo, Command};
use posecast_proto::msg::MAX_ID_LEN;

/// What [`ensure`] did.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Outcome {
    /// The file was uploaded as a new asset.
    Uploaded,
    /// An asset of that name with as many joints was there already.
    Reused,
}

/// An asset name from a file stem: the id rules' characters (letters, digits, `-`, `_`, `.`)
/// kept, anything else `_`, at most [`MAX_ID_LEN`] characters, no leading `.` (refused for
/// uploads), `bvh` when nothing is left.
#[must_use]
pub fn name_from_stem(stem: &str) -> String {
    let name: String = stem
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || matches!(c, '-' | '_' | '.') {
                c
            } else {
                '_'
            }
        })
        .skip_while(|&c| c == '.')
        .take(MAX_ID_LEN)
        .collect::<String>()
        .replace(".corrupt", "_corrupt");
    if name.is_empty() { "bvh".into() } else { name }
}

/// Uploads `bvh` as asset `name` (`POST /api/assets/{name}?format=bvh`) to the server whose
/// websocket is `ws_url`. When the name is taken (409), or the token may not upload (401/403)
/// but the asset exists, the asset is reused if it has `joints` joints (the names are checked
/// against the `drive` answer).
///
/// # Errors
/// The request failed, the server refused the file, or the existing asset is another rig.
pub async fn ensure(
    driver: &Driver,
    ws_url: &str,
    token: Option<&str>,
    name: &str,
    bvh: &[u8],
    joints: usize,
) -> anyhow::Result<Outcome> {
    let url = fetch::resolve(ws_url, &format!("/api/assets/{name}?format=bvh"))?;
    let bearer = token.map(|t| format!("Bearer {t}"));
    let mut headers = vec![("Content-Type", "application/octet-stream")];
    if let Some(b) = &bearer {
        headers.push(("Authorization", b));
    }
    let response = fetch::request("POST", &url, &headers, bvh).await?;
    let refused = || {
        format!(
            "upload of {name} refused: HTTP {} {}",
            response.status,
            error_message(&response.body)
        )
    };
    match response.status {
        200 => Ok(Outcome::Uploaded),
        409 => {
            check_existing(driver, name, joints)
                .await
                .with_context(|| format!("an asset named {name} exists; use --source-name"))?;
            Ok(Outcome::Reused)
        }
        401 | 403 => {
            // A token limited to its avatar cannot upload; the rig may be there already.
            check_existing(driver, name, joints)
                .await
                .with_context(refused)?;
            Ok(Outcome::Reused)
        }
        _ => bail!(refused()),
    }
}

async fn check_existing(driver: &Driver, name: &str, joints: usize) -> anyhow::Result<()> {
    let listed = driver.command(Command::ListAssets).await?;
    // Read as `list_assets`' answer whatever its shape read as (an empty list reads as scenes).
    let assets: Vec<AssetInfo> = serde_json::from_value(listed.to_value())
        .context("list_assets answered something unexpected")?;
    match assets.iter().find(|a| a.name == name) {
        None => bail!("the server has no asset named {name}"),
        Some(a) if a.joints != joints => bail!(
            "the server's asset {name} has {} joints, the file {joints}: another skeleton",
            a.joints
        ),
        Some(_) => Ok(()),
    }
}

/// The `message` of a server's `{"code","message"}` error body, else the body as text.
fn error_message(body: &[u8]) -> String {
    serde_json::from_slice::<serde_json::Value>(body)
        .ok()
        .and_then(|v| {
            let code = v.get("code")?.as_str()?.to_owned();
            let message = v.get("message")?.as_str()?.to_owned();
            Some(format!("{code}: {message}"))
        })
        .unwrap_or_else(|| String::from_utf8_lossy(body).into_owned())
}

#[cfg(test)]
mod tests {
    use super::*;
    use posecast_proto::msg::check_id;

    #[test]
    fn file_stems_become_valid_asset_names() {
        assert_eq!(name_from_stem("01_01"), "01_01");
        assert_eq!(name_from_stem("my walk (take 2)"), "my_walk__take_2_");
        assert_eq!(name_from_stem("..hidden"), "hidden");
        assert_eq!(name_from_stem("x.corrupt"), "x_corrupt");
        assert_eq!(name_from_stem(""), "bvh");
        assert_eq!(name_from_stem("..."), "bvh");
        let long = name_from_stem(&"é".repeat(100));
        assert_eq!(long.len(), MAX_ID_LEN);
        for stem in [
            "01_01",
            "my walk (take 2)",
            "..hidden",
            "",
            &"a".repeat(200),
        ] {
            let name = name_from_stem(stem);
            assert!(check_id("asset", &name).is_ok(), "{name}");
            assert!(!name.starts_with('.'), "{name}");
        }
    }

    #[test]
    fn server_errors_show_their_code_and_message() {
        let body = br#"{"code":"import_failed","message":"x.bvh line 3: expected OFFSET"}"#;
        assert_eq!(
            error_message(body),
            "import_failed: x.bvh line 3: expected OFFSET"
        );
        assert_eq!(error_message(b"plain"), "plain");
    }
}
