//! What the subcommands share: the run configuration arguments, the server parts of the configured workload,
//! logging (to stderr and a run's `server.log`), the tokio runtime, shutdown signals and a run's headline.

use std::fs::File;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

use anyhow::Context;
use fedvla_aggregator::config::{RunConfig, WorkloadKind};
use fedvla_aggregator::parts::ServerParts;
use fedvla_aggregator::records::read_metrics;
use fedvla_aggregator::run_dir::RunDir;
use fedvla_server::runs::SHARDS_DIR;
pub use fedvla_server::runs::boxed;
use fedvla_workloads::linreg::LinRegWorkload;
use fedvla_workloads::smolvla::SmolVlaWorkload;
use fedvla_workloads::workload::server_parts;
use tracing_subscriber::filter::{EnvFilter, LevelFilter};
use tracing_subscriber::layer::SubscriberExt;
use tracing_subscriber::util::SubscriberInitExt;
use tracing_subscriber::{Layer, fmt};

/// `--config` and `--run-config`, shared by the subcommands that run a federation.
#[derive(clap::Args)]
pub struct ConfigArgs {
    /// Run configuration file (defaults to the built-in configs/default.toml).
    #[arg(long)]
    config: Option<PathBuf>,
    /// Overrides, e.g. "num-server-rounds=5 fraction-fit=0.5 seed=7".
    #[arg(long, default_value = "")]
    pub run_config: String,
}

impl ConfigArgs {
    pub fn load(&self) -> anyhow::Result<RunConfig> {
        let base = match &self.config {
            Some(path) => RunConfig::load(path)?,
            None => RunConfig::default(),
        };
        Ok(base.with_overrides(&self.run_config)?)
    }
}

/// The server side of the configured workload and strategy. A new workload gets an arm here and in the native
/// volunteer (`fedvla_server::native_client::volunteer`).
pub fn workload_parts(config: RunConfig, run_dir: RunDir) -> anyhow::Result<ServerParts> {
    match config.workload {
        WorkloadKind::Linreg => server_parts(&LinRegWorkload::from_config(&config), config, run_dir).map_err(boxed),
        WorkloadKind::Smolvla => {
            let workload = SmolVlaWorkload::prepare(&config, &run_dir.path().join(SHARDS_DIR))?;
            println!("{}", workload.inputs());
            server_parts(&workload, config, run_dir).map_err(boxed)
        }
    }
}

/// Logs to stderr at `stderr_level` (unless RUST_LOG says otherwise) and, at info, to `log_file` (a run's
/// `server.log`).
pub fn init_tracing(log_file: Option<File>, stderr_level: LevelFilter) -> LogFile {
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
pub struct LogFile(Arc<Mutex<Option<File>>>);

impl LogFile {
    pub fn set(&self, file: File) {
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

pub fn runtime() -> anyhow::Result<tokio::runtime::Runtime> {
    tokio::runtime::Builder::new_multi_thread().enable_all().build().context("starting the tokio runtime")
}

/// Resolves on ctrl-c or SIGTERM.
pub async fn shutdown_signal() {
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

/// Prints the global held-out loss (and sim success) of the first and the last evaluated round, the run's
/// headline; for a run of several tasks, the last round's figures per task and its language check.
pub fn print_headline(run: &Path) -> anyhow::Result<()> {
    let lines = read_metrics(run)?;
    let evaluated: Vec<_> = lines.iter().filter_map(|m| Some((m.round, m.global.as_ref()?.eval.as_ref()?))).collect();
    if let (Some((r0, first)), Some((rn, last))) = (evaluated.first(), evaluated.last()) {
        println!("global held-out loss: round {r0} {:.4} -> round {rn} {:.4}", first.heldout_loss, last.heldout_loss);
        for task in &last.heldout_by_task {
            let mse = task.action_mse.map_or(String::new(), |mse| format!(", action MSE {mse:.3}"));
            println!("  {}: held-out loss {:.4}{mse} ({} rows)", task.task, task.heldout_loss, task.heldout_examples);
        }
        if let Some(l) = &last.heldout_language {
            println!(
                "  {}: held-out loss told the right goal {:.4}, told another {:.4} ({} rows)",
                l.task, l.loss_told_right, l.loss_told_another, l.heldout_examples
            );
        }
    }
    if let Some(last) = lines.iter().rfind(|m| !m.clients.is_empty()) {
        let took: Vec<String> =
            last.clients.iter().filter_map(|c| Some(format!("{} {:.1} s", c.name, c.seconds?))).collect();
        println!("round {} per client (fetching the model, training, uploading): {}", last.round, took.join(", "));
    }
    let rolled_out: Vec<_> = lines.iter().filter_map(|m| Some((m.round, m.global.as_ref()?.sim.as_ref()?))).collect();
    if let (Some((r0, first)), Some((rn, last))) = (rolled_out.first(), rolled_out.last()) {
        println!(
            "sim success rate on held-out layouts: round {r0} {:.2} -> round {rn} {:.2} ({} episodes)",
            first.success_rate, last.success_rate, last.rollout_episodes
        );
        for task in &last.success_by_task {
            println!("  {}: {}/{} succeeded", task.task, task.successes, task.episodes);
        }
        if let Some(check) = &last.language_check {
            println!("  {check}");
        }
    }
    Ok(())
}
