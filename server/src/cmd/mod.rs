//! Subcommands. To add one: create `src/cmd/<name>.rs` with `pub struct Args` (clap::Args) and
//! `pub fn run(args: Args) -> anyhow::Result<()>`, then add a variant to [`Command`] and an arm to [`run`].

mod aggregation_server;
mod bench;
mod eval;
mod experiment;
mod gen_data;
mod join;
mod loadtest;
mod parity;
mod rehearsal;
mod serve;
mod simulate;
mod support;
mod tasks;
mod train;
mod tune;

use clap::Subcommand;

#[derive(Subcommand)]
pub enum Command {
    /// Run the aggregation server.
    Serve(serve::Args),
    /// Join a server as a native client and train on a local shard.
    Join(join::Args),
    /// Run a server and N native clients in one process over loopback WebSockets.
    Simulate(simulate::Args),
    /// Train the federation's centralized baseline: one trainer on every client's training episodes.
    Train(train::Args),
    /// Run arms (centralized, federations) x seeds and report them with intervals.
    Experiment(experiment::Args),
    /// Search a federation's hyperparameters by successive halving, then judge the winner against the base on
    /// seeds and data the search never saw.
    Tune(tune::Args),
    /// Roll a policy (or the scripted expert) out in the sim: success rate, videos, results.json.
    Eval(eval::Args),
    /// Load-test a server in this process with N WebSocket volunteers over loopback: latencies, CPU, memory,
    /// and every update accepted, refused with a reason, or lost.
    Loadtest(loadtest::Args),
    /// Measure what a client-round costs: update bytes per encoding and model size, codec throughput.
    Bench(bench::Args),
    /// The server of one measured aggregation round, a child process of `bench` (and of its test).
    #[command(hide = true)]
    AggregationServer(aggregation_server::Args),
    /// Check SmolVLA against a LeRobot golden fixture, tensor by tensor.
    Parity(parity::Args),
    /// Write a full-size rehearsal's inputs without a download: a smolvla_base-shaped checkpoint of seeded random
    /// bf16 weights, and a small procedural SO-100 dataset.
    RehearsalInputs(rehearsal::Args),
    /// Record scripted-expert episodes of the SO-100 sim as a LeRobot v3.0 dataset.
    GenData(gen_data::Args),
    /// List the sim's tasks by name, one a line (what `eval --task` and `gen-data --tasks` take).
    Tasks(tasks::Args),
}

pub fn run(command: Command) -> anyhow::Result<()> {
    match command {
        Command::Serve(args) => serve::run(args),
        Command::Join(args) => join::run(args),
        Command::Simulate(args) => simulate::run(args),
        Command::Train(args) => train::run(args),
        Command::Experiment(args) => experiment::run(args),
        Command::Tune(args) => tune::run(args),
        Command::Eval(args) => eval::run(args),
        Command::Parity(args) => parity::run(args),
        Command::Bench(args) => bench::run(args),
        Command::AggregationServer(args) => aggregation_server::run(args),
        Command::Loadtest(args) => loadtest::run(args),
        Command::RehearsalInputs(args) => rehearsal::run(args),
        Command::GenData(args) => gen_data::run(args),
        Command::Tasks(args) => tasks::run(args),
    }
}
