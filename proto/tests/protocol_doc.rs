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

#[test]
fn acks_always_carry_a_result() {
    let ack = ServerMsg::Ack {
        id: 3,
        result: serde_json::Value::Null,
    };
    assert_eq!(
        serde_json::to_string(&ack).unwrap(),
        r#"{"type":"ack","id":3,"result":null}"#
    );
}
