//! Subcommands. To add one: create `src/cmd/<name>.rs` with `pub struct Args` (clap::Args) and
//! `pub fn run(args: Args) -> anyhow::Result<()>`, then add a variant to [`Command`] and an arm to [`run`].

mod eval;
mod experiment;
mod gen_data;
mod join;
mod parity;
mod serve;
mod simulate;
mod train;

use std::fs::File;
use std::path::PathBuf;
use std::sync::{Arc, Mutex};

use anyhow::Context;
use clap::Subcommand;
use fedvla_aggregator::config::{RunConfig, WorkloadKind};
use fedvla_aggregator::parts::ServerParts;
use fedvla_aggregator::run_dir::RunDir;
use fedvla_server::runs::{SHARDS_DIR, boxed};
use fedvla_workloads::linreg::LinRegWorkload;
use fedvla_workloads::smolvla::SmolVlaWorkload;
use fedvla_workloads::workload::server_parts;
use tracing_subscriber::filter::{EnvFilter, LevelFilter};
use tracing_subscriber::layer::SubscriberExt;
use tracing_subscriber::util::SubscriberInitExt;
use tracing_subscriber::{Layer, fmt};

#[derive(Subcommand)]
pub enum Command {
    /// Run the aggregation server.
    Serve(serve::Args),
    /// Join a server as a native client and train on a local shard.
    Join(join::Args),
    /// Run a server and N native clients in one process over loopback WebSockets.
    Simulate(simulate::Args),
    /// Train the federation's centralized baseline: one trainer on every client's training episodes.
    Train(train::Args),
    /// Run arms (centralized, federations) x seeds and report them with intervals.
    Experiment(experiment::Args),
    /// Roll a policy (or the scripted expert) out in the sim: success rate, videos, results.json.
    Eval(eval::Args),
    /// Check SmolVLA against a LeRobot golden fixture, tensor by tensor.
    Parity(parity::Args),
    /// Record scripted-expert episodes of the SO-100 sim as a LeRobot v3.0 dataset.
    GenData(gen_data::Args),
}

pub fn run(command: Command) -> anyhow::Result<()> {
    match command {
        Command::Serve(args) => serve::run(args),
        Command::Join(args) => join::run(args),
        Command::Simulate(args) => simulate::run(args),
        Command::Train(args) => train::run(args),
        Command::Experiment(args) => experiment::run(args),
        Command::Eval(args) => eval::run(args),
        Command::Parity(args) => parity::run(args),
        Command::GenData(args) => gen_data::run(args),
    }
}

/// `--config` and `--run-config`, shared by the subcommands that run a federation.
#[derive(clap::Args)]
pub struct ConfigArgs {
    /// Run configuration file (defaults to the built-in configs/default.toml).
    #[arg(long)]
    config: Option<PathBuf>,
    /// Overrides, e.g. "num-server-rounds=5 fraction-fit=0.5 seed=7".
    #[arg(long, default_value = "")]
    run_config: String,
}

impl ConfigArgs {
    fn load(&self) -> anyhow::Result<RunConfig> {
        let base = match &self.config {
            Some(path) => RunConfig::load(path)?,
            None => RunConfig::default(),
        };
        Ok(base.with_overrides(&self.run_config)?)
    }
}

/// The server side of the configured workload and strategy. A new workload gets an arm here and in the native
/// volunteer (`fedvla_server::native_client::volunteer`).
fn workload_parts(config: RunConfig, run_dir: RunDir) -> anyhow::Result<ServerParts> {
    match config.workload {
        WorkloadKind::Linreg => server_parts(&LinRegWorkload::from_config(&config), config, run_dir).map_err(boxed),
        WorkloadKind::Smolvla => {
            let workload = SmolVlaWorkload::prepare(&config, &run_dir.path().join(SHARDS_DIR))?;
            server_parts(&workload, config, run_dir).map_err(boxed)
        }
    }
}

/// Logs to stderr at `stderr_level` (unless RUST_LOG says otherwise) and, at info, to `log_file` (a run's
/// `server.log`).
fn init_tracing(log_file: Option<File>, stderr_level: LevelFilter) -> LogFile {
    let stderr_filter = EnvFilter::builder().with_default_directive(stderr_level.into()).from_env_lossy();
    let log = LogFile(Arc::new(Mutex::new(log_file)));
    let file = log.clone();
    tracing_subscriber::registry()
        .with(fmt::layer().with_writer(std::io::stderr).with_filter(stderr_filter))
        .with(fmt::layer().with_ansi(false).with_writer(move || file.clone()).with_filter(LevelFilter::INFO))
        .init();
    log
}

/// Where the info log goes: the current run's `server.log` (an experiment moves it from run to run), or nowhere.
#[derive(Clone)]
struct LogFile(Arc<Mutex<Option<File>>>);

impl LogFile {
    fn set(&self, file: File) {
        *self.0.lock().expect("log file lock") = Some(file);
    }
}

impl std::io::Write for LogFile {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        match &mut *self.0.lock().expect("log file lock") {
            Some(file) => file.write(buf),
            None => Ok(buf.len()),
        }
    }

    fn flush(&mut self) -> std::io::Result<()> {
        match &mut *self.0.lock().expect("log file lock") {
            Some(file) => file.flush(),
            None => Ok(()),
        }
    }
}

fn runtime() -> anyhow::Result<tokio::runtime::Runtime> {
    tokio::runtime::Builder::new_multi_thread().enable_all().build().context("starting the tokio runtime")
}

/// Resolves on ctrl-c or SIGTERM.
async fn shutdown_signal() {
    let ctrl_c = async {
        tokio::signal::ctrl_c().await.ok();
    };
    #[cfg(unix)]
    let terminate = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut s) => {
                s.recv().await;
            }
            Err(_) => std::future::pending().await,
        }
    };
    #[cfg(not(unix))]
    let terminate = std::future::pending::<()>();
    tokio::select! {
        () = ctrl_c => {}
        () = terminate => {}
    }
}
