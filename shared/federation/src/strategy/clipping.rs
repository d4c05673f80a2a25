//! Update-norm clipping, a wrapper around any strategy: each client's change from the global model it started
//! from, `update - global`, is scaled down to at most the clipping norm (L2 over every trainable tensor) before the
//! wrapped rule sees it, so no single client can move the model further than that in a round. It is the
//! clipping half of DP-FedAvg (McMahan et al. 2018) and a defence against scaled updates on its own. The norm is
//! fixed, or adaptive (Andrew et al. 2021, "Differentially Private Learning with Adaptive Clipping"): after each
//! round `C <- C * exp(-lr * (b - gamma))`, `b` the fraction of the round's changes within `C`, so `C` follows the
//! `gamma` quantile of the changes' norms as they shrink over a decaying learning rate (a fixed norm set from one
//! round's norms clips every honest change early in a run and none of an attacker's late in it).

use super::dp::PrivacyReport;
use super::interface::{Aggregation, Contribution, Step, Strategy};
use crate::error::AggregateError;
use crate::protocol::StrategyParams;
use crate::tensors::NamedTensors;

/// State key: the clipping norm the next round clips to (an adaptive norm only).
const CLIP_NORM_KEY: &str = "clip/norm";
/// The fraction of a round's changes within the norm, carried from the round's aggregate to its step.
const WITHIN_KEY: &str = "clip/within-fraction";

/// How the clipping norm is chosen.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ClipNorm {
    Fixed(f64),
    /// Starts at `initial` and follows the `target_quantile` of the clients' change norms, at rate `lr`, the count
    /// of clipped clients noised with standard deviation `count_stddev` (DP-FedAvg's; 0 for clipping alone).
    Adaptive {
        initial: f64,
        target_quantile: f64,
        lr: f64,
        count_stddev: f64,
    },
}

impl ClipNorm {
    pub(super) fn initial(self) -> f64 {
        match self {
            ClipNorm::Fixed(norm) | ClipNorm::Adaptive { initial: norm, .. } => norm,
        }
    }

    /// The norm after a round that clipped to `current` and found the fraction `within` of its changes within it
    /// (`None`: no round to learn from); kept as the f32 a saved state holds, so a resumed run clips as an
    /// uninterrupted one.
    pub(super) fn next(self, current: f32, within: Option<f32>) -> f32 {
        match (self, within) {
            (ClipNorm::Adaptive { target_quantile, lr, .. }, Some(b)) => {
                (f64::from(current) * (-lr * (f64::from(b) - target_quantile)).exp()) as f32
            }
            _ => current,
        }
    }
}

/// Clipping around `inner`.
pub struct ClippedUpdates {
    pub inner: Box<dyn Strategy>,
    /// Private, as `clip_norm` starts from it: set once by [`ClippedUpdates::fixed`] or [`ClippedUpdates::adaptive`].
    clip: ClipNorm,
    clip_norm: f32,
}

impl ClippedUpdates {
    /// Every change clipped to `max_norm`.
    pub fn fixed(inner: Box<dyn Strategy>, max_norm: f64) -> Self {
        Self::new(inner, ClipNorm::Fixed(max_norm))
    }

    /// Every change clipped to a norm that starts at `initial` and follows the `target_quantile` of the changes'
    /// norms at rate `lr`.
    pub fn adaptive(inner: Box<dyn Strategy>, initial: f64, target_quantile: f64, lr: f64) -> Self {
        Self::new(inner, ClipNorm::Adaptive { initial, target_quantile, lr, count_stddev: 0.0 })
    }

    fn new(inner: Box<dyn Strategy>, clip: ClipNorm) -> Self {
        Self { inner, clip, clip_norm: clip.initial() as f32 }
    }

    fn adapts(&self) -> bool {
        matches!(self.clip, ClipNorm::Adaptive { .. })
    }
}

impl Strategy for ClippedUpdates {
    fn client_params(&self) -> StrategyParams {
        self.inner.client_params()
    }

