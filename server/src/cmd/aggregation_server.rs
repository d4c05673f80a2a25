//! `fedvla aggregation-server` (hidden): the server of one measured aggregation round, run as a child process by
//! `fedvla bench` and by the aggregation memory test, so that their memory figures are the server's alone
//! ([`fedvla_server::aggregation_memory`]).

use std::path::PathBuf;

use fedvla_server::aggregation_memory::serve_round;
use tracing_subscriber::filter::LevelFilter;

#[derive(clap::Args)]
pub struct Args {
    /// Model size (every tensor) of the global model and of each update.
    #[arg(long)]
    size: String,
    /// Volunteers of the round (all of them sampled).
    #[arg(long)]
    clients: usize,
    /// Where the run directory is created.
    #[arg(long)]
    output: PathBuf,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let _log = super::support::init_tracing(None, LevelFilter::WARN);
    serve_round(&args.size, args.clients, &args.output)
}
