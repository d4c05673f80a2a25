//! A search as its TOML file describes it: the base configuration, the search space and its seed, the rungs of
//! successive halving, and how the winner is judged afresh; the trials it samples from them.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::Context;
use fedvla_aggregator::config::{KeepModels, RunConfig, WorkloadKind};
use fedvla_workloads::smolvla::dataset_root;
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use serde::{Deserialize, Serialize};

/// A search, as its TOML file says it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case", deny_unknown_fields)]
pub struct TuneConfig {
    pub name: String,
    /// Run-configuration overrides (`key=value ...`, as `--run-config` takes them) on configs/default.toml: the base
    /// configuration, trial 0 of the search and the one the winner is judged against.
    #[serde(default)]
    pub run_config: String,
    /// Seeds which configurations are sampled (the trials' federations all run on the base's `seed`).
    pub search_seed: u64,
    /// Trials of the first rung: the base configuration, and `trials - 1` sampled from `space`.
    pub trials: usize,
    /// Each rung's budget in rounds: a trial of a rung is a federation of that many rounds (its learning-rate
    /// schedule fitted to them, as `simulate` would run it). The last is the base's `num-server-rounds`, the budget
    /// the winner and the base are judged at.
    pub rungs: Vec<u64>,
    /// After each rung but the last, the best 1/`reduction` of its trials (at least one) go on to the next, and the
    /// base with them.
    pub reduction: usize,
    /// Trials run at once (each federation keeps about `num-clients` cores busy).
    #[serde(default = "one")]
    pub parallel_trials: usize,
    /// Where the search's folder goes (`<output-dir>/<name>/`).
    #[serde(default = "default_output_dir")]
    pub output_dir: String,
    /// The search space: a run-configuration key and the range its values are drawn from, or (`joint`) a label and
    /// the override strings one of which is applied whole.
    pub space: BTreeMap<String, Range>,
    pub judge: Judge,
}

fn one() -> usize {
    1
}

fn default_output_dir() -> String {
    "outputs/tune".into()
}

/// Where a key's values are drawn from. Reals are rounded to 3 significant digits, so that a configuration reads
/// as it would be written.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case", deny_unknown_fields)]
pub enum Range {
    /// A real, uniform between the bounds.
    Uniform([f64; 2]),
    /// A real whose logarithm is uniform between the bounds' (both above 0): learning rates, mu.
    LogUniform([f64; 2]),
    /// An integer, uniform between the bounds, both included.
    IntUniform([i64; 2]),
    /// An integer whose logarithm is uniform between the bounds' (both above 0), both included: local steps, batch
    /// sizes.
    IntLogUniform([i64; 2]),
    /// One of these values (a strategy's name, a switch).
    Choice(Vec<toml::Value>),
    /// One of these override strings, applied whole: keys that move together, such as `local-steps=200
    /// batch-size=8` against `local-steps=100 batch-size=16` at a fixed sample count.
    Joint(Vec<String>),
}

/// How the search's winner and the base configuration are judged after the search: on seeds, data and sim layouts
/// the search never used, with intervals over seeds (an `experiment` of two arms).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case", deny_unknown_fields)]
pub struct Judge {
    /// Run seeds of the judged runs, none the search's.
    pub seeds: Vec<u64>,
    /// Overrides of both judged arms that give them data the search never saw: for the embedded dataset
    /// `dataset-seed` (a recording of other layouts), or another `dataset`.
    pub run_config: String,
    /// Sim episodes each judged run's last model is rolled out on, on layouts of seeds `eval-seed..`.
    pub eval_episodes: usize,
    pub eval_seed: u64,
}

/// Keys the search sets itself on every trial: its budget, its seed and what a trial does not need (its rollouts).
const SEARCH_KEYS: [&str; 5] =
    ["num-server-rounds", "seed", "eval-every", "rollout-episodes", "client-rollout-episodes"];

