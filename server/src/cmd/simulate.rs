//! `fedvla simulate`: a server and N native clients in one process, over real loopback WebSockets.

use std::path::Path;

use fedvla_aggregator::config::ComputeDevice;
use fedvla_aggregator::run_dir::{METRICS_FILE, RunDir};
use fedvla_server::runs::{self, Bars};
use tracing_subscriber::filter::LevelFilter;

use super::support::ConfigArgs;

#[derive(clap::Args)]
pub struct Args {
    #[command(flatten)]
    config: ConfigArgs,
    /// Number of clients (one shard each); without it, the configuration's `num-clients` (3 by default), so that
    /// a configuration file (`fedvla tune`'s best.toml) runs as it is.
    #[arg(long)]
    clients: Option<usize>,
    /// Where the training steps run: cpu, or wgpu (a GPU; needs a fedvla built with `--features gpu`). Overrides
    /// the configuration's `device`.
    #[arg(long)]
    device: Option<ComputeDevice>,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let mut config = args.config.load()?;
    config.num_clients = args.clients.unwrap_or(config.num_clients);
    config.device = args.device.unwrap_or(config.device);
    let run_dir = RunDir::create(Path::new(&config.output_dir), &config)?;
    // Progress bars own the terminal: only warnings go to stderr, the full log to server.log.
    let _log = super::support::init_tracing(Some(run_dir.log_file()?), LevelFilter::WARN);
    println!("run directory: {}", run_dir.path().display());
    let status = runs::federated(config, run_dir.clone(), &Bars::terminal())?;
    println!("{} rounds done; metrics in {}", status.completed_rounds, run_dir.path().join(METRICS_FILE).display());
    super::support::print_headline(run_dir.path())
}
