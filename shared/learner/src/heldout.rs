//! Held-out evaluation of a policy on shard rows it never trained on: the flow-matching loss with
//! noise and times drawn from a fixed seed (so every round is measured the same way), and the
//! MSE/L1 of sampled action chunks against the recorded ones, in robot units; each row's share
//! of both, for figures per task; and for rows whose instruction decides the goal, the loss again
//! told another goal's instruction (the language check on held-out data).

use burn::tensor::Tensor;
use fedvla_policy::batch::{Prepared, prepare_actions};
use fedvla_policy::smolvla::{gaussian_noise, sample_times};
use fedvla_policy::weights::HostTensor;
use fedvla_policy::{PolicyError, SmolVla, SmolVlaConfig};
use rand::SeedableRng;
use rand::rngs::StdRng;

use crate::examples::ShardExamples;

/// At most this many held-out rows are evaluated (evenly spread), to keep evaluation cheap.
const MAX_ROWS: usize = 96;
const BATCH: usize = 16;
const SEED: u64 = 0xe7a1;

/// The fixed rows of a held-out evaluation.
#[derive(Debug, Clone)]
pub struct HeldOut {
    pub rows: Vec<usize>,
}

impl HeldOut {
    pub fn new(rows: &[usize]) -> Self {
        let step = rows.len().div_ceil(MAX_ROWS).max(1);
        Self { rows: rows.iter().step_by(step).copied().collect() }
    }
}

/// Held-out figures.
#[derive(Debug, Clone, PartialEq)]
pub struct HeldOutMetrics {
    pub loss: f64,
    pub action_mse: f64,
    pub action_l1: f64,
    /// Every evaluated row's own figures, in the order evaluated.
    pub rows: Vec<RowFigures>,
}

/// One held-out row's figures, from the same noise and samples as the totals.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RowFigures {
    pub row: usize,
    /// The flow-matching loss over the row's unpadded action steps.
    pub loss: f64,
    /// The same loss, from the same noise and times, told another goal's instruction in place of its own, for a
    /// row of a task whose instruction decides the goal ([`ShardExamples::another_goal_task`]).
    pub loss_told_another_goal: Option<f64>,
    /// Sum of the squared errors of its unpadded sampled action values, and their count.
    pub squared_error: f64,
    pub action_values: usize,
}

pub fn heldout_metrics(
    model: &SmolVla,
    examples: &ShardExamples,
    held_out: &HeldOut,
) -> Result<HeldOutMetrics, PolicyError> {
    if held_out.rows.is_empty() {
        return Err(PolicyError::Input("no held-out rows to evaluate on".into()));
    }
    let cfg = &model.cfg;
    let device = model.device();
    let mut rng = StdRng::seed_from_u64(SEED);
    let action_stats = examples.stats().get("action")?;
    let (mut loss_sum, mut se, mut ae, mut n_loss, mut n_act) = (0.0, 0.0, 0.0, 0usize, 0usize);
    let mut figures = Vec::with_capacity(held_out.rows.len());
    for rows in held_out.rows.chunks(BATCH) {
        let batch = examples.batch(rows, cfg.chunk_size)?;
        let obs = Prepared::new(cfg, &batch, &device)?;
        let b = rows.len();
        let noise = gaussian_noise(&mut rng, [b, cfg.chunk_size, cfg.max_action_dim], &device);
        let time = sample_times(&mut rng, b);
        let actions = batch.actions.as_ref().expect("shard batches carry actions");
        let pad = batch.action_is_pad.as_deref().expect("shard batches carry pad flags");
        let out =
            model.forward_loss(&obs, prepare_actions(cfg, actions, &device), noise.clone(), &time, Some(pad), None);
        loss_sum += out.loss.into_scalar::<f64>() * b as f64;
        n_loss += b;
        let a = cfg.action_dim();
        let losses = row_losses(cfg, out.losses, pad);
        // Rows whose instruction decides the goal again, told another goal's: the same frames, noise and times.
        let another: Vec<Option<usize>> = rows.iter().map(|&row| examples.another_goal_task(row)).collect();
        let mut told_another = vec![None; b];
        if another.iter().any(Option::is_some) {
            let tasks: Vec<usize> =
                another.iter().zip(rows).map(|(t, &row)| t.unwrap_or_else(|| examples.task_index(row))).collect();
            let told = examples.told(&batch, &tasks);
            let out = model.forward_loss(
                &Prepared::new(cfg, &told, &device)?,
                prepare_actions(cfg, actions, &device),
                noise,
                &time,
                Some(pad),
                None,
            );
            for ((slot, loss), t) in told_another.iter_mut().zip(row_losses(cfg, out.losses, pad)).zip(&another) {
                *slot = t.map(|_| loss);
            }
        }
        for ((&row, loss), loss_told_another_goal) in rows.iter().zip(losses).zip(told_another) {
            figures.push(RowFigures { row, loss, loss_told_another_goal, squared_error: 0.0, action_values: 0 });
        }

        let sample_noise = gaussian_noise(&mut rng, [b, cfg.chunk_size, cfg.max_action_dim], &device);
        let sampled = HostTensor::from_tensor(model.sample_actions(&obs, sample_noise, None).narrow(2, 0, a));
        let predicted = action_stats.unnormalize(&sampled.data);
        let target = action_stats.unnormalize(&actions.data);
        let batch_rows = figures.len() - b;
        for (step, p) in pad.iter().enumerate() {
            if *p {
                continue;
            }
            let row = &mut figures[batch_rows + step / cfg.chunk_size];
            for j in 0..a {
                let d = (predicted[step * a + j] - target[step * a + j]) as f64;
                se += d * d;
                ae += d.abs();
                row.squared_error += d * d;
            }
            n_act += a;
            row.action_values += a;
        }
    }
    Ok(HeldOutMetrics {
        loss: loss_sum / n_loss as f64,
        action_mse: se / n_act.max(1) as f64,
        action_l1: ae / n_act.max(1) as f64,
        rows: figures,
    })
}

/// Each row's loss as the batch's is taken: the squared errors of its unpadded steps' action values, averaged.
fn row_losses(cfg: &SmolVlaConfig, losses: Tensor<3>, pad: &[bool]) -> Vec<f64> {
    let a = cfg.action_dim();
    let losses = HostTensor::from_tensor(losses.narrow(2, 0, a));
    pad.chunks(cfg.chunk_size)
        .enumerate()
        .map(|(n, steps)| {
            let (mut sum, mut count) = (0.0, 0usize);
            for (step, _) in steps.iter().enumerate().filter(|(_, is_pad)| !**is_pad) {
                let at = (n * cfg.chunk_size + step) * a;
                sum += losses.data[at..at + a].iter().map(|&v| f64::from(v)).sum::<f64>();
                count += a;
            }
            sum / count.max(1) as f64
        })
        .collect()
}
