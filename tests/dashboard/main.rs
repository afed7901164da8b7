//! The web dashboard in a real headless Chromium, driven over WebDriver (chromedriver +
//! fantoccini) against an in-process server, one browser at a time (`browser::browser`):
//! - `controls`: the page loads without errors and lists the avatars; its buttons and sliders
//!   change the avatars' state and the pose stream (checked by a separate Rust websocket
//!   client); the preview draws the avatar (screenshot pixel count); uploads; offline and back;
//! - `placement`: every avatar of a scene drawn where it stands (drawn roots, screenshot
//!   columns);
//! - `tokens`: a wrong token, and a server restarted with a new token, leave the page watching
//!   and saying why control is refused; a `#control=…` link opened in the tab restores control;
//! - `world`: scenes and avatars created, placed, focused, picked and removed from the page
//!   (and the multi-avatar screenshot, `docs/src/images/dashboard.png`);
//! - `timeline`: the time display and scrubber move with the stream, range markers,
//!   cross-fades shown;
//! - `layout`: at 1280×800 the controls sit beside the preview, which stays in view; at 400 px
//!   one column without sideways scrolling;
//! - `push`: changes made by others show within a second without the page asking (it never
//!   sends `list_scenes`, and sends no command while idle); who watches and who drives; the
//!   page as an avatar's live driver (Drive, the sliders, Release drive); a take recorded;
//! - `layers`: the Playback panel plays a clip on a masked or additive layer and stops it;
//! - `faces`: the Face panel shows an expression and moves a morph channel; the stream carries
//!   the weights to the page and the WebGL preview morphs the mesh;
//! - `sdk`: the JavaScript client `/sdk/posecast.js` from pages on another origin: binary
//!   frames decoded as a Rust client decodes them, typed command errors, the guide's example page (`docs/src/how-to/javascript.md`);
//! - `webtransport`: the JavaScript client over WebTransport (frames as datagrams, keyframes
//!   acknowledged) decodes the websocket's poses; with UDP out of reach it falls back to the
//!   websocket; the dashboard shows the transport;
//! - `determinism`: ten minutes of random motion with random drop patterns decoded by the
//!   page's `frames2.js` and by `Frame2Decoder` to the same values, frame by frame.
//!
//! Needs `/usr/bin/chromium` and `/usr/bin/chromedriver` (`scripts/test` installs them).
//! Set `POSECAST_UPDATE_SCREENSHOT=1` to also write `docs/src/images/dashboard.png` for the README and the guide.

#![allow(clippy::unwrap_used, clippy::expect_used)]

#[path = "../common/mod.rs"]
mod common;

mod browser;
mod controls;
mod determinism;
mod faces;
mod layers;
mod layout;
mod placement;
mod push;
mod sdk;
mod takes;
mod three;
mod timeline;
mod tokens;
mod webtransport;
mod world;
