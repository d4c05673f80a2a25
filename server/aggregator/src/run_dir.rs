//! `outputs/<date_time>/`: resolved config, per-round metrics, global models, clients' rollouts. Crash-safe:
//! every file is written atomically ([`fedvla_fs::write_atomic`]: whole, synced, its directory synced), a round's
//! model directory is written under a temporary name, synced as a tree and renamed, and the metrics file is
//! replaced whole with each round's line added; a round is complete once its metrics line is. On resume
//! ([`RunDir::resume_point`]) whatever a crash left of later rounds, and every temporary, is swept.

use std::fs::{self, File, OpenOptions};
use std::path::{Path, PathBuf};

use fedvla_federation::{BoxError, NamedTensors, NormalizationStats, TensorError};

use crate::config::{ConfigError, KeepModels, RunConfig};
pub use crate::records::{METRICS_FILE, RESULTS_FILE};
use crate::records::{MetricsLine, RolloutResults, SimFigures, read_metrics};

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
        fedvla_fs::create_dir_all(base).map_err(io(base))?;
        let stamp = chrono::Local::now().format("%Y-%m-%d_%H-%M-%S").to_string();
        let mut path = base.join(&stamp);
        let mut n = 1;
        while path.exists() {
            path = base.join(format!("{stamp}_{n}"));
            n += 1;
        }
        fs::create_dir(&path).map_err(io(&path))?;
        fedvla_fs::sync_dir(base).map_err(io(base))?;
        let dir = Self { path };
        dir.write_config(config)?;
        Ok(dir)
    }

    /// Creates the run directory `path` itself (an experiment names its runs' folders) and writes the resolved
    /// config; `path` must not exist yet.
    pub fn create_at(path: &Path, config: &RunConfig) -> Result<Self, RunDirError> {
        let parent = path.parent().unwrap_or(Path::new("."));
        fedvla_fs::create_dir_all(parent).map_err(io(parent))?;
        fs::create_dir(path).map_err(io(path))?;
        fedvla_fs::sync_dir(parent).map_err(io(parent))?;
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

    /// Where a (re)started server takes the run up: the last completed round, after sweeping what a crash left
    /// beyond it (a model directory saved before its metrics line, clients' evaluations of a round that did not
    /// complete, temporary directories and files), so that every file in the run directory belongs to a completed
    /// round or to the run, and the rounds redone are written afresh.
    pub fn resume_point(&self) -> Result<Option<u64>, RunDirError> {
        let last = self.last_completed_round()?;
        let removed = fedvla_fs::remove_temporaries(&self.path).map_err(io(&self.path))?;
        if removed > 0 {
            tracing::warn!(removed, "removed temporary files a crash left");
        }
        let beyond = |round: u64| last.is_none_or(|l| round > l);
        // `round_N.tmp` is a model directory being written; `round_N` beyond the last metrics line was saved but its
        // round never completed.
        remove_dirs(&self.path.join(MODELS_DIR), |name| match name.strip_suffix(".tmp") {
            Some(stem) => round_number(stem).is_some(),
            None => round_number(name).is_some_and(beyond),
        })?;
        remove_dirs(&self.path.join(EVALUATE_DIR), |name| round_number(name).is_some_and(beyond))?;
        Ok(last)
    }

    /// The last round with a metrics line, dropping a torn last line left by a crash mid-write (metrics files are
    /// no longer appended to, but a run written before may end in one).
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

    /// Adds one round's metrics line: the file is written again whole and renamed over the old one (it is small),
    /// so a crash or a full disk leaves the lines before it or all of them, never a torn one.
    pub fn append_metrics(&self, line: &MetricsLine) -> Result<(), RunDirError> {
        let path = self.path.join(METRICS_FILE);
        let mut text = match fs::read_to_string(&path) {
            Ok(text) => text,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => String::new(),
            Err(e) => return Err(io(&path)(e)),
        };
        text.push_str(&serde_json::to_string(line).expect("metrics serialize"));
        text.push('\n');
        write_atomic(&path, text.as_bytes())
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
        fedvla_fs::create_dir_all(&dir).map_err(io(&dir))?;
        write_atomic(&dir.join(RESULTS_FILE), &serde_json::to_vec_pretty(results).expect("results serialize"))
    }

    pub fn model_dir(&self, round: u64) -> PathBuf {
        self.path.join(MODELS_DIR).join(format!("round_{round}"))
    }

    /// Writes `global_model/round_N/` through every exporter into a temporary directory, syncs it, then renames it.
    /// Returns what the exporters measured in the sim. On failure (a full disk) the temporary directory is removed:
    /// the rounds before stay as they were.
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
        let written = Self::write_model(round, global, strategy_state, exporters, config, &tmp);
        if written.is_err() {
            let _ = fs::remove_dir_all(&tmp);
        }
        let measured = written?;
        if dir.exists() {
            // Left by a run that crashed after saving but before its metrics line: this round is being redone.
            fs::remove_dir_all(&dir).map_err(io(&dir))?;
        }
        fs::rename(&tmp, &dir).map_err(io(&dir))?;
        fedvla_fs::sync_dir(self.path.join(MODELS_DIR).as_path()).map_err(io(&dir))?;
        Ok(measured)
    }

    /// [`save_model`](Self::save_model)'s writing into `tmp`, every file and directory synced before it returns.
    fn write_model(
        round: u64,
        global: &NamedTensors,
        strategy_state: &NamedTensors,
        exporters: &[Box<dyn ModelExporter>],
        config: &RunConfig,
        tmp: &Path,
    ) -> Result<Option<SimFigures>, RunDirError> {
        fedvla_fs::create_dir_all(tmp).map_err(io(tmp))?;
        if !strategy_state.is_empty() {
            let bytes = strategy_state.to_safetensors().map_err(|source| RunDirError::Model { round, source })?;
            write_atomic(&tmp.join(STRATEGY_FILE), &bytes)?;
        }
        let mut measured = None;
        for exporter in exporters {
            let figures =
                exporter.export(round, global, config, tmp).map_err(|source| RunDirError::Export { round, source })?;
            measured = measured.or(figures);
        }
        // The exporters' videos are written in place, not through write_atomic: synced here, before the rename.
        fedvla_fs::sync_tree(tmp).map_err(io(tmp))?;
        Ok(measured)
    }

    /// Removes the global models `keep` lets go, once a round's metrics line is written: under
    /// [`KeepModels::Evaluated`], that of every completed round before the last but round 0 and the rounds whose
    /// metrics line carries the global model's figures. The last completed round's stays: a resumed run starts
    /// from it. Decided from `metrics.jsonl`, so what a crash between a line and this left goes the next time.
    /// Returns how many were removed.
    pub fn remove_superseded_models(&self, keep: KeepModels) -> Result<usize, RunDirError> {
        if keep == KeepModels::All {
            return Ok(0);
        }
        let lines = read_metrics(&self.path).map_err(io(&self.path.join(METRICS_FILE)))?;
        let Some(last) = lines.last().map(|l| l.round) else { return Ok(0) };
        let superseded =
            |round: u64| round < last && round > 0 && lines.iter().any(|l| l.round == round && l.global.is_none());
        let models = self.path.join(MODELS_DIR);
        let removable: Vec<PathBuf> = numbered_dirs(&models, "round_")
            .map_err(io(&models))?
            .into_iter()
            .filter_map(|(round, path)| superseded(round).then_some(path))
            .collect();
        for path in &removable {
            fs::remove_dir_all(path).map_err(io(path))?;
        }
        if !removable.is_empty() {
            fedvla_fs::sync_dir(&models).map_err(io(&models))?;
        }
        Ok(removable.len())
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

/// Removes the entries of `parent` (if it exists) whose names `unfinished` picks, and syncs it.
fn remove_dirs(parent: &Path, unfinished: impl Fn(&str) -> bool) -> Result<(), RunDirError> {
    let entries = match fs::read_dir(parent) {
        Ok(entries) => entries,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(()),
        Err(e) => return Err(io(parent)(e)),
    };
    for entry in entries {
        let path = entry.map_err(io(parent))?.path();
        if path.file_name().is_some_and(|name| unfinished(&name.to_string_lossy())) {
            tracing::warn!(path = %path.display(), "removing what an unfinished round left");
            fs::remove_dir_all(&path).map_err(io(&path))?;
        }
    }
    fedvla_fs::sync_dir(parent).map_err(io(parent))
}

/// Subdirectories of `dir` named `<prefix><number>`, by number (none when `dir` does not exist; `round_3.tmp`, a
/// round being written, is not one): `global_model/round_N/`, `evaluate/round_N/client_K/`.
pub fn numbered_dirs(dir: &Path, prefix: &str) -> std::io::Result<Vec<(u64, PathBuf)>> {
    let entries = match fs::read_dir(dir) {
        Ok(entries) => entries,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
        Err(e) => return Err(e),
    };
    let mut out = Vec::new();
    for entry in entries {
        let entry = entry?;
        let number = entry.file_name().to_str().and_then(|n| n.strip_prefix(prefix)?.parse::<u64>().ok());
        if let Some(number) = number.filter(|_| entry.path().is_dir()) {
            out.push((number, entry.path()));
        }
    }
    out.sort();
    Ok(out)
}

/// `N` of a `round_N` directory.
fn round_number(name: &str) -> Option<u64> {
    name.strip_prefix("round_")?.parse().ok()
}

/// Writes `bytes` to `path` atomically.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), RunDirError> {
    fedvla_fs::write_atomic(path, bytes).map_err(io(path))
}