/// One configuration under search: the value drawn for each key of the space (none for the base).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Trial {
    pub id: usize,
    pub params: BTreeMap<String, toml::Value>,
}

impl Trial {
    /// The trial as `--run-config` overrides on the base: `key=value` for each drawn value, a joint choice as it is.
    pub fn overrides(&self, space: &BTreeMap<String, Range>) -> String {
        self.params
            .iter()
            .map(|(key, value)| match (space.get(key), value) {
                (Some(Range::Joint(_)), toml::Value::String(joint)) => joint.clone(),
                (_, value) => format!("{key}={}", value_text(value)),
            })
            .collect::<Vec<_>>()
            .join(" ")
    }
}

/// A value as an override writes it: strings bare (a choice of strategy names reads `strategy=fedavgm`).
pub fn value_text(value: &toml::Value) -> String {
    match value {
        toml::Value::String(s) => s.clone(),
        other => other.to_string(),
    }
}

impl TuneConfig {
    pub fn load(path: &Path) -> anyhow::Result<Self> {
        let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
        let config: Self = toml::from_str(&text).with_context(|| format!("parsing {}", path.display()))?;
        config.check().with_context(|| format!("{}", path.display()))?;
        Ok(config)
    }

    /// Refuses a search that could not run or would not judge fairly, naming what is wrong.
    pub fn check(&self) -> anyhow::Result<()> {
        anyhow::ensure!(
            !self.name.is_empty() && self.name.chars().all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_'),
            "name {:?} must be [A-Za-z0-9_-]",
            self.name
        );
        let base = self.base()?;
        anyhow::ensure!(base.workload == WorkloadKind::Smolvla, "fedvla tune judges in the sim: workload=smolvla");
        anyhow::ensure!(self.trials >= 2, "trials must be at least 2 (the base and one sampled), got {}", self.trials);
        anyhow::ensure!(self.reduction >= 2, "reduction must be at least 2, got {}", self.reduction);
        anyhow::ensure!(self.parallel_trials >= 1, "parallel-trials must be at least 1");
        anyhow::ensure!(
            self.rungs.first().is_some_and(|&r| r > 0) && self.rungs.windows(2).all(|w| w[0] < w[1]),
            "rungs must be rounds, above 0 and rising, got {:?}",
            self.rungs
        );
        anyhow::ensure!(
            self.rungs.last() == Some(&base.num_server_rounds),
            "the last rung ({:?} rounds) must be the base configuration's num-server-rounds ({}): the budget the \
             winner is judged at against the base",
            self.rungs.last(),
            base.num_server_rounds
        );
        anyhow::ensure!(!self.space.is_empty(), "the search space is empty");
        for (key, range) in &self.space {
            for candidate in range.extremes(key)? {
                let searched = overridden_keys(&candidate);
                if let Some(own) = searched.iter().find(|k| SEARCH_KEYS.contains(&k.as_str())) {
                    anyhow::bail!("space.{key}: {own} is the search's own to set on every trial");
                }
                base.with_overrides(&candidate).with_context(|| format!("space.{key}: `{candidate}`"))?;
            }
        }
        self.check_judge(&base)
    }

    fn check_judge(&self, base: &RunConfig) -> anyhow::Result<()> {
        let judge = &self.judge;
        anyhow::ensure!(!judge.seeds.is_empty(), "judge.seeds is empty");
        anyhow::ensure!(
            !judge.seeds.contains(&base.seed),
            "judge.seeds {:?} include the search's seed {}: judge on seeds the search never ran",
            judge.seeds,
            base.seed
        );
        anyhow::ensure!(judge.eval_episodes > 0, "judge.eval-episodes must be at least 1");
        let searched: Vec<String> = self.space.iter().flat_map(|(k, r)| r.keys(k)).collect();
        let judged = overridden_keys(&judge.run_config);
        if let Some(key) = judged.iter().find(|k| searched.contains(k) || SEARCH_KEYS.contains(&k.as_str())) {
            anyhow::bail!("judge.run-config sets {key}, which the search sets: it may only change the data");
        }
        let judged = base.with_overrides(&judge.run_config).context("judge.run-config")?;
        anyhow::ensure!(
            dataset_root(&judged)? != dataset_root(base)?,
            "the judged runs train on the search's dataset {}: give judge.run-config another dataset-seed (the \
             embedded dataset) or dataset",
            dataset_root(base)?.display()
        );
        Ok(())
    }

