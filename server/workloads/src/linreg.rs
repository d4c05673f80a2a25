//! A real but tiny workload that exercises the federation machinery in milliseconds: least-squares linear
//! regression on synthetic data, trained by minibatch SGD. A frozen random feature projection stands in for SmolVLA's frozen backbone: it
//! never crosses the wire, only the head (`head.weight`, `head.bias`) is trainable and exchanged.

use fedvla_federation::{
    BoxError, Capabilities, EvalMetrics, EvalOutput, Evaluator, LocalTrainer, NamedTensors, RoundTask, TrainOutput,
};
use rand::rngs::StdRng;
use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};

use fedvla_aggregator::config::{Partitioning, RunConfig, WorkloadKind};
use fedvla_aggregator::registry::{ShardOffer, VolunteerOffer};
use fedvla_aggregator::run_dir::ModelExporter;

use crate::workload::Workload;

/// Raw input size.
pub const INPUTS: usize = 8;
/// Feature size after the frozen projection.
pub const FEATURES: usize = 16;
pub const WEIGHT: &str = "head.weight";
pub const BIAS: &str = "head.bias";
/// Seed of the frozen projection and the true regression: the "dataset", shared by every party.
const WORLD_SEED: u64 = 0x5eed_da7a;
const NOISE: f32 = 0.05;

/// The frozen projection and the true head that generates targets.
#[derive(Debug, Clone)]
struct World {
    projection: Vec<f32>,
    true_weight: Vec<f32>,
    true_bias: f32,
}

impl World {
    fn new() -> Self {
        let mut rng = StdRng::seed_from_u64(WORLD_SEED);
        let scale = 1.0 / (INPUTS as f32).sqrt();
        Self {
            projection: (0..FEATURES * INPUTS).map(|_| rng.random_range(-scale..scale) * 2.0).collect(),
            true_weight: (0..FEATURES).map(|_| rng.random_range(-1.0..1.0)).collect(),
            true_bias: rng.random_range(-0.5..0.5),
        }
    }

    /// Frozen features: tanh(P x).
    fn features(&self, x: &[f32]) -> [f32; FEATURES] {
        std::array::from_fn(|i| {
            let row = &self.projection[i * INPUTS..(i + 1) * INPUTS];
            row.iter().zip(x).map(|(p, v)| p * v).sum::<f32>().tanh()
        })
    }

    /// `n` examples; `shift` moves the input distribution (a client's own part of the state space).
    fn examples(&self, seed: u64, n: usize, shift: f32) -> Examples {
        let mut rng = StdRng::seed_from_u64(seed);
        let mut out = Examples::default();
        for _ in 0..n {
            let x: Vec<f32> = (0..INPUTS).map(|_| rng.random_range(-1.0..1.0) + shift).collect();
            let phi = self.features(&x);
            let y = dot(&self.true_weight, &phi) + self.true_bias + rng.random_range(-NOISE..NOISE);
            out.features.push(phi);
            out.targets.push(y);
        }
        out
    }
}

#[derive(Debug, Clone, Default)]
struct Examples {
    features: Vec<[f32; FEATURES]>,
    targets: Vec<f32>,
}

impl Examples {
    fn len(&self) -> usize {
        self.targets.len()
    }

    fn mse(&self, weight: &[f32], bias: f32) -> f64 {
        let sum: f64 = self
            .features
            .iter()
            .zip(&self.targets)
            .map(|(phi, y)| f64::from(dot(weight, phi) + bias - y).powi(2))
            .sum();
        sum / self.len().max(1) as f64
    }
}

fn dot(a: &[f32], b: &[f32]) -> f32 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

/// The initial global head, drawn from `seed`.
pub fn initial_model(seed: u64) -> NamedTensors {
    let mut rng = StdRng::seed_from_u64(seed);
    let mut t = NamedTensors::new();
    let weight = (0..FEATURES).map(|_| rng.random_range(-0.1..0.1)).collect();
    t.insert(WEIGHT, vec![1, FEATURES], weight).expect("shape matches");
    t.insert(BIAS, vec![1], vec![0.0]).expect("shape matches");
    t
}

fn head(tensors: &NamedTensors) -> Result<(Vec<f32>, f32), BoxError> {
    tensors.validate(&initial_model(0).spec())?;
    let weight = tensors.get(WEIGHT).expect("validated").values.clone();
    Ok((weight, tensors.get(BIAS).expect("validated").values[0]))
}

/// Training examples of shard `shard`: clients weigh differently.
pub fn train_examples(shard: usize) -> usize {
    48 + 16 * shard
}