    fn begin(&self, global: &NamedTensors) -> Box<dyn Aggregation> {
        Box::new(Clipping {
            round: ClippedRound::new(global, f64::from(self.clip_norm), self.inner.begin(global)),
            count_within: self.adapts(),
        })
    }

    fn step(&self, global: &NamedTensors, aggregate: NamedTensors) -> Result<Step, AggregateError> {
        if !self.adapts() {
            return self.inner.step(global, aggregate);
        }
        let within = aggregate.get(WITHIN_KEY).and_then(|t| t.values.first().copied());
        let step = self.inner.step(global, aggregate.without(&[WITHIN_KEY]))?;
        let mut state = step.state;
        state.insert(CLIP_NORM_KEY, vec![1], vec![self.clip.next(self.clip_norm, within)]).expect("scalar");
        Ok(Step { global: step.global, state })
    }

    fn commit(&mut self, state: NamedTensors) {
        if !self.adapts() {
            return self.inner.commit(state);
        }
        self.clip_norm = state.get(CLIP_NORM_KEY).and_then(|t| t.values.first().copied()).unwrap_or(self.clip_norm);
        self.inner.commit(state.without(&[CLIP_NORM_KEY]));
    }

    fn state(&self) -> NamedTensors {
        let mut state = self.inner.state();
        if self.adapts() {
            state.insert(CLIP_NORM_KEY, vec![1], vec![self.clip_norm]).expect("scalar");
        }
        state
    }

    fn privacy(&self) -> Option<PrivacyReport> {
        self.inner.privacy()
    }

    fn client_correction(&self, client: u64) -> Option<NamedTensors> {
        self.inner.client_correction(client)
    }
}

struct Clipping {
    round: ClippedRound,
    /// Whether the aggregate carries the fraction of changes within the norm (for an adaptive norm).
    count_within: bool,
}

impl Aggregation for Clipping {
    fn fold(&mut self, update: Contribution<'_>) -> Result<(), AggregateError> {
        self.round.fold(update)
    }

    fn finish(self: Box<Self>) -> Result<NamedTensors, AggregateError> {
        let (mut aggregate, count) = self.round.finish()?;
        if self.count_within && count.folded > 0 {
            let within = count.within as f64 / count.folded as f64;
            aggregate.insert(WITHIN_KEY, vec![1], vec![within as f32]).expect("scalar");
        }
        Ok(aggregate)
    }
}

/// One round's clip-and-count, the part clipping alone and DP-FedAvg share: every change clipped to `max_norm`
/// before the wrapped rule folds it, and how many of the folded changes were within the norm (what an adaptive
/// norm steers by).
pub(super) struct ClippedRound {
    global: NamedTensors,
    max_norm: f64,
    inner: Box<dyn Aggregation>,
    count: WithinCount,
}

/// Of a round's folded changes, how many were within the clipping norm.
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct WithinCount {
    pub folded: usize,
    pub within: usize,
}

impl ClippedRound {
    pub(super) fn new(global: &NamedTensors, max_norm: f64, inner: Box<dyn Aggregation>) -> Self {
        Self { global: global.clone(), max_norm, inner, count: WithinCount::default() }
    }

    /// Clips `update`'s change and folds it into the wrapped rule; an update that does not fit the global model
    /// goes to the wrapped rule as it is, which reports the mismatch with its index.
    pub(super) fn fold(&mut self, update: Contribution<'_>) -> Result<(), AggregateError> {
        let Some((norm, clipped)) = clip_change(&self.global, update.tensors, self.max_norm) else {
            return self.inner.fold(update);
        };
        self.inner.fold(update.with_tensors(clipped.as_ref().unwrap_or(update.tensors)))?;
        self.count.folded += 1;
        self.count.within += usize::from(norm <= self.max_norm);
        Ok(())
    }

    pub(super) fn finish(self) -> Result<(NamedTensors, WithinCount), AggregateError> {
        Ok((self.inner.finish()?, self.count))
    }
}

