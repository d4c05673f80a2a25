//! Server-side evaluation of the global model.

use std::collections::BTreeMap;

use crate::error::BoxError;
use crate::tensors::NamedTensors;

/// Named metrics, e.g. `{"heldout_loss": 0.41, "success_rate": 0.7}`.
pub type EvalMetrics = BTreeMap<String, f64>;

/// Evaluates global trainable tensors on held-out data (the SmolVLA held-out evaluation implements this).
pub trait Evaluator {
    fn evaluate(&mut self, global: &NamedTensors) -> Result<EvalMetrics, BoxError>;
}
