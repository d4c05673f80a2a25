//! Server-side evaluation of the global model.

use serde::{Deserialize, Serialize};

use crate::data_report::NormalizationStats;
use crate::error::BoxError;
use crate::tensors::NamedTensors;

/// What an evaluator measures of a global model on held-out data: the loss, and for a policy its action errors
/// in robot units. The console (www/console.js) reads these names from each metrics line's `global`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct EvalMetrics {
    pub heldout_loss: f64,
    pub heldout_examples: u64,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub action_mse: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub action_l1: Option<f64>,
    /// Each task's share of the held-out rows, in the order the tasks first appear (data of more than one task).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub heldout_by_task: Vec<TaskHeldOut>,
    /// The language check on held-out rows, where a task's instruction decides the goal.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub heldout_language: Option<LanguageHeldOut>,
}

/// The held-out figures of one task's rows: their mean loss, and the MSE of their sampled action values.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TaskHeldOut {
    /// The task's name (`fedvla tasks`), or its instruction where it is no sim task.
    pub task: String,
    pub heldout_examples: u64,
    pub heldout_loss: f64,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub action_mse: Option<f64>,
}

/// The held-out rows of the task whose instruction decides the goal (pick-colour), their mean loss told their own
/// instruction and told another goal's, from the same frames, noise and times: a policy that ignores the
/// instruction has the same loss on both, one that reads it a higher loss told another goal. It shows whether
/// the instruction is read long before rollouts succeed often enough to tell (the sim's language check).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LanguageHeldOut {
    /// The task's name (`fedvla tasks`).
    pub task: String,
    pub heldout_examples: u64,
    pub loss_told_right: f64,
    pub loss_told_another: f64,
}

impl EvalMetrics {
    /// Whether every figure is a number: a model whose evaluation is not finite is not published.
    pub fn is_finite(&self) -> bool {
        self.heldout_loss.is_finite() && [self.action_mse, self.action_l1].iter().flatten().all(|v| v.is_finite())
    }
}

/// Evaluates global trainable tensors on held-out data (the SmolVLA held-out evaluation implements this).
pub trait Evaluator {
    fn evaluate(&mut self, global: &NamedTensors) -> Result<EvalMetrics, BoxError>;

    /// Normalises with `stats` from now on (the run's, once agreed by federated statistics). Evaluators of data
    /// that needs no normalisation ignore them.
    fn set_norm_stats(&mut self, stats: &NormalizationStats) -> Result<(), BoxError> {
        let _ = stats;
        Ok(())
    }
}
