//! `outputs/<date_time>/`: resolved config, per-round metrics, global models, clients' rollouts. Crash-safe:
//! every file is written atomically ([`fedvla_fs::write_atomic`]), a round's model directory is written under a
//! temporary name and renamed, metrics lines are appended and synced once per round (a torn last line is dropped
//! on resume).

use std::fs::{self, File, OpenOptions};
use std::io::Write;
use std::path::{Path, PathBuf};

use fedvla_federation::{BoxError, NamedTensors, NormalizationStats, TensorError};

use crate::config::{ConfigError, RunConfig};
pub use crate::records::{METRICS_FILE, RESULTS_FILE};
use crate::records::{MetricsLine, RolloutResults, SimFigures};

pub const CONFIG_FILE: &str = "config.toml";
pub const MODELS_DIR: &str = "global_model";
/// In a round's model directory: the LeRobot policy directory and the sim rollouts of the global model.
pub const POLICY_DIR: &str = "policy";
pub const ROLLOUTS_DIR: &str = "rollouts";
pub const LOG_FILE: &str = "server.log";
/// Clients' evaluations of the global model: `evaluate/round_N/client_K/` (rollout videos and results.json).
pub const EVALUATE_DIR: &str = "evaluate";
/// The trainable tensors of each round; resume reads it back.
pub const TRAINABLE_FILE: &str = "trainable.safetensors";
/// What the strategy carries into the next round (server moments, control variates), when it carries anything.
pub const STRATEGY_FILE: &str = "strategy.safetensors";
/// The normalisation statistics a run agreed by federated statistics, written once before round 1.
pub const NORM_STATS_FILE: &str = "norm_stats.json";

#[derive(Debug, thiserror::Error)]
pub enum RunDirError {
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error(transparent)]
    Config(#[from] ConfigError),
    /// A record of the run directory (a metrics line, the volunteer registry) that does not parse.
    #[error("{path} line {line}: {message}")]
    Metrics { path: PathBuf, line: usize, message: String },
    #[error("global model of round {round}: {source}")]
    Model { round: u64, source: TensorError },
    #[error("exporting round {round}: {source}")]
    Export { round: u64, source: BoxError },
}

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> RunDirError + '_ {
    move |source| RunDirError::Io { path: path.to_owned(), source }
}

/// Writes one round's global model into a fresh directory. The LeRobot policy export and the sim rollouts plug in
/// here. `config` is the run's configuration as the round ran it: the operator may have changed settings (e.g.
/// rollout-episodes). Returns what the export measured in the sim, for the round's metrics.
pub trait ModelExporter: Send + Sync {
    fn export(
        &self,
        round: u64,
        global: &NamedTensors,
        config: &RunConfig,
        dir: &Path,
    ) -> Result<Option<SimFigures>, BoxError>;

    /// Exports with `stats` from now on (the run's, once agreed by federated statistics). Exporters that write no
    /// normalisation ignore them.
    fn set_norm_stats(&self, stats: &NormalizationStats) -> Result<(), BoxError> {
        let _ = stats;
        Ok(())
    }
}

/// Writes the trainable tensors as `trainable.safetensors` (always on: resume needs it).
#[derive(Debug, Clone, Copy, Default)]
pub struct TrainableSafetensors;

impl ModelExporter for TrainableSafetensors {
    fn export(
        &self,
        _round: u64,
        global: &NamedTensors,
        _config: &RunConfig,
        dir: &Path,
    ) -> Result<Option<SimFigures>, BoxError> {
        fedvla_fs::write_atomic(&dir.join(TRAINABLE_FILE), &global.to_safetensors()?)?;
        Ok(None)
    }
}

/// One run's output directory.
#[derive(Debug, Clone)]
pub struct RunDir {
    path: PathBuf,
}

impl RunDir {
    /// Creates `<base>/<date_time>/` (suffixed if taken) and writes the resolved config.
    pub fn create(base: &Path, config: &RunConfig) -> Result<Self, RunDirError> {
        fs::create_dir_all(base).map_err(io(base))?;
        let stamp = chrono::Local::now().format("%Y-%m-%d_%H-%M-%S").to_string();
        let mut path = base.join(&stamp);
        let mut n = 1;
        while path.exists() {
            path = base.join(format!("{stamp}_{n}"));
            n += 1;
        }
        fs::create_dir(&path).map_err(io(&path))?;
        let dir = Self { path };
        dir.write_config(config)?;
        Ok(dir)
    }

