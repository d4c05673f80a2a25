//! The `fedvla` binary's library: the native volunteer's I/O ([`native_client`]), whole runs in one process
//! ([`runs`]: a federation over loopback, its centralized baseline), experiments over them ([`experiment`]),
//! hyperparameter searches on the experiment's runner ([`tune`]), a load test of the server ([`loadtest`]) and a
//! full-size rehearsal's inputs made without a download ([`rehearsal`]).
//! The CLI (src/main.rs, src/cmd/) is a thin layer over this, the aggregator (`fedvla-aggregator`), the app
//! (`fedvla-app`) and the workloads (`fedvla-workloads`).

pub mod aggregation_memory;
pub mod attack;
pub mod experiment;
pub mod loadtest;
pub mod native_client;
pub mod rehearsal;
pub mod runs;
pub mod tune;
