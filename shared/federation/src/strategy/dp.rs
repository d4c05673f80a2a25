//! Client-level DP-FedAvg (McMahan et al. 2018, "Learning Differentially Private Recurrent Language Models"), a
//! wrapper around a mean-based strategy: each client's change from the global model is clipped to the clipping
//! norm `C` (as [`super::ClippedUpdates`] clips), the wrapped rule averages, and Gaussian noise of standard
//! deviation `z * C * w_max / W` is added to every value of the average, `w_max / W` being the largest client's
//! share of the weights (`1/m` for `m` equal shards): the most one client can move the average, so `z` is the
//! noise multiplier the accountant needs. The clipping norm is fixed, or adaptive (Andrew et al. 2021,
//! "Differentially Private Learning with Adaptive Clipping"): after each round `C <- C * exp(-lr * (b - gamma))`,
//! `b` the fraction of clients whose change was within `C` plus Gaussian noise of standard deviation
//! `count_stddev / m`, so `C` follows the `gamma` quantile of the changes' norms; the update's own noise
//! multiplier is then raised to `(z^-2 - (2 count_stddev)^-2)^-1/2`, so each round as a whole releases at `z`
//! (their theorem 1). The privacy spent is the RDP accountant's ([`crate::accountant`]) at the rate at which
//! clients are sampled, one release per committed round. The noise of a round is drawn from the run's seed and
//! the round's number, so a retried or resumed round draws the same.

use rand::SeedableRng;
use rand::rngs::StdRng;
use rand_distr::{Distribution, Normal};
use serde::{Deserialize, Serialize};

use super::clipping::{ClipNorm, ClippedRound};
use super::interface::{Aggregation, Contribution, Step, Strategy};
use crate::accountant::{PrivacySpent, privacy_spent};
use crate::error::AggregateError;
use crate::protocol::StrategyParams;
use crate::seed::mix;
use crate::tensors::NamedTensors;

/// State keys: rounds committed, and the clipping norm the next round clips to.
const ROUNDS_KEY: &str = "dp/rounds";
const CLIP_NORM_KEY: &str = "dp/clip-norm";
/// The noisy fraction of a round's clients within the clipping norm, carried from the round's aggregate to its step.
const WITHIN_KEY: &str = "dp/within-fraction";

/// What a round's metrics record of the privacy spent so far.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PrivacyReport {
    #[serde(flatten)]
    pub spent: PrivacySpent,
    /// The noise multiplier `z` each round releases at.
    pub noise_multiplier: f64,
    /// The rate at which clients are sampled into a round.
    pub sampling_rate: f64,
    /// The clipping norm the next round clips to.
    pub clip_norm: f64,
}

/// DP-FedAvg around `inner`, whose aggregate must be a weighted mean of the (clipped) updates.
pub struct DpFedAvg {
    pub inner: Box<dyn Strategy>,
    pub noise_multiplier: f64,
    pub clip: ClipNorm,
    pub sampling_rate: f64,
    pub delta: f64,
    pub seed: u64,
    rounds: u64,
    /// Kept as the f32 the saved state holds, so a resumed run clips exactly as an uninterrupted one.
    clip_norm: f32,
}

impl DpFedAvg {
    pub fn new(
        inner: Box<dyn Strategy>,
        noise_multiplier: f64,
        clip: ClipNorm,
        sampling_rate: f64,
        delta: f64,
        seed: u64,
    ) -> Self {
        let clip_norm = clip.initial() as f32;
        Self { inner, noise_multiplier, clip, sampling_rate, delta, seed, rounds: 0, clip_norm }
    }

    /// The noise multiplier of the averaged update: all of `z`, less what the adaptive norm's count takes.
    fn update_noise_multiplier(&self) -> f64 {
        match self.clip {
            ClipNorm::Adaptive { count_stddev, .. } if self.noise_multiplier > 0.0 => {
                (self.noise_multiplier.powi(-2) - (2.0 * count_stddev).powi(-2)).powf(-0.5)
            }
            _ => self.noise_multiplier,
        }
    }
}

impl Strategy for DpFedAvg {
    fn client_params(&self) -> StrategyParams {
        self.inner.client_params()
    }

