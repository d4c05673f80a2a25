//! The records a run writes for others to read, each defined once: a line of `metrics.jsonl` ([`MetricsLine`],
//! with a record per sampled client) and a model's sim rollouts ([`RolloutResults`], every `results.json`). The
//! coordinator, `fedvla train`, `fedvla eval` and the server's rollouts write them; resume, the console
//! (www/console.js reads these field names: `round`, `attempt`, `seconds`, `clients[].accepted`,
//! `clients[].train_loss`, `global.heldout_loss`, `global.action_mse`, `global.heldout_by_task`,
//! `global.success_by_task`, `global.language_check`, `settings`; `results.json`'s `success_rate` and
//! `model_version`), `simulate`'s headline and the experiment reports read them.

use std::collections::BTreeMap;
use std::path::Path;

use fedvla_federation::{EvalMetrics, PrivacyReport, RolloutEpisode};
use serde::{Deserialize, Serialize};

use crate::control::Settings;
use crate::stats::Interval;

/// A run's metrics, one [`MetricsLine`] a line.
pub const METRICS_FILE: &str = "metrics.jsonl";
/// A model's sim rollouts ([`RolloutResults`]).
pub const RESULTS_FILE: &str = "results.json";

/// One round of a run: a federation's aggregated (or skipped) round, or the centralized baseline after the
/// samples of one federated round. Round 0 is the initial model's evaluation.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct MetricsLine {
    pub round: u64,
    /// The global model's version after the round (equal to the round).
    pub model_version: u64,
    /// CRC-32 of the global model's tensors.
    pub model_crc32: u32,
    /// Which attempt at the round closed it (attempts with too few updates are retried).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub attempt: Option<u64>,
    /// Wall-clock seconds of the round, training and evaluation included.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub seconds: Option<f64>,
    pub timestamp: String,
    /// The sampled clients (none for round 0 and for the centralized baseline).
    #[serde(default)]
    pub clients: Vec<ClientRecord>,
    /// The global model's figures, when the round evaluated or rolled it out.
    #[serde(default)]
    pub global: Option<GlobalMetrics>,
    /// Why the round was skipped (every aggregate it could form failed); the model stayed as it was.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub skipped: Option<String>,
    /// The operator's settings this round was the first to use.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub settings: Option<Settings>,
    /// Refused client inputs since the previous line, by error code.
    #[serde(default)]
    pub rejections: BTreeMap<String, u64>,
    /// Centralized baseline: mean training loss of the round's steps and the samples consumed so far.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub train_loss: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub samples: Option<u64>,
    /// DP-FedAvg: the privacy spent by the rounds so far, and the clipping norm the next round uses.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub privacy: Option<PrivacyReport>,
}

impl MetricsLine {
    /// The update norms of the clients whose updates went into the round's aggregate; `None` when the round was
    /// skipped (nothing went in).
    pub fn accepted_update_norms(&self) -> Option<Vec<f64>> {
        if self.skipped.is_some() {
            return None;
        }
        Some(self.clients.iter().filter(|c| c.accepted).filter_map(|c| c.update_norm).collect())
    }
}

/// A global model's figures: its held-out evaluation and its rollouts in the sim.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct GlobalMetrics {
    #[serde(flatten)]
    pub eval: Option<EvalMetrics>,
    #[serde(flatten)]
    pub sim: Option<SimFigures>,
}

/// A model's success in the sim on held-out layouts.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SimFigures {
    pub success_rate: f64,
    pub rollout_episodes: u64,
    pub rollout_mean_length: f64,
    /// Each task's share, in the order the rollouts cycle through them (rollouts of more than one task).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub success_by_task: Vec<TaskSuccess>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub language_check: Option<LanguageCheck>,
}

/// One task's episodes of a model's rollouts.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TaskSuccess {
    /// Its name (`fedvla tasks`).
    pub task: String,
    pub episodes: u64,
    pub successes: u64,
    pub success_rate: f64,
}

/// The language check of a model's rollouts: every episode of the task whose instruction decides the goal
/// (pick-colour) rolled out twice on the same layout with the same sampling noise, told its own instruction and
/// told another goal's ([`ToldWrong`]), success judged by the episode's own goal both times. A policy that ignores
/// the instruction scores the same on both; one that follows it fails when told wrong.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LanguageCheck {
    pub task: String,
    pub episodes: u64,
    pub right_successes: u64,
    pub wrong_successes: u64,
    /// Wilson 95% intervals of the two success rates.
    pub right: Interval,
    pub wrong: Interval,
}

