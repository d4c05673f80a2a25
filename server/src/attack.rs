//! Simulated attackers, for `simulate` and the robust rules' tests: a volunteer that trains honestly and then
//! sends a corrupted update, `global + strength * (update - global)` (`scale`: a boosted update, as a model
//! replacement attack sends) or `global - strength * (update - global)` (`sign-flip`: the honest step reversed
//! and amplified) or `global + strength * N(0, 1)` (`noise`: no training signal at all, seeded by the task); or
//! one that poisons its data (`label-shuffle`: the labels of its training rows shuffled among them before it
//! trains, see `native_client`) and sends what that training gives. `attackers = K` makes clients 0..K such
//! volunteers.

use fedvla_aggregator::config::AttackKind;
use fedvla_federation::protocol::RolloutRequest;
use fedvla_federation::{
    BoxError, Capabilities, EvalOutput, LocalTrainer, NamedTensors, RolloutOutput, RoundTask, TrainOutput,
};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use rand_distr::StandardNormal;

/// How an attacker corrupts its updates.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Attack {
    pub kind: AttackKind,
    pub strength: f64,
}

impl Attack {
    /// `update` as this attack sends it, from the `global` model it started from; `seed` draws the noise.
    pub fn corrupt(&self, global: &NamedTensors, update: &NamedTensors, seed: u64) -> NamedTensors {
        let factor = match self.kind {
            AttackKind::Scale => self.strength,
            AttackKind::SignFlip => -self.strength,
            // The poison is in the data it trained on.
            AttackKind::LabelShuffle => return update.clone(),
            AttackKind::Noise => {
                let mut rng = StdRng::seed_from_u64(seed);
                let mut out = global.clone();
                for (_, values) in out.iter_mut() {
                    for v in values {
                        *v += (self.strength * rng.sample::<f64, _>(StandardNormal)) as f32;
                    }
                }
                return out;
            }
        };
        let mut out = NamedTensors::new();
        for (name, g) in global.iter() {
            let u = update.get(name).map_or(&g.values, |t| &t.values);
            let values = g
                .values
                .iter()
                .zip(u)
                .map(|(g, u)| (f64::from(*g) + factor * (f64::from(*u) - f64::from(*g))) as f32)
                .collect();
            out.insert(name, g.shape.clone(), values).expect("global shape");
        }
        out
    }
}

/// A volunteer's trainer whose updates `attack` corrupts; everything else is the honest trainer's.
pub struct Attacker<T> {
    pub inner: T,
    pub attack: Attack,
    global: Option<NamedTensors>,
}

impl<T> Attacker<T> {
    pub fn new(inner: T, attack: Attack) -> Self {
        Self { inner, attack, global: None }
    }
}

impl<T: LocalTrainer> LocalTrainer for Attacker<T> {
    fn capabilities(&self) -> Capabilities {
        self.inner.capabilities()
    }

    fn set_global(&mut self, global: &NamedTensors) -> Result<(), BoxError> {
        self.global = Some(global.clone());
        self.inner.set_global(global)
    }

    fn set_correction(&mut self, correction: &NamedTensors) -> Result<(), BoxError> {
        self.inner.set_correction(correction)
    }

    fn set_norm_stats(&mut self, stats: &fedvla_federation::NormalizationStats) -> Result<(), BoxError> {
        self.inner.set_norm_stats(stats)
    }

    async fn train(&mut self, task: &RoundTask) -> Result<TrainOutput, BoxError> {
        let mut out = self.inner.train(task).await?;
        if let Some(global) = &self.global {
            out.update = self.attack.corrupt(global, &out.update, task.seed);
        }
        Ok(out)
    }

    async fn evaluate(&mut self) -> Result<EvalOutput, BoxError> {
        self.inner.evaluate().await
    }

    async fn rollout(&mut self, request: &RolloutRequest) -> Result<Vec<RolloutOutput>, BoxError> {
        self.inner.rollout(request).await
    }
}
