//! An experiment as its TOML file describes it (arms x seeds, the final sim evaluation), and what each finished
//! run of the runner leaves behind (`final.json`, and its last held-out evaluation).

use std::path::{Path, PathBuf};

use anyhow::Context;
use fedvla_aggregator::config::RunConfig;
use fedvla_aggregator::records::{MetricsLine, RolloutResults};
use fedvla_aggregator::run_dir::write_atomic;
use fedvla_federation::EvalMetrics;
use serde::{Deserialize, Serialize};

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
    /// Runs at once (each federation keeps about `num-clients` cores busy).
    #[serde(default = "one")]
    pub parallel_runs: usize,
    pub arms: Vec<Arm>,
}

fn one() -> usize {
    1
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

/// What a finished run leaves in `final.json`: its evaluation in the sim on held-out layouts (where its runner asked
/// for one: an experiment's runs, not a search's trials, which are judged on the server's held-out episodes alone),
/// and its wall time.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FinalEvaluation {
    /// The last round, whose global model was evaluated.
    pub round: u64,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sim: Option<RolloutResults>,
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
        anyhow::ensure!(config.parallel_runs > 0, "{}: parallel-runs must be at least 1", path.display());
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

pub fn write_final(run: &Path, evaluation: &FinalEvaluation) -> anyhow::Result<()> {
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

/// A run's last held-out evaluation on the server's episodes (every run evaluates its last round).
pub fn last_heldout(metrics: &[MetricsLine]) -> Option<&EvalMetrics> {
    metrics.iter().rev().find_map(|l| l.global.as_ref()?.eval.as_ref())
}
