//! The network client library.
