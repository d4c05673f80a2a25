//! `fedvla loadtest`: N volunteers against a server in this process, over loopback; prints what it measured
//! (`fedvla_server::loadtest`), and writes it as JSON with `--json`.

use std::path::PathBuf;
use std::time::Duration;

use anyhow::Context;
use fedvla_server::loadtest::{self, LoadOptions};
use tracing_subscriber::filter::LevelFilter;

#[derive(clap::Args)]
pub struct Args {
    /// Concurrent WebSocket volunteers (at most 5000).
    #[arg(long, default_value_t = 100)]
    clients: usize,
    /// Rounds (at most 100).
    #[arg(long, default_value_t = 3)]
    rounds: u64,
    /// Each volunteer's linreg steps a round.
    #[arg(long, default_value_t = 10)]
    local_steps: u32,
    /// The run is stopped after this many seconds, and what it measured reported.
    #[arg(long, default_value_t = 300)]
    time_limit_secs: u64,
    /// Where the run directory goes.
    #[arg(long, default_value = "outputs/loadtest")]
    output_dir: PathBuf,
    /// Also write the report to this file as JSON.
    #[arg(long)]
    json: Option<PathBuf>,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    // Only warnings: refusals and failures; every volunteer's join would drown the report.
    let _log = super::support::init_tracing(None, LevelFilter::WARN);
    let options = LoadOptions {
        clients: args.clients,
        rounds: args.rounds,
        local_steps: args.local_steps,
        time_limit: Duration::from_secs(args.time_limit_secs),
        output_dir: args.output_dir,
    };
    let report = loadtest::run(&options)?;
    println!("{report}");
    if let Some(path) = &args.json {
        let json = serde_json::to_string_pretty(&report)?;
        std::fs::write(path, json).with_context(|| path.display().to_string())?;
    }
    Ok(())
}
