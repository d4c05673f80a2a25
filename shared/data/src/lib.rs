//! LeRobot data (placeholder until the data crate lands).