#[cfg(test)]
mod tests {
    use std::io::Write;

    use super::*;
    use crate::records::GlobalMetrics;

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
    fn resuming_sweeps_what_a_crash_left_beyond_the_last_completed_round() {
        let base = tempfile::tempdir().unwrap();
        let dir = RunDir::create(base.path(), &RunConfig::default()).unwrap();
        let mut t = NamedTensors::new();
        t.insert("w", vec![1], vec![1.0]).unwrap();
        let exporters: Vec<Box<dyn ModelExporter>> = vec![Box::new(TrainableSafetensors)];
        for round in 0..=2 {
            dir.save_model(round, &t, &NamedTensors::new(), &exporters, &RunConfig::default()).unwrap();
            dir.write_client_results(round, 7, &RolloutResults::default()).unwrap();
        }
        // Round 2 was saved, but the crash came before its metrics line; round 3 was being written.
        for round in 0..=1 {
            dir.append_metrics(&MetricsLine { round, ..MetricsLine::default() }).unwrap();
        }
        fs::create_dir_all(dir.model_dir(3).with_extension("tmp")).unwrap();
        fs::write(dir.path().join(".metrics.jsonl.partial"), b"{").unwrap();
        fs::write(dir.model_dir(1).join(".x.partial"), b"").unwrap();

        assert_eq!(dir.resume_point().unwrap(), Some(1));
        let names = |d: PathBuf| {
            let mut names: Vec<_> = fs::read_dir(d).unwrap().map(|e| e.unwrap().file_name()).collect();
            names.sort();
            names
        };
        assert_eq!(names(dir.path().join(MODELS_DIR)), ["round_0", "round_1"]);
        assert_eq!(names(dir.path().join(EVALUATE_DIR)), ["round_0", "round_1"]);
        assert_eq!(names(dir.model_dir(1)), [TRAINABLE_FILE]);
        assert_eq!(names(dir.path().to_owned()), [CONFIG_FILE, EVALUATE_DIR, MODELS_DIR, METRICS_FILE]);
        assert_eq!(dir.load_model(1).unwrap(), t);
    }