    fn begin(&self, global: &NamedTensors) -> Box<dyn Aggregation> {
        Box::new(DpRound {
            round: ClippedRound::new(global, f64::from(self.clip_norm), self.inner.begin(global)),
            clip_norm: f64::from(self.clip_norm),
            noise_multiplier: self.update_noise_multiplier(),
            count_stddev: match self.clip {
                ClipNorm::Adaptive { count_stddev, .. } => count_stddev,
                ClipNorm::Fixed(_) => 0.0,
            },
            rng: StdRng::seed_from_u64(mix(self.seed, self.rounds)),
            total_weight: 0,
            max_weight: 0,
        })
    }

    fn step(&self, global: &NamedTensors, aggregate: NamedTensors) -> Result<Step, AggregateError> {
        let within = aggregate.get(WITHIN_KEY).and_then(|t| t.values.first().copied());
        let step = self.inner.step(global, aggregate.without(&[WITHIN_KEY]))?;
        let clip_norm = self.clip.next(self.clip_norm, within);
        let mut state = step.state;
        state.insert(ROUNDS_KEY, vec![1], vec![(self.rounds + 1) as f32]).expect("scalar");
        state.insert(CLIP_NORM_KEY, vec![1], vec![clip_norm]).expect("scalar");
        Ok(Step { global: step.global, state })
    }

    fn commit(&mut self, state: NamedTensors) {
        let scalar = |key: &str| state.get(key).and_then(|t| t.values.first().copied());
        self.rounds = scalar(ROUNDS_KEY).map_or(0, |r| r as u64);
        self.clip_norm = scalar(CLIP_NORM_KEY).unwrap_or(self.clip.initial() as f32);
        self.inner.commit(state.without(&[ROUNDS_KEY, CLIP_NORM_KEY]));
    }

    fn state(&self) -> NamedTensors {
        let mut state = self.inner.state();
        state.insert(ROUNDS_KEY, vec![1], vec![self.rounds as f32]).expect("scalar");
        state.insert(CLIP_NORM_KEY, vec![1], vec![self.clip_norm]).expect("scalar");
        state
    }

    fn privacy(&self) -> Option<PrivacyReport> {
        Some(PrivacyReport {
            spent: privacy_spent(self.sampling_rate, self.noise_multiplier, self.rounds, self.delta),
            noise_multiplier: self.noise_multiplier,
            sampling_rate: self.sampling_rate,
            clip_norm: f64::from(self.clip_norm),
        })
    }
}

struct DpRound {
    /// The clipping and the count of changes within the norm, as clipping alone does them.
    round: ClippedRound,
    clip_norm: f64,
    noise_multiplier: f64,
    count_stddev: f64,
    rng: StdRng,
    total_weight: u128,
    max_weight: u64,
}

impl Aggregation for DpRound {
    fn fold(&mut self, update: Contribution<'_>) -> Result<(), AggregateError> {
        let examples = update.examples;
        self.round.fold(update)?;
        self.total_weight += u128::from(examples);
        self.max_weight = self.max_weight.max(examples);
        Ok(())
    }