    /// The base configuration: configs/default.toml with `run-config`.
    pub fn base(&self) -> anyhow::Result<RunConfig> {
        RunConfig::default().with_overrides(&self.run_config).context("run-config")
    }

    /// The search's folder.
    pub fn dir(&self) -> PathBuf {
        Path::new(&self.output_dir).join(&self.name)
    }

    /// Every trial of the first rung: the base (0), then `trials - 1` drawn from the space by `search-seed`.
    pub fn sample(&self) -> Vec<Trial> {
        let mut rng = StdRng::seed_from_u64(self.search_seed);
        let base = Trial { id: 0, params: BTreeMap::new() };
        let drawn = (1..self.trials).map(|id| Trial {
            id,
            params: self.space.iter().map(|(key, range)| (key.clone(), range.draw(&mut rng))).collect(),
        });
        std::iter::once(base).chain(drawn).collect()
    }

    /// The configuration of `trial` as a rung of `rounds` runs it: its overrides on the base, evaluated on the
    /// server's held-out episodes after its last round, without sim rollouts (a trial is judged on the held-out
    /// loss).
    pub fn trial_config(&self, trial: &Trial, rounds: u64) -> anyhow::Result<RunConfig> {
        let config = self.full_config(trial)?;
        Ok(RunConfig {
            num_server_rounds: rounds,
            eval_every: rounds,
            keep_models: KeepModels::Evaluated,
            rollout_episodes: 0,
            client_rollout_episodes: 0,
            ..config
        })
    }

    /// The configuration of `trial` as `simulate` runs it at the whole budget: what best.toml holds.
    pub fn full_config(&self, trial: &Trial) -> anyhow::Result<RunConfig> {
        let overrides = trial.overrides(&self.space);
        self.base()?.with_overrides(&overrides).with_context(|| format!("trial {}: `{overrides}`", trial.id))
    }

    /// Where `trial`'s run at `rounds` goes.
    pub fn trial_path(&self, trial: &Trial, rounds: u64) -> PathBuf {
        self.dir().join("trials").join(format!("trial_{:03}", trial.id)).join(format!("rounds_{rounds}"))
    }
}

impl Range {
    /// A value drawn from the range.
    fn draw(&self, rng: &mut StdRng) -> toml::Value {
        match self {
            Self::Uniform([low, high]) => {
                toml::Value::Float(significant(rng.random_range(*low..=*high)).clamp(*low, *high))
            }
            Self::LogUniform([low, high]) => {
                toml::Value::Float(significant(rng.random_range(low.ln()..=high.ln()).exp()).clamp(*low, *high))
            }
            Self::IntUniform([low, high]) => toml::Value::Integer(rng.random_range(*low..=*high)),
            Self::IntLogUniform([low, high]) => {
                let ln = rng.random_range((*low as f64).ln()..=(*high as f64).ln());
                toml::Value::Integer((ln.exp().round() as i64).clamp(*low, *high))
            }
            Self::Choice(values) => values[rng.random_range(0..values.len())].clone(),
            Self::Joint(overrides) => toml::Value::String(overrides[rng.random_range(0..overrides.len())].clone()),
        }
    }

