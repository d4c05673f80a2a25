//! The federation server (axum), the native client transport and the synthetic workload used until the
//! SmolVLA trainer lands. The `fedvla` binary (src/main.rs, src/cmd/) is a thin layer over this library.

pub mod app;
pub mod config;
pub mod connection;
pub mod console;
pub mod coordinator;
pub mod datagen;
pub mod error;
pub mod experiment;
pub mod http;
pub mod linreg;
pub mod native_client;
pub mod records;
pub mod run_dir;
pub mod runs;
pub mod server;
pub mod sim_eval;
pub mod smolvla_workload;
pub mod static_files;
pub mod volunteer;
pub mod workload;
