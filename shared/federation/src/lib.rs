//! Federation (placeholder until the protocol lands).
