//! Held-out evaluation of a policy on shard rows it never trained on: the flow-matching loss with
//! noise and times drawn from a fixed seed (so every round is measured the same way), and the
//! MSE/L1 of sampled action chunks against the recorded ones, in robot units.

use fedvla_policy::batch::{Prepared, prepare_actions};
use fedvla_policy::smolvla::{gaussian_noise, sample_times};
use fedvla_policy::weights::HostTensor;
use fedvla_policy::{PolicyError, SmolVla};
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
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HeldOutMetrics {
    pub loss: f64,
    pub action_mse: f64,
    pub action_l1: f64,
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
    for rows in held_out.rows.chunks(BATCH) {
        let batch = examples.batch(rows, cfg.chunk_size)?;
        let obs = Prepared::new(cfg, &batch, &device)?;
        let b = rows.len();
        let noise = gaussian_noise(&mut rng, [b, cfg.chunk_size, cfg.max_action_dim], &device);
        let time = sample_times(&mut rng, b);
        let actions = batch.actions.as_ref().expect("shard batches carry actions");
        let out = model.forward_loss(
            &obs,
            prepare_actions(cfg, actions, &device),
            noise,
            &time,
            batch.action_is_pad.as_deref(),
            None,
        );
        loss_sum += out.loss.into_scalar::<f64>() * b as f64;
        n_loss += b;

        let sample_noise = gaussian_noise(&mut rng, [b, cfg.chunk_size, cfg.max_action_dim], &device);
        let a = cfg.action_dim();
        let sampled = HostTensor::from_tensor(model.sample_actions(&obs, sample_noise, None).narrow(2, 0, a));
        let predicted = action_stats.unnormalize(&sampled.data);
        let target = action_stats.unnormalize(&actions.data);
        let pad = batch.action_is_pad.as_deref().expect("shard batches carry pad flags");
        for (step, p) in pad.iter().enumerate() {
            if *p {
                continue;
            }
            for j in 0..a {
                let d = (predicted[step * a + j] - target[step * a + j]) as f64;
                se += d * d;
                ae += d.abs();
            }
            n_act += a;
        }
    }
    Ok(HeldOutMetrics {
        loss: loss_sum / n_loss as f64,
        action_mse: se / n_act.max(1) as f64,
        action_l1: ae / n_act.max(1) as f64,
    })
}