impl std::fmt::Display for LanguageCheck {
    /// Both success rates with their intervals, in words.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "language check ({}): told the right goal {}/{} [{:.2}, {:.2}], told another goal {}/{} [{:.2}, {:.2}] \
             (Wilson 95%)",
            self.task,
            self.right_successes,
            self.episodes,
            self.right.ci95_low,
            self.right.ci95_high,
            self.wrong_successes,
            self.episodes,
            self.wrong.ci95_low,
            self.wrong.ci95_high
        )
    }
}

/// An episode of the language check rolled out again, told another goal's instruction.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ToldWrong {
    /// The episode it repeats (its index in the rollouts).
    pub episode: u32,
    pub seed: u64,
    pub instruction: String,
    /// Whether the episode's own goal was met all the same.
    pub success: bool,
    pub length: u32,
}

/// What a client trains on, as the server knows it: the example count of a shard it built is one it verified;
/// an own dataset's is the client's claim, weighed no more than `own-data-max-examples`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "kebab-case")]
pub enum DataSource {
    /// Shard `index` of the run's dataset, served by the server.
    Shard { index: usize, examples: u64 },
    /// The volunteer's own dataset, which never leaves its machine.
    Own { claimed_examples: u64, weight: u64 },
}

impl DataSource {
    /// What the client's updates weigh.
    pub fn weight(self) -> u64 {
        match self {
            Self::Shard { examples, .. } => examples,
            Self::Own { weight, .. } => weight,
        }
    }

    /// The example count its updates should claim.
    pub fn expected_claim(self) -> u64 {
        match self {
            Self::Shard { examples, .. } => examples,
            Self::Own { claimed_examples, .. } => claimed_examples,
        }
    }
}

/// One sampled client of a round.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct ClientRecord {
    pub client_id: u64,
    pub name: String,
    /// What it trains on (none for a workload without shards).
    #[serde(default)]
    pub data: Option<DataSource>,
    /// Whether its update went into the round's aggregate.
    pub accepted: bool,
    /// What its update weighed: its shard's training examples, or its own dataset's claim within the cap.
    pub examples: Option<u64>,
    /// What its update's header claimed.
    pub claimed_examples: Option<u64>,
    /// Why its update was left out of the aggregate after the aggregate or its evaluation failed.
    pub dropped: Option<String>,
    pub train_loss: Option<f64>,
    /// Bytes of its update's binary frames, headers included.
    pub update_bytes: Option<u64>,
    /// The L2 norm of its update's change from the round's global model, over every trained value (what
    /// clipping and the robust rules judge; the scale a clipping norm is chosen on).
    #[serde(default)]
    pub update_norm: Option<f64>,
    /// Seconds it spent on the round, as it reported.
    pub seconds: Option<f64>,
    pub bytes_up: Option<u64>,
    pub bytes_down: Option<u64>,
    /// Bytes of its download of the round's global model, as it reported: the whole model, the deltas since the
    /// version it held, or 0 when it held this one.
    #[serde(default)]
    pub download_bytes: Option<u64>,
    /// Its held-out evaluation of the model the round started from.
    pub eval_examples: Option<u64>,
    pub eval_loss: Option<f64>,
    /// Its sim rollouts of the model the round started from.
    pub rollout: Option<RolloutResults>,
    /// Error codes of its inputs the server refused this round.
    #[serde(default)]
    pub refused: Vec<String>,
}

/// A model's rollouts in the sim: `results.json` of `fedvla eval`, of each round's global model, and of each
/// client's rollouts (`evaluate/round_N/client_K/`).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct RolloutResults {
    /// Who acted: a policy directory, "expert", the round's global model, or a client.
    pub policy: String,
    /// The global model version a client rolled out (the one its round started from).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub model_version: Option<u64>,
    pub episodes: Vec<RolloutEpisode>,
    /// Successful episodes over all (none without episodes).
    pub success_rate: Option<f64>,
    pub mean_length: Option<f64>,
    /// Episodes whose video could not be written; their results still count.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub video_errors: Vec<VideoError>,
    /// The language check's second rollouts, told the wrong instruction, and what they add up to.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub told_wrong: Vec<ToldWrong>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub language_check: Option<LanguageCheck>,
}

