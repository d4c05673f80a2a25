//! The one runner of whole runs, for an experiment's grid and a search's trials alike: each run (a federation or
//! its centralized baseline) in its own folder, its last global model evaluated where the run asks (in the sim, on
//! held-out layouts), then `final.json` written last. A run whose `final.json` is there is never run again, so a
//! killed experiment or search resumes where it stopped; a run that did not finish starts over.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::time::Instant;

use anyhow::Context;
use burn::tensor::Device;
use fedvla_aggregator::config::{RunConfig, WorkloadKind};
use fedvla_aggregator::records::{RolloutResults, read_metrics};
use fedvla_aggregator::run_dir::{POLICY_DIR, RunDir};
use fedvla_data::LeRobotDataset;
use fedvla_learner::rollout::SimPolicy;
use fedvla_policy::PolicyDir;
use fedvla_sim::TaskKind;
use fedvla_workloads::datagen::ensure_unrecorded;
use fedvla_workloads::sim_eval::{Agent, SimEvalOptions, evaluate_in_sim};
use fedvla_workloads::smolvla::{dataset_root, ensure_dataset, rollout_tasks};
use indicatif::{ProgressBar, ProgressStyle};

use super::config::{ExperimentConfig, FINAL_FILE, FinalEvaluation, Mode, last_heldout, read_final, write_final};
use super::report;
use crate::runs::{self, Bars};

/// One whole run: where it goes, what it trains, and how its last global model is judged.
#[derive(Debug, Clone)]
pub struct RunSpec {
    /// What the progress lines call it.
    pub label: String,
    pub path: PathBuf,
    pub mode: Mode,
    pub config: RunConfig,
    /// The sim layouts the last global model is rolled out on after training; `None`: judged by the server's
    /// held-out evaluation alone.
    pub final_sim: Option<Layouts>,
}

/// Sim layouts of seeds `seed..seed + episodes`, which no dataset a run trains on may record.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Layouts {
    pub episodes: usize,
    pub seed: u64,
}

/// Called with a run's folder as it starts (the CLI moves its log there).
pub type OnStart<'a> = &'a (dyn Fn(&Path) -> anyhow::Result<()> + Sync);

/// Runs every arm on every seed that has not finished yet, then writes the report. Returns the report's folder.
pub fn run(config: &ExperimentConfig, on_start: OnStart<'_>) -> anyhow::Result<PathBuf> {
    let dir = config.dir();
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    let layouts = Layouts { episodes: config.eval_episodes, seed: config.eval_seed };
    let grid = config
        .arms
        .iter()
        .flat_map(|arm| config.seeds.iter().map(move |&seed| (arm, seed)))
        .map(|(arm, seed)| {
            Ok(RunSpec {
                label: format!("{} seed {seed}", arm.name),
                path: config.run_path(arm, seed),
                mode: arm.mode,
                config: config.run_config(arm, seed)?,
                final_sim: Some(layouts),
            })
        })
        .collect::<anyhow::Result<Vec<_>>>()?;
    execute(&grid, config.parallel_runs, on_start)?;
    report::write(config)?;
    Ok(dir)
}

/// Runs `runs` (those not finished yet), up to `parallel` at a time, with one progress bar over them all.
/// Returns each run's final evaluation, in the order of `runs`. The first failure stops every worker from taking
/// another run and is returned once the runs in flight end.
pub fn execute(runs: &[RunSpec], parallel: usize, on_start: OnStart<'_>) -> anyhow::Result<Vec<FinalEvaluation>> {
    let unfinished: Vec<&RunSpec> = runs.iter().filter(|r| !r.path.join(FINAL_FILE).exists()).collect();
    record_datasets(&unfinished)?;
    let bar = ProgressBar::new(runs.len() as u64);
    bar.set_style(ProgressStyle::with_template("[{bar:30}] {pos}/{len} runs {msg} ({elapsed}, eta {eta})")?);
    bar.set_position((runs.len() - unfinished.len()) as u64);
    let next = AtomicUsize::new(0);
    let failed = AtomicBool::new(false);
    let outcomes = std::thread::scope(|scope| -> anyhow::Result<Vec<(usize, anyhow::Result<FinalEvaluation>)>> {
        let workers: Vec<_> = (0..parallel.clamp(1, runs.len().max(1)))
            .map(|_| {
                scope.spawn(|| {
                    let mut outcomes = Vec::new();
                    while !failed.load(Ordering::SeqCst) {
                        let i = next.fetch_add(1, Ordering::SeqCst);
                        let Some(spec) = runs.get(i) else { break };
                        let outcome = execute_one(spec, on_start, &bar);
                        failed.fetch_or(outcome.is_err(), Ordering::SeqCst);
                        outcomes.push((i, outcome));
                    }
                    outcomes
                })
            })
            .collect();
        let mut outcomes = Vec::new();
        for worker in workers {
            outcomes.extend(worker.join().map_err(|_| anyhow::anyhow!("a worker of the runner panicked"))?);
        }
        Ok(outcomes)
    })?;
    bar.finish_and_clear();
    let mut evaluations: Vec<Option<FinalEvaluation>> = vec![None; runs.len()];
    for (i, outcome) in outcomes {
        evaluations[i] = Some(outcome?);
    }
    evaluations.into_iter().zip(runs).map(|(e, r)| e.with_context(|| format!("{}: not run", r.label))).collect()
}

