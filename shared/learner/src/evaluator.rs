//! The server's evaluation of each global model on the federation's own held-out episodes.

use burn::tensor::Device;
use fedvla_federation::{BoxError, EvalMetrics, Evaluator, NamedTensors, NormalizationStats};
use fedvla_policy::weights::ParamStore;
use fedvla_policy::{SmolVla, SmolVlaConfig, WeightMap};

use crate::examples::ShardExamples;
use crate::heldout::{HeldOut, heldout_metrics};
use crate::tensors::to_weights;

/// Held-out loss and action errors of a global model on the server's held-out shard.
pub struct HeldOutEvaluator {
    model: SmolVla,
    examples: ShardExamples,
    held_out: HeldOut,
    device: Device,
}

impl HeldOutEvaluator {
    /// `weights` is the full checkpoint the federation started from (its frozen part is reused).
    pub fn new(cfg: &SmolVlaConfig, weights: &WeightMap, examples: ShardExamples, device: &Device) -> Self {
        let store = ParamStore::upload(weights.iter(), device, false);
        let held_out = HeldOut::new(&examples.held_out_rows);
        Self { model: SmolVla::new(cfg, &store), examples, held_out, device: device.clone() }
    }
}

impl Evaluator for HeldOutEvaluator {
    fn evaluate(&mut self, global: &NamedTensors) -> Result<EvalMetrics, BoxError> {
        let weights = to_weights(global);
        fedvla_policy::weights::check_keys(
            &self.model.cfg.param_specs().into_iter().filter(|s| s.trainable).collect::<Vec<_>>(),
            &weights,
            "global model",
        )?;
        let model = self.model.with_trainable(&ParamStore::upload(weights.iter(), &self.device, false));
        let m = heldout_metrics(&model, &self.examples, &self.held_out)?;
        Ok(EvalMetrics {
            heldout_loss: m.loss,
            heldout_examples: self.held_out.rows.len() as u64,
            action_mse: Some(m.action_mse),
            action_l1: Some(m.action_l1),
        })
    }

    fn set_norm_stats(&mut self, stats: &NormalizationStats) -> Result<(), BoxError> {
        Ok(self.examples.set_norm_stats(stats)?)
    }
}
