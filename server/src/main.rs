//! `fedvla`: a thin dispatcher; each subcommand lives in its own module under src/cmd/.

mod cmd;

use clap::Parser;

#[derive(Parser)]
#[command(name = "fedvla", version, about = "Federated learning of the SmolVLA robot policy")]
struct Cli {
    #[command(subcommand)]
    command: cmd::Command,
}

fn main() -> anyhow::Result<()> {
    cmd::run(Cli::parse().command)
}
