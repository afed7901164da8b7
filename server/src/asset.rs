//! Imported assets (placeholder until the importers land).
