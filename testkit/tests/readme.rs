//! The guide's "Use posecast in your tests" (`docs/src/how-to/testing.md`) shows
//! `examples/first_test.rs` (which `cargo test` runs): the copy there must be that file,
//! character for character.

#![allow(clippy::unwrap_used, clippy::expect_used)]

const GUIDE: &str = include_str!("../../docs/src/how-to/testing.md");
const EXAMPLE: &str = include_str!("../examples/first_test.rs");

/// The body of the first ```rust block after `heading`.
fn first_rust_block<'a>(text: &'a str, heading: &str) -> Option<&'a str> {
    let section = &text[text.find(heading)?..];
    let start = section.find("```rust\n")? + "```rust\n".len();
    let end = section[start..].find("\n```")? + 1;
    Some(&section[start..start + end])
}

#[test]
fn the_guides_example_is_the_example_program() {
    let block = first_rust_block(GUIDE, "# Use posecast in your tests")
        .expect("docs/src/how-to/testing.md has a section \"Use posecast in your tests\" with a ```rust block");
    if block != EXAMPLE {
        let line = block
            .lines()
            .zip(EXAMPLE.lines())
            .position(|(a, b)| a != b)
            .map_or_else(|| "the lengths".to_owned(), |i| format!("line {}", i + 1));
        panic!(
            "docs/src/how-to/testing.md's example differs from testkit/examples/first_test.rs at {line}: copy the file into the guide again"
        );
    }
}
