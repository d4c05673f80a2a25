//! The federation's aggregator, with no HTTP in it: the run configuration, the run directory and the records it
//! holds (and the intervals its figures are stated with, [`stats`]), the round lifecycle ([`coordinator`]: sampling, collecting, aggregating through the strategy, evaluating,
//! persisting), the operator's controls, the events it reports, the registry of volunteers and their shards, and
//! the memory budget of uploads on their way in ([`upload_budget`]).
//! The HTTP/WebSocket app (`fedvla-app`) feeds it and watches it; workloads (`fedvla-workloads`) plug into it
//! through [`parts::ServerParts`].

pub mod config;
pub mod control;
pub mod coordinator;
pub mod events;
pub mod parts;
pub mod records;
pub mod registry;
pub mod run_dir;
pub mod sessions;
pub mod stats;
pub mod upload_budget;
