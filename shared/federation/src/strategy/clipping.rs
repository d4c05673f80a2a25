//! Update-norm clipping, a wrapper around any strategy: each client's change from the global model it started
//! from, `update - global`, is scaled down to at most `max_norm` (L2 over every trainable tensor) before the
//! wrapped rule sees it, so no single client can move the model further than that in a round. It is the
//! clipping half of DP-FedAvg (McMahan et al. 2018) and a defence against scaled updates on its own.

use super::dp::PrivacyReport;
use super::interface::{Aggregation, Contribution, Step, Strategy};
use crate::error::AggregateError;
use crate::protocol::StrategyParams;
use crate::tensors::NamedTensors;

pub struct ClippedUpdates {
    pub inner: Box<dyn Strategy>,
    pub max_norm: f64,
}

impl Strategy for ClippedUpdates {
    fn client_params(&self) -> StrategyParams {
        self.inner.client_params()
    }

    fn begin(&self, global: &NamedTensors) -> Box<dyn Aggregation> {
        Box::new(Clipping { global: global.clone(), max_norm: self.max_norm, inner: self.inner.begin(global) })
    }

    fn step(&self, global: &NamedTensors, aggregate: NamedTensors) -> Result<Step, AggregateError> {
        self.inner.step(global, aggregate)
    }

    fn commit(&mut self, state: NamedTensors) {
        self.inner.commit(state);
    }

    fn state(&self) -> NamedTensors {
        self.inner.state()
    }

    fn privacy(&self) -> Option<PrivacyReport> {
        self.inner.privacy()
    }

    fn client_correction(&self, client: u64) -> Option<NamedTensors> {
        self.inner.client_correction(client)
    }
}

struct Clipping {
    global: NamedTensors,
    max_norm: f64,
    inner: Box<dyn Aggregation>,
}

impl Aggregation for Clipping {
    fn fold(&mut self, update: Contribution<'_>) -> Result<(), AggregateError> {
        match clip_change(&self.global, update.tensors, self.max_norm) {
            Some((_, Some(clipped))) => self.inner.fold(update.with_tensors(&clipped)),
            // Within the norm, or a mismatch the wrapped rule reports with its index.
            _ => self.inner.fold(update),
        }
    }

    fn finish(self: Box<Self>) -> Result<NamedTensors, AggregateError> {
        self.inner.finish()
    }
}

/// The L2 norm of `update`'s change from `global` (over every tensor), and, when it exceeds `max_norm`, `update`
/// moved back toward `global` until it does not; `None` when `update` does not fit `global`.
pub(super) fn clip_change(
    global: &NamedTensors,
    update: &NamedTensors,
    max_norm: f64,
) -> Option<(f64, Option<NamedTensors>)> {
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
        let clipped = ClippedUpdates { inner: Box::new(FedAvg), max_norm: 5.0 };
        let global = one([1.0, 1.0]);
        // Deltas [3, 4] (norm 5: kept) and [30, 40] (norm 50: scaled by 1/10 to [3, 4]); equal weights.
        let updates = [(one([4.0, 5.0]), 1), (one([31.0, 41.0]), 1)];
        let step = aggregate(&clipped, &global, updates.iter().map(|(t, n)| (t, *n))).unwrap();
        assert_eq!(step.global.get("w").unwrap().values, vec![4.0, 5.0]);
        // Unclipped, the attacker drags the mean to [17.5, 23].
        let plain = aggregate(&FedAvg, &global, updates.iter().map(|(t, n)| (t, *n))).unwrap();
        assert_eq!(plain.global.get("w").unwrap().values, vec![17.5, 23.0]);
    }
}
