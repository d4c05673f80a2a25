//! `fedvla serve`: the aggregation server.

use std::path::{Path, PathBuf};

use anyhow::Context;
use fedvla_aggregator::coordinator::CoordinatorError;
use fedvla_aggregator::run_dir::RunDir;
use fedvla_app::server;
use tokio::net::TcpListener;
use tracing_subscriber::filter::LevelFilter;

use super::support::ConfigArgs;

#[derive(clap::Args)]
pub struct Args {
    #[command(flatten)]
    config: ConfigArgs,
    /// Continue the run in this directory (outputs/<date_time>) after its last completed round; its
    /// config.toml is the base that --run-config overrides.
    #[arg(long, conflicts_with = "config")]
    resume: Option<PathBuf>,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let (config, run_dir) = match &args.resume {
        Some(dir) => {
            let (run_dir, base) = RunDir::open(dir)?;
            let config = base.with_overrides(&args.config.run_config)?;
            run_dir.write_config(&config)?;
            (config, run_dir)
        }
        None => {
            let config = args.config.load()?;
            let run_dir = RunDir::create(Path::new(&config.output_dir), &config)?;
            (config, run_dir)
        }
    };
    let _log = super::support::init_tracing(Some(run_dir.log_file()?), LevelFilter::INFO);
    tracing::info!(run_dir = %run_dir.path().display(), "run directory");
    let listen = config.listen.clone();
    let dir = run_dir.path().to_owned();
    super::support::runtime()?.block_on(async move {
        let listener = TcpListener::bind(&listen).await.with_context(|| format!("binding {listen}"))?;
        let handle = server::start(super::support::workload_parts(config, run_dir)?, listener)?;
        let cancel = handle.cancel_token();
        tokio::spawn(async move {
            super::support::shutdown_signal().await;
            tracing::info!("shutting down");
            cancel.cancel();
        });
        match handle.finish().await {
            Ok(status) => {
                tracing::info!(rounds = status.completed_rounds, rejections = ?status.rejections, "done");
                Ok(())
            }
            Err(CoordinatorError::Cancelled) => {
                tracing::info!("stopped; continue with `fedvla serve --resume {}`", dir.display());
                Ok(())
            }
            Err(e) => Err(e.into()),
        }
    })
}
