//! Running an experiment's grid: every arm on every seed not finished yet, each run's final evaluation in the
//! sim, then the report.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::Context;
use burn::tensor::Device;
use fedvla_aggregator::records::RolloutResults;
use fedvla_aggregator::run_dir::{POLICY_DIR, RunDir};
use fedvla_data::LeRobotDataset;
use fedvla_learner::rollout::SimPolicy;
use fedvla_policy::PolicyDir;
use fedvla_sim::TaskKind;
use fedvla_workloads::datagen::ensure_unrecorded;
use fedvla_workloads::sim_eval::{Agent, SimEvalOptions, evaluate_in_sim};
use fedvla_workloads::smolvla::{dataset_root, rollout_tasks};
use indicatif::{ProgressBar, ProgressStyle};

use super::config::{Arm, ExperimentConfig, FINAL_FILE, FinalEvaluation, Mode, write_final};
use super::report;
use crate::runs::{self, Bars};

/// Runs every arm on every seed that has not finished yet, then writes the report. Returns the report's folder.
pub fn run(config: &ExperimentConfig, log: &dyn Fn(&Path) -> anyhow::Result<()>) -> anyhow::Result<PathBuf> {
    let dir = config.dir();
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    let grid: Vec<(&Arm, u64)> =
        config.arms.iter().flat_map(|arm| config.seeds.iter().map(move |&seed| (arm, seed))).collect();
    let bar = ProgressBar::new(grid.len() as u64);
    bar.set_style(ProgressStyle::with_template("[{bar:30}] {pos}/{len} runs {msg} ({elapsed}, eta {eta})")?);
    for (arm, seed) in grid {
        let path = config.run_path(arm, seed);
        if path.join(FINAL_FILE).exists() {
            bar.inc(1);
            continue;
        }
        bar.set_message(format!("{} seed {seed}", arm.name));
        // A run that did not finish is started over: a half-written run is not a result.
        if path.exists() {
            std::fs::remove_dir_all(&path).with_context(|| format!("removing the unfinished {}", path.display()))?;
        }
        let run_config = config.run_config(arm, seed)?;
        let run_dir = RunDir::create_at(&path, &run_config)?;
        log(&path)?;
        let started = Instant::now();
        let result = match arm.mode {
            Mode::Centralized => runs::centralized(run_config.clone(), run_dir, &Bars::hidden()),
            Mode::Federated => runs::federated(run_config.clone(), run_dir, &Bars::hidden()).map(drop),
        };
        result.with_context(|| format!("arm {} seed {seed} ({})", arm.name, path.display()))?;
        let train_seconds = started.elapsed().as_secs_f64();
        let last = final_round(&path)?;
        let layouts = config.eval_seed..config.eval_seed + config.eval_episodes as u64;
        let root = dataset_root(&run_config)?;
        ensure_unrecorded(&root, layouts).with_context(|| format!("arm {} seed {seed}", arm.name))?;
        let dataset = LeRobotDataset::open(&root).with_context(|| format!("opening {}", root.display()))?;
        let tasks = rollout_tasks(&dataset);
        let sim = evaluate_final(&path, last, config, &tasks, run_config.rollout_max_frames as usize)?;
        bar.println(format!(
            "{} seed {seed}: sim success {:.2} on {} held-out layouts ({:.0} s)",
            arm.name,
            sim.success_rate.unwrap_or(0.0),
            sim.episodes.len(),
            train_seconds
        ));
        write_final(&path, &FinalEvaluation { round: last, sim, train_seconds })?;
        // The clients' shards are copies of the dataset (over a gigabyte a federated run) that nothing reads
        // once the run is over; its models, metrics and rollouts stay.
        let shards = path.join(runs::SHARDS_DIR);
        if shards.exists() {
            std::fs::remove_dir_all(&shards).with_context(|| format!("removing {}", shards.display()))?;
        }
        bar.inc(1);
    }
    bar.finish_and_clear();
    report::write(config)?;
    Ok(dir)
}

/// The last round a run saved.
fn final_round(run: &Path) -> anyhow::Result<u64> {
    let lines = fedvla_aggregator::records::read_metrics(run)?;
    lines.last().map(|l| l.round).with_context(|| format!("{}: no metrics", run.display()))
}

/// The run's last global model (its LeRobot export) rolled out on the experiment's held-out layouts, unfilmed,
/// episode k on the k-th of the run's `tasks`.
fn evaluate_final(
    run: &Path,
    round: u64,
    config: &ExperimentConfig,
    tasks: &[TaskKind],
    max_frames: usize,
) -> anyhow::Result<RolloutResults> {
    let policy_dir = RunDir::at(run).model_dir(round).join(POLICY_DIR);
    let policy = PolicyDir::load(&policy_dir).with_context(|| format!("loading {}", policy_dir.display()))?;
    let stats = policy.stats.clone().context("the exported policy has no normalisation statistics")?;
    let tokenizer = policy.tokenizer()?.context("the exported policy has no tokenizer")?;
    let sim_policy = SimPolicy::new(&policy.cfg, &policy.weights, stats, &tokenizer, tasks, &Device::flex())?;
    let source = policy_dir.display().to_string();
    let options =
        SimEvalOptions { episodes: config.eval_episodes, seed: config.eval_seed, max_frames, video_size: None };
    evaluate_in_sim(Agent::Policy { policy: &sim_policy, source: &source }, &options, &run.join("final_sim"), |_, _| {})
}