/// Client `shard`'s trainer: its [`train_examples`] and a held-out split of 32.
#[derive(Debug, Clone)]
pub struct LinRegTrainer {
    train: Examples,
    heldout: Examples,
    global: (Vec<f32>, f32),
    weight: Vec<f32>,
    bias: f32,
    /// SCAFFOLD's `c - c_i`, added to every step's gradient (zeros: none).
    correction: (Vec<f32>, f32),
}

impl LinRegTrainer {
    pub fn new(shard: usize, partitioning: Partitioning) -> Self {
        let world = World::new();
        let shift = match partitioning {
            Partitioning::Iid => 0.0,
            Partitioning::ByEpisode | Partitioning::ByLayout | Partitioning::ByTask | Partitioning::Dirichlet => {
                0.5 * (shard as f32 % 3.0 - 1.0)
            }
        };
        let seed = WORLD_SEED ^ (shard as u64 + 1).wrapping_mul(0x9e37_79b9_7f4a_7c15);
        let (weight, bias) = head(&initial_model(0)).expect("initial model is valid");
        Self {
            train: world.examples(seed, train_examples(shard), shift),
            heldout: world.examples(seed ^ 1, 32, shift),
            global: (weight.clone(), bias),
            correction: (vec![0.0; weight.len()], 0.0),
            weight,
            bias,
        }
    }

    /// Poisons the training targets for a simulated attacker: shuffled among the training examples by `seed`.
    pub fn shuffle_labels(&mut self, seed: u64) {
        self.train.targets.shuffle(&mut StdRng::seed_from_u64(seed));
    }
}

impl LocalTrainer for LinRegTrainer {
    fn capabilities(&self) -> Capabilities {
        Capabilities { backend: "cpu-f32".into(), memory_bytes: (self.train.len() * FEATURES * 4) as u64 }
    }

    fn set_global(&mut self, global: &NamedTensors) -> Result<(), BoxError> {
        let (weight, bias) = head(global)?;
        self.global = (weight.clone(), bias);
        self.weight = weight;
        self.bias = bias;
        Ok(())
    }

    fn set_correction(&mut self, correction: &NamedTensors) -> Result<(), BoxError> {
        self.correction = match correction.is_empty() {
            true => (vec![0.0; FEATURES], 0.0),
            false => head(correction)?,
        };
        Ok(())
    }

    /// Minibatch SGD on the squared error, plus FedProx's proximal term when `proximal_mu` > 0 and SCAFFOLD's
    /// correction when one is set.
    async fn train(&mut self, task: &RoundTask) -> Result<TrainOutput, BoxError> {
        let mut rng = StdRng::seed_from_u64(task.seed);
        let mut order: Vec<usize> = (0..self.train.len()).collect();
        let mut cursor = order.len();
        let (lr, mu) = (task.lr as f32, task.strategy.proximal_mu as f32);
        let batch = (task.batch_size as usize).min(order.len());
        let mut loss_sum = 0.0f64;
        for _ in 0..task.local_steps {
            let mut grad_w = [0f32; FEATURES];
            let mut grad_b = 0f32;
            let mut batch_loss = 0f64;
            for _ in 0..batch {
                if cursor == order.len() {
                    order.shuffle(&mut rng);
                    cursor = 0;
                }
                let i = order[cursor];
                cursor += 1;
                let phi = &self.train.features[i];
                let err = dot(&self.weight, phi) + self.bias - self.train.targets[i];
                batch_loss += f64::from(err * err);
                for (g, x) in grad_w.iter_mut().zip(phi) {
                    *g += 2.0 * err * x / batch as f32;
                }
                grad_b += 2.0 * err / batch as f32;
            }
            loss_sum += batch_loss / batch as f64;
            let (correction_w, correction_b) = &self.correction;
            for (((w, g), w0), c) in self.weight.iter_mut().zip(grad_w).zip(&self.global.0).zip(correction_w) {
                *w -= lr * (g + mu * (*w - w0) + c);
            }
            self.bias -= lr * (grad_b + mu * (self.bias - self.global.1) + correction_b);
        }
        let mut update = NamedTensors::new();
        update.insert(WEIGHT, vec![1, FEATURES], self.weight.clone())?;
        update.insert(BIAS, vec![1], vec![self.bias])?;
        Ok(TrainOutput {
            update,
            examples: self.train.len() as u64,
            train_loss: loss_sum / f64::from(task.local_steps.max(1)),
        })
    }

    async fn evaluate(&mut self) -> Result<EvalOutput, BoxError> {
        Ok(EvalOutput { examples: self.heldout.len() as u64, loss: self.heldout.mse(&self.weight, self.bias) })
    }
}

