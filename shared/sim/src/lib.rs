//! SO-100 simulation (placeholder until the sim lands).