impl RolloutResults {
    /// The results of `episodes`, with their success rate and mean length.
    pub fn of(policy: String, model_version: Option<u64>, episodes: Vec<RolloutEpisode>) -> Self {
        let n = episodes.len() as f64;
        let (success_rate, mean_length) = match episodes.is_empty() {
            true => (None, None),
            false => (
                Some(episodes.iter().filter(|e| e.success).count() as f64 / n),
                Some(episodes.iter().map(|e| f64::from(e.length)).sum::<f64>() / n),
            ),
        };
        Self {
            policy,
            model_version,
            episodes,
            success_rate,
            mean_length,
            video_errors: Vec::new(),
            told_wrong: Vec::new(),
            language_check: None,
        }
    }

    /// With the language check of `told_wrong` (none without them): each compared with the episode it repeats.
    pub fn with_language_check(mut self, told_wrong: Vec<ToldWrong>) -> Self {
        let repeated: Vec<&RolloutEpisode> =
            told_wrong.iter().filter_map(|w| self.episodes.iter().find(|e| e.episode == w.episode)).collect();
        let task = repeated.first().and_then(|e| e.task.clone());
        let episodes = told_wrong.len() as u64;
        let right_successes = repeated.iter().filter(|e| e.success).count() as u64;
        let wrong_successes = told_wrong.iter().filter(|w| w.success).count() as u64;
        let intervals = (Interval::wilson(right_successes, episodes), Interval::wilson(wrong_successes, episodes));
        self.language_check = match (task, intervals) {
            (Some(task), (Some(right), Some(wrong))) => {
                Some(LanguageCheck { task, episodes, right_successes, wrong_successes, right, wrong })
            }
            _ => None,
        };
        self.told_wrong = told_wrong;
        self
    }

    /// Each task's episodes, in the order the tasks first appear (episodes that name no task are left out).
    pub fn by_task(&self) -> Vec<TaskSuccess> {
        let mut out: Vec<TaskSuccess> = Vec::new();
        for episode in &self.episodes {
            let Some(task) = &episode.task else { continue };
            let index = match out.iter().position(|t| &t.task == task) {
                Some(index) => index,
                None => {
                    out.push(TaskSuccess { task: task.clone(), episodes: 0, successes: 0, success_rate: 0.0 });
                    out.len() - 1
                }
            };
            out[index].episodes += 1;
            out[index].successes += u64::from(episode.success);
        }
        for task in &mut out {
            task.success_rate = task.successes as f64 / task.episodes as f64;
        }
        out
    }

    /// The figures a metrics line carries: per task only where the rollouts set more than one.
    pub fn figures(&self) -> Option<SimFigures> {
        let by_task = self.by_task();
        Some(SimFigures {
            success_rate: self.success_rate?,
            rollout_episodes: self.episodes.len() as u64,
            rollout_mean_length: self.mean_length?,
            success_by_task: if by_task.len() > 1 { by_task } else { Vec::new() },
            language_check: self.language_check.clone(),
        })
    }
}

/// An episode whose video could not be written.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct VideoError {
    pub episode: u32,
    pub message: String,
}

/// The time as metrics lines record it (RFC 3339, local time).
pub fn timestamp() -> String {
    chrono::Local::now().to_rfc3339()
}

/// Every complete line of a run's `metrics.jsonl` (a line being appended right now is left for the next read).
pub fn read_metrics(run_dir: &Path) -> std::io::Result<Vec<MetricsLine>> {
    let text = match std::fs::read_to_string(run_dir.join(METRICS_FILE)) {
        Ok(text) => text,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
        Err(e) => return Err(e),
    };
    let complete = &text[..text.rfind('\n').map_or(0, |i| i + 1)];
    complete
        .lines()
        .enumerate()
        .map(|(i, line)| {
            serde_json::from_str(line).map_err(|e| {
                std::io::Error::new(std::io::ErrorKind::InvalidData, format!("{METRICS_FILE} line {}: {e}", i + 1))
            })
        })
        .collect()
}
