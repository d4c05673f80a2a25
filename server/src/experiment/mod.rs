//! `fedvla experiment --config configs/experiments/NAME.toml`: arms (the centralized baseline and federation
//! configurations) x seeds, each a whole run in `<out>/<arm>/seed_<s>/`, then a final evaluation of each run's
//! last global model in the sim on held-out layouts, then the report (`report.md`, `report.json`, PNG plots).
//! A run that finished (its `final.json` is there) is never run again, so a killed experiment resumes where it
//! stopped; a run that did not finish starts over.

pub mod plot;
pub mod report;
pub mod stats;

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::Context;
use burn::tensor::Device;
use fedvla_learner::rollout::SimPolicy;
use fedvla_policy::PolicyDir;
use indicatif::{ProgressBar, ProgressStyle};
use serde::{Deserialize, Serialize};

use fedvla_aggregator::config::RunConfig;
use fedvla_aggregator::records::RolloutResults;
use fedvla_aggregator::run_dir::{POLICY_DIR, RunDir, write_atomic};
use fedvla_workloads::sim_eval::{Agent, SimEvalOptions, evaluate_in_sim};

use crate::runs::{self, Bars};

/// An experiment, as its TOML file says it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case", deny_unknown_fields)]
pub struct ExperimentConfig {
    pub name: String,
    /// Every arm runs once per seed (the run configuration's `seed`).
    pub seeds: Vec<u64>,
    /// Sim episodes each run's last global model is evaluated on after training, on layouts of seeds
    /// `eval-seed..`, which no dataset records.
    pub eval_episodes: usize,
    #[serde(default = "default_eval_seed")]
    pub eval_seed: u64,
    /// Run-configuration overrides every arm starts from (`key=value ...`, as `--run-config` takes them).
    #[serde(default)]
    pub run_config: String,
    /// Where the experiment's folder goes (`<output-dir>/<name>/`).
    #[serde(default = "default_output_dir")]
    pub output_dir: String,
    pub arms: Vec<Arm>,
}

fn default_eval_seed() -> u64 {
    fedvla_workloads::sim_eval::DEFAULT_SEED
}

fn default_output_dir() -> String {
    "outputs/experiments".into()
}

/// One configuration under comparison.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case", deny_unknown_fields)]
pub struct Arm {
    pub name: String,
    pub mode: Mode,
    /// Overrides on top of the experiment's.
    #[serde(default)]
    pub run_config: String,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Mode {
    /// `fedvla train`: one trainer on the union of the clients' training episodes.
    Centralized,
    /// `fedvla simulate`: a server and `num-clients` native clients over loopback.
    Federated,
}

/// What a finished run leaves in `final.json`: its held-out evaluation in the sim, and its wall time.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FinalEvaluation {
    /// The last round, whose global model was evaluated.
    pub round: u64,
    pub sim: RolloutResults,
    /// Training wall time (the run, without this final evaluation), seconds.
    pub train_seconds: f64,
}

pub const FINAL_FILE: &str = "final.json";

impl ExperimentConfig {
    pub fn load(path: &Path) -> anyhow::Result<Self> {
        let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
        let config: Self = toml::from_str(&text).with_context(|| format!("parsing {}", path.display()))?;
        anyhow::ensure!(!config.seeds.is_empty() && !config.arms.is_empty(), "{}: no seeds or no arms", path.display());
        anyhow::ensure!(config.eval_episodes > 0, "{}: eval-episodes must be at least 1", path.display());
        for arm in &config.arms {
            anyhow::ensure!(
                !arm.name.is_empty() && arm.name.chars().all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_'),
                "{}: arm name {:?} must be [A-Za-z0-9_-]",
                path.display(),
                arm.name
            );
            config.run_config(arm, config.seeds[0])?;
        }
        Ok(config)
    }

    /// The experiment's folder.
    pub fn dir(&self) -> PathBuf {
        Path::new(&self.output_dir).join(&self.name)
    }

    /// Where `arm`'s run of `seed` goes.
    pub fn run_path(&self, arm: &Arm, seed: u64) -> PathBuf {
        self.dir().join(&arm.name).join(format!("seed_{seed}"))
    }

    /// The run configuration of `arm` on `seed`.
    pub fn run_config(&self, arm: &Arm, seed: u64) -> anyhow::Result<RunConfig> {
        let config = RunConfig::default()
            .with_overrides(&self.run_config)
            .and_then(|c| c.with_overrides(&arm.run_config))
            .with_context(|| format!("arm {}", arm.name))?;
        Ok(RunConfig { seed, ..config })
    }
}

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
        let sim = evaluate_final(&path, last, config, run_config.rollout_max_frames as usize)?;
        bar.println(format!(
            "{} seed {seed}: sim success {:.2} on {} held-out layouts ({:.0} s)",
            arm.name,
            sim.success_rate.unwrap_or(0.0),
            sim.episodes.len(),
            train_seconds
        ));
        write_final(&path, &FinalEvaluation { round: last, sim, train_seconds })?;
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

/// The run's last global model (its LeRobot export) rolled out on the experiment's held-out layouts, unfilmed.
fn evaluate_final(
    run: &Path,
    round: u64,
    config: &ExperimentConfig,
    max_frames: usize,
) -> anyhow::Result<RolloutResults> {
    let policy_dir = RunDir::at(run).model_dir(round).join(POLICY_DIR);
    let policy = PolicyDir::load(&policy_dir).with_context(|| format!("loading {}", policy_dir.display()))?;
    let stats = policy.stats.clone().context("the exported policy has no normalisation statistics")?;
    let tokenizer = policy.tokenizer()?.context("the exported policy has no tokenizer")?;
    let sim_policy = SimPolicy::new(&policy.cfg, &policy.weights, stats, &tokenizer, &Device::flex())?;
    let source = policy_dir.display().to_string();
    let options =
        SimEvalOptions { episodes: config.eval_episodes, seed: config.eval_seed, max_frames, video_size: None };
    evaluate_in_sim(Agent::Policy { policy: &sim_policy, source: &source }, &options, &run.join("final_sim"), |_, _| {})
}

fn write_final(run: &Path, evaluation: &FinalEvaluation) -> anyhow::Result<()> {
    let bytes = serde_json::to_vec_pretty(evaluation).expect("the final evaluation serializes");
    write_atomic(&run.join(FINAL_FILE), &bytes)?;
    Ok(())
}

/// A finished run's final evaluation.
pub fn read_final(run: &Path) -> anyhow::Result<FinalEvaluation> {
    let path = run.join(FINAL_FILE);
    let text = std::fs::read_to_string(&path).with_context(|| format!("reading {}", path.display()))?;
    serde_json::from_str(&text).with_context(|| format!("parsing {}", path.display()))
}
