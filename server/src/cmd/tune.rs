//! `fedvla tune --config configs/tune/NAME.toml`: successive halving over a federation's hyperparameters, the
//! best drawn configuration judged afresh against the base, then `report.md`, `report.json`, `trials.png` and
//! `best.toml` (see `fedvla_server::tune`). Killed and started again, it runs only what had not finished.

use std::path::PathBuf;

use anyhow::Context;
use fedvla_aggregator::run_dir::RunDir;
use fedvla_server::tune::{self, TuneConfig};
use tracing_subscriber::filter::LevelFilter;

#[derive(clap::Args)]
pub struct Args {
    /// The search's TOML file.
    #[arg(long)]
    config: PathBuf,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let config = TuneConfig::load(&args.config)?;
    let log = super::support::init_tracing(None, LevelFilter::WARN);
    let dir = config.dir();
    println!(
        "search {}: {} trials over {} keys, rungs of {:?} rounds (the best 1/{} of each and the base go on), {} at once, \
         into {}",
        config.name,
        config.trials,
        config.space.len(),
        config.rungs,
        config.reduction,
        config.parallel_trials,
        dir.display()
    );
    // One run at a time logs into its own server.log; runs at once share the search's log, where no run's lines
    // would be told from another's in a run's folder.
    let shared_log = dir.join("tune.log");
    if config.parallel_trials > 1 {
        std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
        let file = std::fs::OpenOptions::new().create(true).append(true).open(&shared_log);
        log.set(file.with_context(|| format!("opening {}", shared_log.display()))?);
    }
    let dir = tune::run(&config, &|run| {
        if config.parallel_trials == 1 {
            log.set(RunDir::at(run).log_file()?);
        }
        Ok(())
    })?;
    println!("{}", std::fs::read_to_string(dir.join(tune::report::REPORT_MD))?);
    println!("report in {}; the best configuration: {}", dir.display(), dir.join(tune::BEST_CONFIG).display());
    Ok(())
}