/// Records the embedded datasets `runs` train on that are not recorded yet, one at a time, before any run starts:
/// runs in parallel would otherwise each start recording the same one.
fn record_datasets(runs: &[&RunSpec]) -> anyhow::Result<()> {
    for spec in runs.iter().filter(|r| r.config.workload == WorkloadKind::Smolvla) {
        ensure_dataset(&spec.config).with_context(|| spec.label.clone())?;
    }
    Ok(())
}

/// One run, or its final evaluation where it finished before.
fn execute_one(spec: &RunSpec, on_start: OnStart<'_>, bar: &ProgressBar) -> anyhow::Result<FinalEvaluation> {
    let path = &spec.path;
    if path.join(FINAL_FILE).exists() {
        return read_final(path);
    }
    // A run that did not finish is started over: a half-written run is not a result.
    if path.exists() {
        std::fs::remove_dir_all(path).with_context(|| format!("removing the unfinished {}", path.display()))?;
    }
    let run_dir = RunDir::create_at(path, &spec.config)?;
    on_start(path)?;
    bar.set_message(spec.label.clone());
    let started = Instant::now();
    let result = match spec.mode {
        Mode::Centralized => runs::centralized(spec.config.clone(), run_dir, &Bars::hidden()),
        Mode::Federated => runs::federated(spec.config.clone(), run_dir, &Bars::hidden()).map(drop),
    };
    result.with_context(|| format!("{} ({})", spec.label, path.display()))?;
    let train_seconds = started.elapsed().as_secs_f64();
    let metrics = read_metrics(path)?;
    let round = metrics.last().map(|l| l.round).with_context(|| format!("{}: no metrics", path.display()))?;
    let heldout_loss = last_heldout(&metrics).map(|e| e.heldout_loss);
    let sim = spec.final_sim.map(|layouts| evaluate_final(spec, round, layouts)).transpose()?;
    let loss = heldout_loss.map_or("none".to_owned(), |l| format!("{l:.4}"));
    let mut line = format!("{}: held-out loss {loss}", spec.label);
    if let Some(sim) = &sim {
        let success = sim.success_rate.unwrap_or(0.0);
        line += &format!(", sim success {success:.2} on {} held-out layouts", sim.episodes.len());
    }
    let line = format!("{line} ({train_seconds:.0} s)");
    // Where there is no terminal to draw the bar on (a log of a search of hours), the line still goes out.
    if bar.is_hidden() {
        println!("{line}");
    } else {
        bar.println(line);
    }
    let evaluation = FinalEvaluation { round, sim, train_seconds };
    write_final(path, &evaluation)?;
    // The clients' shards are copies of the dataset (over a gigabyte a federated run) that nothing reads once the
    // run is over; its models, metrics and rollouts stay.
    let shards = path.join(runs::SHARDS_DIR);
    if shards.exists() {
        std::fs::remove_dir_all(&shards).with_context(|| format!("removing {}", shards.display()))?;
    }
    bar.inc(1);
    Ok(evaluation)
}

/// The run's last global model (its LeRobot export) rolled out on `layouts`, unfilmed, episode k on the k-th of the
/// tasks its dataset records; refused where that dataset recorded any of the layouts.
fn evaluate_final(spec: &RunSpec, round: u64, layouts: Layouts) -> anyhow::Result<RolloutResults> {
    let root = dataset_root(&spec.config)?;
    ensure_unrecorded(&root, layouts.seed..layouts.seed + layouts.episodes as u64)
        .with_context(|| spec.label.clone())?;
    let dataset = LeRobotDataset::open(&root).with_context(|| format!("opening {}", root.display()))?;
    let tasks: Vec<TaskKind> = rollout_tasks(&dataset);
    let policy_dir = RunDir::at(&spec.path).model_dir(round).join(POLICY_DIR);
    let policy = PolicyDir::load(&policy_dir).with_context(|| format!("loading {}", policy_dir.display()))?;
    let stats = policy.stats.clone().context("the exported policy has no normalisation statistics")?;
    let tokenizer = policy.tokenizer()?.context("the exported policy has no tokenizer")?;
    let sim_policy = SimPolicy::new(&policy.cfg, &policy.weights, stats, &tokenizer, &tasks, &Device::flex())?;
    let source = policy_dir.display().to_string();
    let options = SimEvalOptions {
        episodes: layouts.episodes,
        seed: layouts.seed,
        max_frames: spec.config.rollout_max_frames as usize,
        video_size: None,
    };
    let agent = Agent::Policy { policy: &sim_policy, source: &source };
    evaluate_in_sim(agent, &options, &spec.path.join("final_sim"), |_, _| {})
}
