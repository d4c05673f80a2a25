//! `fedvla train`: the centralized baseline of the federation a configuration describes (see
//! `fedvla_server::runs::centralized`).

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
    /// Where the training steps run: cpu, or wgpu (a GPU; needs a fedvla built with `--features gpu`). Overrides
    /// the configuration's `device`.
    #[arg(long)]
    device: Option<ComputeDevice>,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let mut config = args.config.load()?;
    config.device = args.device.unwrap_or(config.device);
    let run_dir = RunDir::create(Path::new(&config.output_dir), &config)?;
    let _log = super::support::init_tracing(Some(run_dir.log_file()?), LevelFilter::WARN);
    println!("run directory: {}", run_dir.path().display());
    let clients = config.sampled_clients(config.num_clients);
    println!(
        "centralized: {} rounds x {clients} clients x {} local steps x batch {}",
        config.num_server_rounds, config.local_steps, config.batch_size
    );
    runs::centralized(config, run_dir.clone(), &Bars::terminal())?;
    println!("metrics in {}", run_dir.path().join(METRICS_FILE).display());
    super::support::print_headline(run_dir.path())
}
