//! SmolVLA as a federated client's `LocalTrainer`: the trainable tensors (expert + projections)
//! are the update; the frozen backbone stays on the client. The same code runs natively and in
//! the browser; only the burn device differs.

use burn::tensor::Device;
use fedvla_federation::{BoxError, Capabilities, EvalOutput, LocalTrainer, NamedTensors, RoundTask, TrainOutput};
use fedvla_policy::{SmolVlaConfig, Trainer, WeightMap};
use rand::rngs::StdRng;
use rand::seq::SliceRandom;
use rand::SeedableRng;

use crate::examples::ShardExamples;
use crate::heldout::{HeldOut, heldout_metrics};
use crate::tensors::{to_named, to_weights};

/// A client's trainer over its shard.
pub struct SmolVlaTrainer {
    trainer: Trainer,
    examples: ShardExamples,
    held_out: HeldOut,
    backend: String,
}

impl SmolVlaTrainer {
    /// `weights` is the full initial checkpoint (frozen + trainable); `seed` drives this client's
    /// flow-matching noise and times; `backend` names the device for the server's client table.
    pub fn new(cfg: &SmolVlaConfig, weights: &WeightMap, examples: ShardExamples, seed: u64, device: &Device, backend: &str) -> Result<Self, BoxError> {
        let trainer = Trainer::new(cfg, weights, device, seed)?;
        let held_out = HeldOut::new(&examples.held_out_rows);
        Ok(Self { trainer, examples, held_out, backend: backend.into() })
    }
}

impl LocalTrainer for SmolVlaTrainer {
    fn capabilities(&self) -> Capabilities {
        let params: usize = self.trainer.model.cfg.param_specs().iter().map(|s| s.numel()).sum();
        Capabilities { backend: self.backend.clone(), memory_bytes: (params * 4) as u64 }
    }

    fn set_global(&mut self, global: &NamedTensors) -> Result<(), BoxError> {
        self.trainer.set_trainable_weights(&to_weights(global))?;
        Ok(())
    }

    /// `local_steps` AdamW steps on batches drawn (seeded by the task) from the training rows,
    /// each row visited once per pass.
    async fn train(&mut self, task: &RoundTask) -> Result<TrainOutput, BoxError> {
        let rows = &self.examples.train_rows;
        if rows.is_empty() {
            return Err("this client's shard has no training episodes".into());
        }
        let chunk = self.trainer.model.cfg.chunk_size;
        let batch_size = (task.batch_size as usize).clamp(1, rows.len());
        let mut rng = StdRng::seed_from_u64(task.seed);
        let mut order = rows.clone();
        let mut cursor = order.len();
        let mut loss_sum = 0.0;
        for _ in 0..task.local_steps {
            let mut picked = Vec::with_capacity(batch_size);
            while picked.len() < batch_size {
                if cursor == order.len() {
                    order.shuffle(&mut rng);
                    cursor = 0;
                }
                picked.push(order[cursor]);
                cursor += 1;
            }
            let batch = self.examples.batch(&picked, chunk)?;
            loss_sum += self.trainer.train_step(&batch, task.lr)?.loss as f64;
        }
        Ok(TrainOutput {
            update: to_named(&self.trainer.trainable_weights())?,
            examples: rows.len() as u64,
            train_loss: loss_sum / task.local_steps.max(1) as f64,
        })
    }

    async fn evaluate(&mut self) -> Result<EvalOutput, BoxError> {
        let metrics = heldout_metrics(&self.trainer.model, &self.examples, &self.held_out)?;
        Ok(EvalOutput { examples: self.held_out.rows.len() as u64, loss: metrics.loss })
    }
}