    fn finish(mut self: Box<Self>) -> Result<NamedTensors, AggregateError> {
        let (mut aggregate, count) = self.round.finish()?;
        let share = self.max_weight as f64 / self.total_weight as f64;
        let stddev = self.noise_multiplier * self.clip_norm * share;
        if stddev > 0.0 {
            let noise = Normal::new(0.0, stddev).expect("finite positive standard deviation");
            for (_, values) in aggregate.iter_mut() {
                for v in values {
                    *v = (f64::from(*v) + noise.sample(&mut self.rng)) as f32;
                }
            }
        }
        let count_noise = match self.count_stddev {
            0.0 => 0.0,
            s => Normal::new(0.0, s).expect("finite positive standard deviation").sample(&mut self.rng),
        };
        let within = (count.within as f64 + count_noise) / count.folded as f64;
        aggregate.insert(WITHIN_KEY, vec![1], vec![within as f32]).expect("scalar");
        Ok(aggregate)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::strategy::interface::{aggregate, one};
    use crate::strategy::mean::FedAvg;

    fn dp(noise_multiplier: f64, clip: ClipNorm) -> DpFedAvg {
        DpFedAvg::new(Box::new(FedAvg), noise_multiplier, clip, 1.0, 1e-5, 7)
    }

    /// A one-tensor model of `n` values `value`.
    fn flat(n: usize, value: f32) -> NamedTensors {
        let mut t = NamedTensors::new();
        t.insert("w", vec![n], vec![value; n]).unwrap();
        t
    }

    #[test]
    fn without_noise_it_is_clipped_fedavg() {
        let s = dp(0.0, ClipNorm::Fixed(5.0));
        // Deltas [3, 4] (norm 5: kept) and [30, 40] (clipped to [3, 4]) from [1, 1]: the mean is [4, 5].
        let updates = [(one([4.0, 5.0]), 1), (one([31.0, 41.0]), 3)];
        let step = aggregate(&s, &one([1.0, 1.0]), updates.iter().map(|(t, n)| (t, *n))).unwrap();
        assert_eq!(step.global.get("w").unwrap().values, vec![4.0, 5.0]);
        assert_eq!(step.state.get(ROUNDS_KEY).unwrap().values, vec![1.0]);
        assert_eq!(step.state.get(CLIP_NORM_KEY).unwrap().values, vec![5.0]);
    }

    #[test]
    fn the_noise_has_the_standard_deviation_of_the_largest_share() {
        // z = 0.5, C = 2, weights 1 and 3: sigma = 0.5 * 2 * 3/4 = 0.75 on every value of a zero mean.
        let s = dp(0.5, ClipNorm::Fixed(2.0));
        let n = 40_000;
        let (global, update) = (flat(n, 0.0), flat(n, 0.0));
        let step = aggregate(&s, &global, [(&update, 1), (&update, 3)]).unwrap();
        let values = &step.global.get("w").unwrap().values;
        let mean = values.iter().map(|&v| f64::from(v)).sum::<f64>() / n as f64;
        let sd = (values.iter().map(|&v| (f64::from(v) - mean).powi(2)).sum::<f64>() / n as f64).sqrt();
        // The sample deviation of 40,000 normal draws is within 1.5% of sigma with overwhelming probability.
        assert!((sd - 0.75).abs() < 0.75 * 0.015 && mean.abs() < 0.02, "mean {mean}, sd {sd}");
        // The same round again draws the same noise; the next round draws other noise.
        assert_eq!(aggregate(&s, &global, [(&update, 1), (&update, 3)]).unwrap(), step);
        let mut next = dp(0.5, ClipNorm::Fixed(2.0));
        next.commit(step.state.clone());
        assert_ne!(aggregate(&next, &global, [(&update, 1), (&update, 3)]).unwrap().global, step.global);
    }

    #[test]
    fn the_adaptive_norm_moves_toward_its_quantile() {
        // No noise: C = 1, 1 of 4 changes within it (b = 0.25), gamma 0.5, lr 0.2: C' = exp(-0.2 * (0.25 - 0.5)).
        let clip = ClipNorm::Adaptive { initial: 1.0, target_quantile: 0.5, lr: 0.2, count_stddev: 0.0 };
        let mut s = dp(0.0, clip);
        let updates = [one([0.5, 0.0]), one([3.0, 0.0]), one([0.0, 4.0]), one([-2.0, 0.0])];
        let step = aggregate(&s, &one([0.0, 0.0]), updates.iter().map(|t| (t, 1))).unwrap();
        let want = (0.2f64 * 0.25).exp() as f32;
        assert_eq!(step.state.get(CLIP_NORM_KEY).unwrap().values, vec![want]);
        s.commit(step.state);
        assert_eq!(s.privacy().unwrap().clip_norm, f64::from(want));
        // The update's noise multiplier gives up what the count takes: z = 0.5, count sd 1 -> (4 - 1/4)^-1/2.
        let noisy = dp(0.5, ClipNorm::Adaptive { initial: 1.0, target_quantile: 0.5, lr: 0.2, count_stddev: 1.0 });
        assert!((noisy.update_noise_multiplier() - 3.75f64.powf(-0.5)).abs() < 1e-12);
    }

    #[test]
    fn state_round_trips_and_privacy_counts_committed_rounds() {
        let mut s = DpFedAvg::new(Box::new(FedAvg), 1.0, ClipNorm::Fixed(1.0), 0.1, 1e-5, 0);
        assert_eq!(s.privacy().unwrap().spent.epsilon, 0.0);
        let mut state = NamedTensors::new();
        state.insert(ROUNDS_KEY, vec![1], vec![100.0]).unwrap();
        state.insert(CLIP_NORM_KEY, vec![1], vec![0.5]).unwrap();
        s.commit(state.clone());
        assert_eq!(s.state(), state);
        // 100 rounds at q = 0.1, z = 1: dp_accounting's epsilon (see the accountant's tests).
        let report = s.privacy().unwrap();
        assert!((report.spent.epsilon - 7.903850223578231).abs() < 1e-8, "{report:?}");
        assert_eq!((report.spent.rounds, report.clip_norm), (100, 0.5));
    }
}
