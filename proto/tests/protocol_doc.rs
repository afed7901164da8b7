//! PROTOCOL.md is what an independent client is written from, so its examples are checked
//! against the types: every complete JSON message in a `json` block parses as a client or a
//! server message, and the full `description` example's hash is the one a client computes.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use posecast_proto::msg::{ClientMsg, ServerMsg};

const PROTOCOL: &str = include_str!("../PROTOCOL.md");

/// Every JSON value of the document's ```json blocks (a value may span lines), as text.
fn json_examples() -> Vec<String> {
    let mut out = Vec::new();
    let mut in_block = false;
    let mut current = String::new();
    let mut depth = 0i32;
    for line in PROTOCOL.lines() {
        if line.starts_with("```") {
            in_block = line == "```json";
            current.clear();
            depth = 0;
            continue;
        }
        if !in_block || (current.is_empty() && !line.trim_start().starts_with('{')) {
            continue;
        }
        current.push_str(line);
        current.push('\n');
        let mut in_string = false;
        let mut escaped = false;
        for c in line.chars() {
            match c {
                _ if escaped => escaped = false,
                '\\' if in_string => escaped = true,
                '"' => in_string = !in_string,
                '{' | '[' if !in_string => depth += 1,
                '}' | ']' if !in_string => depth -= 1,
                _ => {}
            }
        }
        if depth == 0 {
            out.push(std::mem::take(&mut current));
        }
    }
    out
}

#[test]
fn every_complete_message_example_parses() {
    let examples = json_examples();
    let mut checked = 0;
    let mut wrong = Vec::new();
    for text in examples.iter().filter(|t| t.contains("\"type\"")) {
        // `…` marks an example shortened by hand: not a whole message. The unknown op `fly`
        // is the document's example of a command that does not parse.
        if text.contains('…') || text.contains(r#""op":"fly""#) {
            continue;
        }
        let client = serde_json::from_str::<ClientMsg>(text);
        let server = serde_json::from_str::<ServerMsg>(text);
        if let (Err(c), Err(s)) = (client, server) {
            wrong.push(format!(
                "{text}  as a client message: {c}\n  as a server message: {s}"
            ));
        }
        checked += 1;
    }
    assert!(
        wrong.is_empty(),
        "PROTOCOL.md examples that are no message:\n{}",
        wrong.join("\n")
    );
    assert!(
        checked >= 40,
        "only {checked} examples found: is the extraction broken?"
    );
}

#[test]
fn the_description_example_hash_is_what_a_client_computes() {
    let example = json_examples()
        .into_iter()
        .find(|t| t.contains("\"type\":\"description\"") && !t.contains('…'))
        .expect("PROTOCOL.md has a complete description example");
    let ServerMsg::Description { avatar, .. } = serde_json::from_str(&example).unwrap() else {
        panic!("not a description: {example}");
    };
    assert_eq!(
        avatar.hash,
        format!("{:016x}", avatar.compute_hash()),
        "the example's hash is not FNV-1a over the bytes PROTOCOL.md lists"
    );
    avatar
        .to_skeleton()
        .expect("the example describes a valid rig");
}

/// Every ack carries `result` (`null` for `done`); version 3 also names the kind. Both read
/// back.
#[test]
fn acks_carry_their_result_bare_or_tagged() {
    use posecast_proto::command::CommandResult;
    use posecast_proto::msg::AvatarId;
    assert_eq!(
        ServerMsg::ack_bare(3, &CommandResult::Done),
        r#"{"id":3,"result":null,"type":"ack"}"#
    );
    let done = ServerMsg::Ack {
        id: 3,
        result: CommandResult::Done,
    };
    assert_eq!(
        serde_json::to_string(&done).unwrap(),
        r#"{"type":"ack","id":3,"kind":"done","result":null}"#
    );
    let added = ServerMsg::Ack {
        id: 4,
        result: CommandResult::AvatarAdded {
            avatar: AvatarId("guest".into()),
        },
    };
    let tagged = serde_json::to_string(&added).unwrap();
    assert_eq!(
        tagged,
        r#"{"type":"ack","id":4,"kind":"avatar_added","result":{"avatar":"guest"}}"#
    );
    for text in [
        tagged,
        ServerMsg::ack_bare(
            4,
            &CommandResult::AvatarAdded {
                avatar: AvatarId("guest".into()),
            },
        ),
    ] {
        assert_eq!(
            serde_json::from_str::<ServerMsg>(&text).unwrap(),
            added,
            "{text}"
        );
    }
    for text in [
        r#"{"type":"ack","id":3,"result":null}"#,
        r#"{"type":"ack","id":3,"kind":"done"}"#,
        r#"{"type":"ack","id":3,"kind":"done","result":null}"#,
    ] {
        assert_eq!(
            serde_json::from_str::<ServerMsg>(text).unwrap(),
            done,
            "{text}"
        );
    }
    // A kind that does not fit its value is not an ack.
    assert!(
        serde_json::from_str::<ServerMsg>(r#"{"type":"ack","id":3,"kind":"scenes","result":{}}"#)
            .is_err()
    );
}
