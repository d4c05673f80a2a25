//! The server's evaluation of each global model on the federation's own held-out episodes, in total and, for data
//! of several tasks, per task.

use burn::tensor::Device;
use fedvla_federation::{
    BoxError, EvalMetrics, Evaluator, LanguageHeldOut, NamedTensors, NormalizationStats, TaskHeldOut,
};
use fedvla_policy::weights::ParamStore;
use fedvla_policy::{SmolVla, SmolVlaConfig};

use fedvla_sim::TaskKind;

use crate::examples::ShardExamples;
use crate::heldout::{HeldOut, RowFigures, heldout_metrics};
use crate::tensors::to_weights;

/// Held-out loss and action errors of a global model on the server's held-out shard.
pub struct HeldOutEvaluator {
    model: SmolVla,
    examples: ShardExamples,
    held_out: HeldOut,
    device: Device,
}

impl HeldOutEvaluator {
    /// `store` holds the full checkpoint the federation started from, on `device` (its frozen part is reused).
    pub fn new(cfg: &SmolVlaConfig, store: &ParamStore, examples: ShardExamples, device: &Device) -> Self {
        let held_out = HeldOut::new(&examples.held_out_rows);
        Self { model: SmolVla::new(cfg, store), examples, held_out, device: device.clone() }
    }
}

/// The rows' figures grouped by their task (a sim task by its name, any other by its instruction), in the order the
/// tasks first appear; none for rows of one task, whose figures are the totals.
fn by_task(examples: &ShardExamples, rows: &[RowFigures]) -> Vec<TaskHeldOut> {
    let mut groups: Vec<(String, Vec<&RowFigures>)> = Vec::new();
    for figures in rows {
        let instruction = examples.task_of(figures.row);
        let task =
            TaskKind::of_instruction(instruction).map_or_else(|| instruction.to_owned(), |t| t.name().to_owned());
        match groups.iter_mut().find(|(name, _)| *name == task) {
            Some((_, members)) => members.push(figures),
            None => groups.push((task, vec![figures])),
        }
    }
    if groups.len() < 2 {
        return Vec::new();
    }
    groups
        .into_iter()
        .map(|(task, members)| {
            let values: usize = members.iter().map(|r| r.action_values).sum();
            TaskHeldOut {
                task,
                heldout_examples: members.len() as u64,
                heldout_loss: members.iter().map(|r| r.loss).sum::<f64>() / members.len() as f64,
                action_mse: (values > 0).then(|| members.iter().map(|r| r.squared_error).sum::<f64>() / values as f64),
            }
        })
        .collect()
}

/// The language check of the rows told another goal: their mean loss told their own instruction and told the other.
fn language(examples: &ShardExamples, rows: &[RowFigures]) -> Option<LanguageHeldOut> {
    let told: Vec<(f64, f64)> = rows.iter().filter_map(|r| Some((r.loss, r.loss_told_another_goal?))).collect();
    let first = rows.iter().find(|r| r.loss_told_another_goal.is_some())?;
    let task = TaskKind::of_instruction(examples.task_of(first.row))?;
    let n = told.len() as f64;
    Some(LanguageHeldOut {
        task: task.name().to_owned(),
        heldout_examples: told.len() as u64,
        loss_told_right: told.iter().map(|(right, _)| right).sum::<f64>() / n,
        loss_told_another: told.iter().map(|(_, another)| another).sum::<f64>() / n,
    })
}

impl Evaluator for HeldOutEvaluator {
    fn evaluate(&mut self, global: &NamedTensors) -> Result<EvalMetrics, BoxError> {
        let weights = to_weights(global);
        fedvla_policy::weights::check_keys(
            &self.model.cfg.param_specs().into_iter().filter(|s| s.trainable).collect::<Vec<_>>(),
            &weights,
            "global model",
        )?;
        let model = self.model.with_trainable(&ParamStore::upload_owned(weights, &self.device, false));
        let m = heldout_metrics(&model, &self.examples, &self.held_out)?;
        Ok(EvalMetrics {
            heldout_loss: m.loss,
            heldout_examples: self.held_out.rows.len() as u64,
            action_mse: Some(m.action_mse),
            action_l1: Some(m.action_l1),
            heldout_by_task: by_task(&self.examples, &m.rows),
            heldout_language: language(&self.examples, &m.rows),
        })
    }

    fn set_norm_stats(&mut self, stats: &NormalizationStats) -> Result<(), BoxError> {
        Ok(self.examples.set_norm_stats(stats)?)
    }
}