    /// Creates the run directory `path` itself (an experiment names its runs' folders) and writes the resolved
    /// config; `path` must not exist yet.
    pub fn create_at(path: &Path, config: &RunConfig) -> Result<Self, RunDirError> {
        if let Some(parent) = path.parent() {
            fs::create_dir_all(parent).map_err(io(parent))?;
        }
        fs::create_dir(path).map_err(io(path))?;
        let dir = Self { path: path.to_owned() };
        dir.write_config(config)?;
        Ok(dir)
    }

    /// The run directory at `path`, for reading what it holds.
    pub fn at(path: &Path) -> Self {
        Self { path: path.to_owned() }
    }

    /// Opens an existing run for `--resume`, with the config it was started with.
    pub fn open(path: &Path) -> Result<(Self, RunConfig), RunDirError> {
        let config = RunConfig::load(&path.join(CONFIG_FILE))?;
        Ok((Self { path: path.to_owned() }, config))
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    pub fn write_config(&self, config: &RunConfig) -> Result<(), RunDirError> {
        write_atomic(&self.path.join(CONFIG_FILE), config.to_toml().as_bytes())
    }

    /// Records the statistics the run agreed by federated statistics.
    pub fn write_norm_stats(&self, stats: &NormalizationStats) -> Result<(), RunDirError> {
        let json = serde_json::to_vec_pretty(stats).expect("statistics serialize");
        write_atomic(&self.path.join(NORM_STATS_FILE), &json)
    }

    /// The statistics the run agreed, when it has.
    pub fn read_norm_stats(&self) -> Result<Option<NormalizationStats>, RunDirError> {
        let path = self.path.join(NORM_STATS_FILE);
        match fs::read(&path) {
            Ok(bytes) => serde_json::from_slice(&bytes).map(Some).map_err(|e| RunDirError::Metrics {
                line: e.line(),
                message: e.to_string(),
                path,
            }),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
            Err(source) => Err(RunDirError::Io { path, source }),
        }
    }

    /// The last round with a metrics line, dropping a torn last line left by a crash mid-write.
    pub fn last_completed_round(&self) -> Result<Option<u64>, RunDirError> {
        let path = self.path.join(METRICS_FILE);
        let text = match fs::read_to_string(&path) {
            Ok(t) => t,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(e) => return Err(io(&path)(e)),
        };
        let complete = &text[..text.rfind('\n').map_or(0, |i| i + 1)];
        if complete.len() != text.len() {
            tracing::warn!(path = %path.display(), "dropping a torn last metrics line");
            write_atomic(&path, complete.as_bytes())?;
        }
        let mut last = None;
        for (i, line) in complete.lines().enumerate() {
            let err = |message: String| RunDirError::Metrics { path: path.clone(), line: i + 1, message };
            let round = serde_json::from_str::<MetricsLine>(line).map_err(|e| err(e.to_string()))?.round;
            if last.is_some_and(|l| round != l + 1) || (last.is_none() && round != 0) {
                return Err(err(format!("round {round} does not follow round {last:?}")));
            }
            last = Some(round);
        }
        Ok(last)
    }

    /// Appends one round's metrics line and syncs it to disk.
    pub fn append_metrics(&self, line: &MetricsLine) -> Result<(), RunDirError> {
        let path = self.path.join(METRICS_FILE);
        let mut file = OpenOptions::new().create(true).append(true).open(&path).map_err(io(&path))?;
        let mut text = serde_json::to_string(line).expect("metrics serialize");
        text.push('\n');
        file.write_all(text.as_bytes()).map_err(io(&path))?;
        file.sync_data().map_err(io(&path))
    }

    /// Where client `client_id`'s evaluation during round `round` is filed.
    pub fn client_eval_dir(&self, round: u64, client_id: u64) -> PathBuf {
        self.path.join(EVALUATE_DIR).join(format!("round_{round}")).join(format!("client_{client_id}"))
    }

    /// Writes client `client_id`'s rollout results of round `round` as `evaluate/round_N/client_K/results.json`.
    pub fn write_client_results(
        &self,
        round: u64,
        client_id: u64,
        results: &RolloutResults,
    ) -> Result<(), RunDirError> {
        let dir = self.client_eval_dir(round, client_id);
        fs::create_dir_all(&dir).map_err(io(&dir))?;
        write_atomic(&dir.join(RESULTS_FILE), &serde_json::to_vec_pretty(results).expect("results serialize"))
    }

    pub fn model_dir(&self, round: u64) -> PathBuf {
        self.path.join(MODELS_DIR).join(format!("round_{round}"))
    }

    /// Writes `global_model/round_N/` through every exporter into a temporary directory, then renames it. Returns
    /// what the exporters measured in the sim.
    pub fn save_model(
        &self,
        round: u64,
        global: &NamedTensors,
        strategy_state: &NamedTensors,
        exporters: &[Box<dyn ModelExporter>],
        config: &RunConfig,
    ) -> Result<Option<SimFigures>, RunDirError> {
        let dir = self.model_dir(round);
        let tmp = dir.with_extension("tmp");
        if tmp.exists() {
            fs::remove_dir_all(&tmp).map_err(io(&tmp))?;
        }
        fs::create_dir_all(&tmp).map_err(io(&tmp))?;
        if !strategy_state.is_empty() {
            let bytes = strategy_state.to_safetensors().map_err(|source| RunDirError::Model { round, source })?;
            write_atomic(&tmp.join(STRATEGY_FILE), &bytes)?;
        }
        let mut measured = None;
        for exporter in exporters {
            let figures =
                exporter.export(round, global, config, &tmp).map_err(|source| RunDirError::Export { round, source })?;
            measured = measured.or(figures);
        }
        if dir.exists() {
            // Left by a run that crashed after saving but before its metrics line: this round is being redone.
            fs::remove_dir_all(&dir).map_err(io(&dir))?;
        }
        fs::rename(&tmp, &dir).map_err(io(&dir))?;
        fedvla_fs::sync_dir(self.path.join(MODELS_DIR).as_path()).map_err(io(&dir))?;
        Ok(measured)
    }

    /// The strategy's state after `round`; empty when it carried none.
    pub fn load_strategy_state(&self, round: u64) -> Result<NamedTensors, RunDirError> {
        let path = self.model_dir(round).join(STRATEGY_FILE);
        match fs::read(&path) {
            Ok(bytes) => NamedTensors::from_safetensors(&bytes).map_err(|source| RunDirError::Model { round, source }),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(NamedTensors::new()),
            Err(e) => Err(io(&path)(e)),
        }
    }

    pub fn load_model(&self, round: u64) -> Result<NamedTensors, RunDirError> {
        let path = self.model_dir(round).join(TRAINABLE_FILE);
        let bytes = fs::read(&path).map_err(io(&path))?;
        NamedTensors::from_safetensors(&bytes).map_err(|source| RunDirError::Model { round, source })
    }

    /// Opens `server.log` for appending.
    pub fn log_file(&self) -> Result<File, RunDirError> {
        let path = self.path.join(LOG_FILE);
        OpenOptions::new().create(true).append(true).open(&path).map_err(io(&path))
    }
}

/// Writes `bytes` to `path` atomically.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), RunDirError> {
    fedvla_fs::write_atomic(path, bytes).map_err(io(path))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn metrics_resume_point_and_torn_line() {
        let base = tempfile::tempdir().unwrap();
        let dir = RunDir::create(base.path(), &RunConfig::default()).unwrap();
        assert_eq!(dir.last_completed_round().unwrap(), None);
        dir.append_metrics(&MetricsLine { round: 0, ..MetricsLine::default() }).unwrap();
        dir.append_metrics(&MetricsLine { round: 1, ..MetricsLine::default() }).unwrap();
        let path = dir.path().join(METRICS_FILE);
        let mut f = OpenOptions::new().append(true).open(&path).unwrap();
        f.write_all(b"{\"round\": 2, \"glo").unwrap();
        assert_eq!(dir.last_completed_round().unwrap(), Some(1));
        assert_eq!(fs::read_to_string(&path).unwrap().lines().count(), 2);
        let (reopened, config) = RunDir::open(dir.path()).unwrap();
        assert_eq!(config, RunConfig::default());
        assert_eq!(reopened.last_completed_round().unwrap(), Some(1));
    }

    #[test]
    fn models_are_saved_and_loaded() {
        let base = tempfile::tempdir().unwrap();
        let dir = RunDir::create(base.path(), &RunConfig::default()).unwrap();
        let mut t = NamedTensors::new();
        t.insert("w", vec![2], vec![1.0, 2.0]).unwrap();
        let exporters: Vec<Box<dyn ModelExporter>> = vec![Box::new(TrainableSafetensors)];
        dir.save_model(3, &t, &NamedTensors::new(), &exporters, &RunConfig::default()).unwrap();
        dir.save_model(3, &t, &NamedTensors::new(), &exporters, &RunConfig::default()).unwrap();
        assert_eq!(dir.load_model(3).unwrap(), t);
        assert!(!dir.model_dir(3).with_extension("tmp").exists());
    }
}
