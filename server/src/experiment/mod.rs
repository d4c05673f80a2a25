//! `fedvla experiment --config configs/experiments/NAME.toml`: arms (the centralized baseline and federation
//! configurations) x seeds, each a whole run in `<out>/<arm>/seed_<s>/`, then a final evaluation of each run's
//! last global model in the sim on held-out layouts, then the report (`report.md`, `report.json`, PNG plots).
//! A run that finished (its `final.json` is there) is never run again, so a killed experiment resumes where it
//! stopped; a run that did not finish starts over. Its [`runner`] is the one `fedvla tune` runs its trials on.

pub mod config;
pub mod plot;
pub mod report;
pub mod runner;
/// The intervals of a report, shared with the language check of every sim evaluation (`results.json`).
pub use fedvla_aggregator::stats;

pub use config::{Arm, ExperimentConfig, FINAL_FILE, FinalEvaluation, Mode, last_heldout, read_final};
pub use runner::run;