/// The server's held-out evaluation: mean squared error on 256 examples no client holds.
#[derive(Debug, Clone)]
pub struct LinRegEvaluator {
    heldout: Examples,
}

impl Default for LinRegEvaluator {
    fn default() -> Self {
        Self { heldout: World::new().examples(WORLD_SEED ^ 0xe7a1, 256, 0.0) }
    }
}

impl Evaluator for LinRegEvaluator {
    fn evaluate(&mut self, global: &NamedTensors) -> Result<EvalMetrics, BoxError> {
        let (weight, bias) = head(global)?;
        Ok(EvalMetrics {
            heldout_loss: self.heldout.mse(&weight, bias),
            heldout_examples: self.heldout.len() as u64,
            ..EvalMetrics::default()
        })
    }
}

/// The linreg workload: initial head from the run's seed, `num_clients` shards partitioned as configured.
#[derive(Debug, Clone, Copy)]
pub struct LinRegWorkload {
    pub seed: u64,
    pub partitioning: Partitioning,
    pub num_clients: usize,
}

impl LinRegWorkload {
    pub fn from_config(config: &RunConfig) -> Self {
        Self { seed: config.seed, partitioning: config.partitioning, num_clients: config.num_clients }
    }
}

impl Workload for LinRegWorkload {
    fn initial_model(&self) -> Result<NamedTensors, BoxError> {
        Ok(initial_model(self.seed))
    }

    fn evaluator(&self) -> Result<Box<dyn Evaluator + Send>, BoxError> {
        Ok(Box::new(LinRegEvaluator::default()))
    }

    fn exporters(&self) -> Vec<Box<dyn ModelExporter>> {
        Vec::new()
    }

    /// Shards without files (a linreg client generates its shard from its index, skewed as `partitioning` says)
    /// and no weights to download.
    fn volunteer_offer(&self) -> Result<VolunteerOffer, BoxError> {
        let shards = (0..self.num_clients)
            .map(|k| ShardOffer { file: None, train_examples: train_examples(k) as u64 })
            .collect();
        let mut offer = VolunteerOffer::shards_only(WorkloadKind::Linreg, shards);
        offer.policy = serde_json::json!({ "partitioning": self.partitioning });
        Ok(offer)
    }
}

#[cfg(test)]
mod tests {
    use fedvla_federation::StrategyParams;

    use super::*;

    fn task(seed: u64) -> RoundTask {
        RoundTask {
            round: 1,
            model_version: 0,
            local_steps: 200,
            batch_size: 16,
            lr: 0.05,
            lr_schedule: None,
            seed,
            strategy: StrategyParams::plain("fedavg"),
            keep_optimizer_state: false,
            opening_frames: None,
            deadline_ms: 1000,
            eval_request: false,
            rollout: None,
            update_encoding: fedvla_federation::UpdateEncoding::F32,
            model_deltas: None,
        }
    }

    fn block_on<F: Future>(f: F) -> F::Output {
        use std::task::{Context, Poll, Waker};
        let mut f = std::pin::pin!(f);
        match f.as_mut().poll(&mut Context::from_waker(Waker::noop())) {
            Poll::Ready(out) => out,
            Poll::Pending => panic!("the linreg trainer never waits"),
        }
    }

    #[test]
    fn training_lowers_heldout_loss() {
        let mut evaluator = LinRegEvaluator::default();
        let initial = initial_model(3);
        let before = evaluator.evaluate(&initial).unwrap().heldout_loss;
        let mut trainer = LinRegTrainer::new(0, Partitioning::Iid);
        trainer.set_global(&initial).unwrap();
        let local_before = block_on(trainer.evaluate()).unwrap().loss;
        let out = block_on(trainer.train(&task(1))).unwrap();
        let after = evaluator.evaluate(&out.update).unwrap().heldout_loss;
        assert!(after < before * 0.5, "held-out loss {before} -> {after}");
        assert!(block_on(trainer.evaluate()).unwrap().loss < local_before * 0.5);
        assert_eq!(out.examples, 48);
        assert_eq!(out.update.spec(), initial.spec());
    }

    #[test]
    fn training_is_deterministic_per_seed() {
        let run = |seed| {
            let mut trainer = LinRegTrainer::new(1, Partitioning::ByEpisode);
            trainer.set_global(&initial_model(0)).unwrap();
            block_on(trainer.train(&task(seed))).unwrap().update
        };
        assert_eq!(run(5).checksum(), run(5).checksum());
        assert_ne!(run(5).checksum(), run(6).checksum());
    }
}
