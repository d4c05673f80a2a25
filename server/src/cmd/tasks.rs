//! `fedvla tasks`: the sim's tasks by name, one a line, as `eval --task`, `gen-data --tasks` and the run
//! configuration's `dataset-tasks` spell them.

use fedvla_sim::TaskKind;

#[derive(clap::Args)]
pub struct Args {}

pub fn run(_args: Args) -> anyhow::Result<()> {
    for task in TaskKind::ALL {
        println!("{task}");
    }
    Ok(())
}