    /// The overrides that span what `key`'s range can give (its bounds, or every choice), after checking the range
    /// itself.
    fn extremes(&self, key: &str) -> anyhow::Result<Vec<String>> {
        let bounds = |low: f64, high: f64, log: bool| {
            anyhow::ensure!(
                low.is_finite() && high.is_finite() && low <= high && (!log || low > 0.0),
                "space.{key}: bounds [{low}, {high}] must be finite and rising{}",
                if log { ", above 0" } else { "" }
            );
            Ok(())
        };
        let texts = |values: &[toml::Value]| values.iter().map(|v| format!("{key}={}", value_text(v))).collect();
        match self {
            Self::Uniform([low, high]) | Self::LogUniform([low, high]) => {
                bounds(*low, *high, matches!(self, Self::LogUniform(_)))?;
                Ok(texts(&[toml::Value::Float(*low), toml::Value::Float(*high)]))
            }
            Self::IntUniform([low, high]) | Self::IntLogUniform([low, high]) => {
                bounds(*low as f64, *high as f64, matches!(self, Self::IntLogUniform(_)))?;
                Ok(texts(&[toml::Value::Integer(*low), toml::Value::Integer(*high)]))
            }
            Self::Choice(values) => {
                anyhow::ensure!(!values.is_empty(), "space.{key}: no choices");
                if let Some(v) = values.iter().find(|v| value_text(v).contains(char::is_whitespace)) {
                    anyhow::bail!("space.{key}: choice {v} has white space; several keys at once are a `joint`");
                }
                Ok(texts(values))
            }
            Self::Joint(overrides) => {
                anyhow::ensure!(!overrides.is_empty(), "space.{key}: no joint choices");
                Ok(overrides.clone())
            }
        }
    }

    /// The run-configuration keys the range sets.
    fn keys(&self, key: &str) -> Vec<String> {
        match self {
            Self::Joint(overrides) => overrides.iter().flat_map(|o| overridden_keys(o)).collect(),
            _ => vec![key.to_owned()],
        }
    }
}

impl std::fmt::Display for Range {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let list = |values: &mut dyn Iterator<Item = String>| values.collect::<Vec<_>>().join(", ");
        match self {
            Self::Uniform([low, high]) => write!(f, "uniform in [{low}, {high}]"),
            Self::LogUniform([low, high]) => write!(f, "log-uniform in [{low}, {high}]"),
            Self::IntUniform([low, high]) => write!(f, "integer, uniform in [{low}, {high}]"),
            Self::IntLogUniform([low, high]) => write!(f, "integer, log-uniform in [{low}, {high}]"),
            Self::Choice(values) => write!(f, "one of {}", list(&mut values.iter().map(value_text))),
            Self::Joint(overrides) => write!(f, "one of {}", list(&mut overrides.iter().map(|o| format!("`{o}`")))),
        }
    }
}

/// The keys of `key=value ...` overrides.
fn overridden_keys(overrides: &str) -> Vec<String> {
    overrides.split_whitespace().map(|pair| pair.split_once('=').map_or(pair, |(key, _)| key).to_owned()).collect()
}

/// `x` rounded to 3 significant digits.
fn significant(x: f64) -> f64 {
    if x == 0.0 || !x.is_finite() {
        return x;
    }
    let scale = 10f64.powi(2 - x.abs().log10().floor() as i32);
    (x * scale).round() / scale
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn draws_stay_in_their_ranges_and_read_as_written() {
        let mut rng = StdRng::seed_from_u64(7);
        for _ in 0..200 {
            let toml::Value::Float(lr) = Range::LogUniform([1e-4, 1e-2]).draw(&mut rng) else { panic!("a real") };
            assert!((1e-4..=1e-2).contains(&lr) && significant(lr) == lr, "{lr}");
            let toml::Value::Integer(steps) = Range::IntLogUniform([25, 400]).draw(&mut rng) else { panic!("int") };
            assert!((25..=400).contains(&steps), "{steps}");
        }
        assert_eq!(significant(0.000_123_456), 0.000_123);
        assert_eq!(significant(98_765.0), 98_800.0);
    }
}
