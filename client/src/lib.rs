//! posecast clients.
