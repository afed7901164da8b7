//! The posecast server.
