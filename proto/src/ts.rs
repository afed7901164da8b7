//! The TypeScript declarations of the wire's JSON, generated from these Rust types (feature
//! `ts`, with [`ts_rs`]), so the JavaScript client and the dashboard type-check against what
//! the server really sends. `server/sdk/protocol.d.ts` is the output, checked in and served at
//! `/sdk/protocol.d.ts`; `cargo run -p posecast-tools --bin gen-ts` writes it again and a test
//! (`tools/tests/ts_types.rs`) fails when it is out of date.

use crate::command::{
    AdditiveReference, AssetDetail, AssetInfo, AvatarState, ClipInfo, Command, CommandResult,
    DofInfo, DriveInfo, DriveVia, Driver, FadeState, JointInfo, JointMapping, JointMask, JointRef,
    LayerState, OnRelease, RecordingInfo, ReplayState, RootMotion, SceneInfo, TakeDriver, TakeInfo,
    Units, Viewer,
};
use crate::description::AvatarDescription;
use crate::expressions::{Expression, ExpressionBind, Override};
use crate::msg::{
    Access, AvatarId, AvatarPoseJson, ClientMsg, Encoding, ErrorCode, ErrorDetails, FrameJson,
    ProtocolError, SceneId, ServerMsg,
};
use crate::placement::Placement;
use crate::precision::Precision;
use crate::rig_options::{NeutralPose, PipelineOptions, ReorientFrame, SignedAxis, UpAxisOverride};
use crate::subset::JointSet;
use crate::tokens::{MintRequest, MintedToken, Right, TokenInfo};
use crate::trackers::{CalibrationInfo, CalibrationPose, Legs, LocomotionClip, TrackerTransform};
use ts_rs::{Config, TS};

/// The file's first lines.
const HEADER: &str = "\
// The JSON messages of the posecast websocket protocol (version 5) and of its REST answers, as
// TypeScript types. GENERATED from the Rust types of posecast-proto (`proto/src/ts.rs`): do not
// edit; run `cargo run -p posecast-tools --bin gen-ts` after changing them. proto/PROTOCOL.md
// explains every message. Served at /sdk/protocol.d.ts; the SDK's posecast.d.ts builds on it.
";

/// The declarations: every message type and every type a message holds, in one module.
#[must_use]
pub fn declarations() -> String {
    // JSON numbers: a u64 (a command id, a clock in µs) is a `number`, not a `bigint`.
    let cfg = Config::new().with_large_int("number");
    let mut out = String::from(HEADER);
    macro_rules! declare {
        ($($t:ty),* $(,)?) => {$(
            out.push('\n');
            if let Some(docs) = <$t as TS>::docs() {
                out.push_str(&docs);
            }
            out.push_str("export ");
            out.push_str(&<$t as TS>::decl(&cfg));
            out.push('\n');
        )*};
    }
    declare!(
        ClientMsg,
        ServerMsg,
        Command,
        CommandResult,
        ProtocolError,
        ErrorDetails,
        ErrorCode,
        Encoding,
        Precision,
        Access,
        Right,
        MintRequest,
        TokenInfo,
        MintedToken,
        SceneId,
        AvatarId,
        Placement,
        JointSet,
        AvatarDescription,
        Expression,
        ExpressionBind,
        Override,
        FrameJson,
        AvatarPoseJson,
        SceneInfo,
        AvatarState,
        FadeState,
        JointMask,
        LayerState,
        AdditiveReference,
        JointRef,
        RootMotion,
        AssetInfo,
        ClipInfo,
        AssetDetail,
        JointMapping,
        Units,
        JointInfo,
        DofInfo,
        DriveInfo,
        Driver,
        DriveVia,
        Viewer,
        OnRelease,
        TrackerTransform,
        Legs,
        CalibrationPose,
        CalibrationInfo,
        LocomotionClip,
        RecordingInfo,
        TakeInfo,
        TakeDriver,
        ReplayState,
        PipelineOptions,
        NeutralPose,
        UpAxisOverride,
        SignedAxis,
        ReorientFrame,
    );
    // `done` has no value in serde's form, but an `ack` and a REST answer write
    // `"result": null` for it (`msg::tagged`, `CommandResult::to_tagged_value`).
    let done = r#"{ "kind": "done" }"#;
    assert!(out.contains(done), "ts-rs no longer writes {done}");
    // Rustdoc's links read as plain code in TypeScript's doc comments.
    out.replace(done, r#"{ "kind": "done", "result": null }"#)
        .replace("[`", "`")
        .replace("`]", "`")
}
