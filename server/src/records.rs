//! The records a run writes for others to read, defined once: a line of `metrics.jsonl` ([`MetricsLine`]). The
//! coordinator and `fedvla train` write it; resume, the console (www/console.js reads the same field names),
//! `simulate`'s summary and the experiment reports read it.

use std::collections::BTreeMap;
use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::run_dir::METRICS_FILE;

/// One round of a run: a federation's aggregated (or skipped) round, or the centralized baseline after the
/// samples of one federated round. Round 0 is the initial model's evaluation.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct MetricsLine {
    pub round: u64,
    /// The global model's version after the round (equal to the round).
    #[serde(default)]
    pub model_version: u64,
    /// CRC-32 of the global model's tensors.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub model_crc32: Option<u32>,
    /// Which attempt at the round closed it (attempts with too few updates are retried).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub attempt: Option<u64>,
    /// Wall-clock seconds of the round, training and evaluation included.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub seconds: Option<f64>,
    #[serde(default)]
    pub timestamp: String,
    /// The sampled clients (empty for round 0 and for the centralized baseline).
    #[serde(default)]
    pub clients: Vec<serde_json::Value>,
    /// The global model's evaluation, when the round evaluated it.
    #[serde(default)]
    pub global: Option<GlobalMetrics>,
    /// Why the round was skipped (every aggregate it could form failed); the model stayed as it was.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub skipped: Option<String>,
    /// Refused client inputs since the previous line, by error code.
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub rejections: BTreeMap<String, u64>,
    /// Centralized baseline: mean training loss of the round's steps and samples consumed so far.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub train_loss: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub samples: Option<u64>,
}

/// A global model's figures: held-out loss and action errors (robot units) on the server's held-out episodes,
/// and its success in the sim on held-out layouts.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct GlobalMetrics {
    pub heldout_loss: f64,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub heldout_examples: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub action_mse: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub action_l1: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub success_rate: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rollout_episodes: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rollout_mean_length: Option<f64>,
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