    #[test]
    fn keeping_evaluated_models_removes_the_others_once_superseded() {
        let base = tempfile::tempdir().unwrap();
        let dir = RunDir::create(base.path(), &RunConfig::default()).unwrap();
        let mut t = NamedTensors::new();
        t.insert("w", vec![1], vec![1.0]).unwrap();
        let exporters: Vec<Box<dyn ModelExporter>> = vec![Box::new(TrainableSafetensors)];
        let rounds = |dir: &RunDir| -> Vec<u64> {
            numbered_dirs(&dir.path().join(MODELS_DIR), "round_").unwrap().into_iter().map(|(round, _)| round).collect()
        };
        // Rounds 0 and 3 evaluated; round 1 and 2 did not.
        let complete = |round: u64, evaluated: bool, keep: KeepModels| {
            dir.save_model(round, &t, &NamedTensors::new(), &exporters, &RunConfig::default()).unwrap();
            let global = evaluated.then(GlobalMetrics::default);
            dir.append_metrics(&MetricsLine { round, global, ..MetricsLine::default() }).unwrap();
            dir.remove_superseded_models(keep).unwrap()
        };
        assert_eq!(complete(0, true, KeepModels::Evaluated), 0);
        assert_eq!(complete(1, false, KeepModels::All), 0);
        assert_eq!(complete(2, false, KeepModels::All), 0);
        assert_eq!(rounds(&dir), [0, 1, 2]);
        // Switched to keeping the evaluated ones: round 1 goes, round 2 is the last completed and stays.
        assert_eq!(complete(3, true, KeepModels::Evaluated), 2);
        assert_eq!(rounds(&dir), [0, 3]);
        assert_eq!(complete(4, false, KeepModels::Evaluated), 0);
        assert_eq!(complete(5, false, KeepModels::Evaluated), 1);
        assert_eq!(rounds(&dir), [0, 3, 5]);
        assert_eq!(dir.load_model(5).unwrap(), t);
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