/// The L2 norm of `update`'s change from `global` (over every tensor), and, when it exceeds `max_norm`, `update`
/// moved back toward `global` until it does not; `None` when `update` does not fit `global`.
fn clip_change(global: &NamedTensors, update: &NamedTensors, max_norm: f64) -> Option<(f64, Option<NamedTensors>)> {
    update.validate(&global.spec()).ok()?;
    let norm = update.distance(global).ok()?;
    if norm <= max_norm {
        return Some((norm, None));
    }
    let scale = max_norm / norm;
    let mut clipped = NamedTensors::new();
    for (name, g) in global.iter() {
        let u = &update.get(name).expect("validated").values;
        let values =
            g.values.iter().zip(u).map(|(g, u)| (f64::from(*g) + (f64::from(*u) - f64::from(*g)) * scale) as f32);
        clipped.insert(name, g.shape.clone(), values.collect()).expect("global shape");
    }
    Some((norm, Some(clipped)))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::strategy::interface::{aggregate, one};
    use crate::strategy::mean::FedAvg;

    #[test]
    fn clipping_by_hand() {
        let clipped = ClippedUpdates::fixed(Box::new(FedAvg), 5.0);
        let global = one([1.0, 1.0]);
        // Deltas [3, 4] (norm 5: kept) and [30, 40] (norm 50: scaled by 1/10 to [3, 4]); equal weights.
        let updates = [(one([4.0, 5.0]), 1), (one([31.0, 41.0]), 1)];
        let step = aggregate(&clipped, &global, updates.iter().map(|(t, n)| (t, *n))).unwrap();
        assert_eq!(step.global.get("w").unwrap().values, vec![4.0, 5.0]);
        // Unclipped, the attacker drags the mean to [17.5, 23].
        let plain = aggregate(&FedAvg, &global, updates.iter().map(|(t, n)| (t, *n))).unwrap();
        assert_eq!(plain.global.get("w").unwrap().values, vec![17.5, 23.0]);
    }

    #[test]
    fn the_adaptive_norm_follows_its_quantile_and_resumes() {
        // C = 1; changes of norm 0.5, 3, 4 and 2 from [0, 0]: one within (b = 1/4), the others scaled to norm 1.
        let mut clipped = ClippedUpdates::adaptive(Box::new(FedAvg), 1.0, 0.5, 0.2);
        let updates = [one([0.5, 0.0]), one([3.0, 0.0]), one([0.0, 4.0]), one([-2.0, 0.0])];
        let step = aggregate(&clipped, &one([0.0, 0.0]), updates.iter().map(|t| (t, 1))).unwrap();
        assert_eq!(step.global.get("w").unwrap().values, vec![0.125, 0.25]);
        // C' = exp(-0.2 * (0.25 - 0.5)); the aggregate's count is not a tensor of the model.
        let want = (0.2f64 * 0.25).exp() as f32;
        assert_eq!(step.state.get(CLIP_NORM_KEY).unwrap().values, vec![want]);
        assert!(step.global.get(WITHIN_KEY).is_none());
        clipped.commit(step.state.clone());
        assert_eq!(clipped.state(), step.state);
        // A fresh wrapper given the saved state clips the next round as the committed one does.
        let mut resumed = ClippedUpdates::adaptive(Box::new(FedAvg), 1.0, 0.5, 0.2);
        resumed.commit(step.state);
        let next = [one([2.0, 0.0]), one([0.0, 0.5])];
        let (a, b) = (
            aggregate(&clipped, &one([0.0, 0.0]), next.iter().map(|t| (t, 1))).unwrap(),
            aggregate(&resumed, &one([0.0, 0.0]), next.iter().map(|t| (t, 1))).unwrap(),
        );
        assert_eq!(a, b);
        assert_eq!(a.global.get("w").unwrap().values, vec![want / 2.0, 0.25]);
    }
}
