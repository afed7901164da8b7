//! The built-in avatar generator.
