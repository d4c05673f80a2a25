//! `fedvla experiment --config configs/experiments/NAME.toml`: arms x seeds, then `report.md`, `report.json` and
//! plots (see `fedvla_server::experiment`). Killed and started again, it runs only what had not finished.

use std::path::PathBuf;

use fedvla_aggregator::run_dir::RunDir;
use fedvla_server::experiment::{self, ExperimentConfig};
use tracing_subscriber::filter::LevelFilter;

#[derive(clap::Args)]
pub struct Args {
    /// The experiment's TOML file.
    #[arg(long)]
    config: PathBuf,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let config = ExperimentConfig::load(&args.config)?;
    let log = super::support::init_tracing(None, LevelFilter::WARN);
    println!(
        "experiment {}: {} arms x {} seeds into {}",
        config.name,
        config.arms.len(),
        config.seeds.len(),
        config.dir().display()
    );
    let dir = experiment::run(&config, &|run| {
        log.set(RunDir::at(run).log_file()?);
        Ok(())
    })?;
    println!("{}", std::fs::read_to_string(dir.join(experiment::report::REPORT_MD))?);
    println!("report in {}", dir.display());
    Ok(())
}
