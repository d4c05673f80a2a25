//! `fedvla simulate`: a server and N native clients in one process, over real loopback WebSockets.

use std::path::Path;

use fedvla_aggregator::records::read_metrics;
use fedvla_aggregator::run_dir::{METRICS_FILE, RunDir};
use fedvla_server::runs::{self, Bars};
use tracing_subscriber::filter::LevelFilter;

use super::ConfigArgs;

#[derive(clap::Args)]
pub struct Args {
    #[command(flatten)]
    config: ConfigArgs,
    /// Number of clients (one shard each).
    #[arg(long, default_value_t = 3)]
    clients: usize,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let mut config = args.config.load()?;
    config.num_clients = args.clients;
    let run_dir = RunDir::create(Path::new(&config.output_dir), &config)?;
    // Progress bars own the terminal: only warnings go to stderr, the full log to server.log.
    let _log = super::init_tracing(Some(run_dir.log_file()?), LevelFilter::WARN);
    println!("run directory: {}", run_dir.path().display());
    let status = runs::federated(config, run_dir.clone(), &Bars::terminal())?;
    println!("{} rounds done; metrics in {}", status.completed_rounds, run_dir.path().join(METRICS_FILE).display());
    print_headline(run_dir.path())
}

/// Prints the global held-out loss (and sim success) of the first and the last evaluated round, the run's
/// headline.
pub fn print_headline(run: &Path) -> anyhow::Result<()> {
    let lines = read_metrics(run)?;
    let evaluated: Vec<_> = lines.iter().filter_map(|m| Some((m.round, m.global.as_ref()?.eval?))).collect();
    if let (Some((r0, first)), Some((rn, last))) = (evaluated.first(), evaluated.last()) {
        println!("global held-out loss: round {r0} {:.4} -> round {rn} {:.4}", first.heldout_loss, last.heldout_loss);
    }
    let rolled_out: Vec<_> = lines.iter().filter_map(|m| Some((m.round, m.global.as_ref()?.sim?))).collect();
    if let (Some((r0, first)), Some((rn, last))) = (rolled_out.first(), rolled_out.last()) {
        println!(
            "sim success rate on held-out layouts: round {r0} {:.2} -> round {rn} {:.2} ({} episodes)",
            first.success_rate, last.success_rate, last.rollout_episodes
        );
    }
    Ok(())
}
