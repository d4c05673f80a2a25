//! Robust rules: coordinate-wise statistics of the round's client models that a few wild updates cannot drag
//! far, unweighted by examples (a weight is a claim an attacker would inflate). FedMedian is Yin et al. 2018's
//! coordinate-wise median; FedTrimmedAvg drops the `beta` fraction of largest and of smallest values of every
//! coordinate and averages the rest (Yin et al. 2018's trimmed mean). Both buffer the round's updates.

use super::interface::{Aggregation, Strategy};
use crate::error::AggregateError;
use crate::protocol::StrategyParams;
use crate::tensors::{NamedTensors, TensorSpec};

/// Coordinate-wise median of the clients' models.
#[derive(Debug, Clone, Copy, Default)]
pub struct FedMedian;

/// Coordinate-wise mean after dropping the `beta` fraction of largest and of smallest values (beta in [0, 0.5)).
#[derive(Debug, Clone, Copy)]
pub struct FedTrimmedAvg {
    pub beta: f64,
}

impl Strategy for FedMedian {
    fn client_params(&self) -> StrategyParams {
        StrategyParams { name: "median".into(), proximal_mu: 0.0 }
    }

    fn begin(&self, global: &NamedTensors) -> Box<dyn Aggregation> {
        Box::new(Buffered::new(global, Statistic::Median))
    }
}

impl Strategy for FedTrimmedAvg {
    fn client_params(&self) -> StrategyParams {
        StrategyParams { name: "trimmed-mean".into(), proximal_mu: 0.0 }
    }

    fn begin(&self, global: &NamedTensors) -> Box<dyn Aggregation> {
        Box::new(Buffered::new(global, Statistic::TrimmedMean(self.beta)))
    }
}

#[derive(Debug, Clone, Copy)]
enum Statistic {
    Median,
    TrimmedMean(f64),
}

impl Statistic {
    /// Of `values`, which it sorts.
    fn of(self, values: &mut [f32]) -> f32 {
        values.sort_unstable_by(f32::total_cmp);
        let n = values.len();
        match self {
            Self::Median if n % 2 == 1 => values[n / 2],
            Self::Median => ((f64::from(values[n / 2 - 1]) + f64::from(values[n / 2])) / 2.0) as f32,
            Self::TrimmedMean(beta) => {
                let cut = ((beta * n as f64).floor() as usize).min((n - 1) / 2);
                let kept = &values[cut..n - cut];
                (kept.iter().map(|&v| f64::from(v)).sum::<f64>() / kept.len() as f64) as f32
            }
        }
    }
}

/// A round's updates, kept whole until the round closes.
struct Buffered {
    global: NamedTensors,
    spec: TensorSpec,
    statistic: Statistic,
    updates: Vec<NamedTensors>,
}

impl Buffered {
    fn new(global: &NamedTensors, statistic: Statistic) -> Self {
        Self { global: global.clone(), spec: global.spec(), statistic, updates: Vec::new() }
    }
}

impl Aggregation for Buffered {
    fn fold(&mut self, update: &NamedTensors, _examples: u64) -> Result<(), AggregateError> {
        update.validate(&self.spec).map_err(|source| AggregateError::Mismatch { index: self.updates.len(), source })?;
        self.updates.push(update.clone());
        Ok(())
    }

    fn finish(self: Box<Self>) -> Result<NamedTensors, AggregateError> {
        if self.updates.is_empty() {
            return Err(AggregateError::NoUpdates);
        }
        let mut out = NamedTensors::new();
        let mut column = Vec::with_capacity(self.updates.len());
        for (name, t) in self.global.iter() {
            let values = (0..t.values.len())
                .map(|i| {
                    column.clear();
                    column.extend(self.updates.iter().map(|u| u.get(name).expect("validated").values[i]));
                    self.statistic.of(&mut column)
                })
                .collect();
            out.insert(name, t.shape.clone(), values).expect("global shape");
        }
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::strategy::interface::{aggregate, one};

    fn run(strategy: &dyn Strategy, updates: &[[f32; 2]]) -> Vec<f32> {
        let updates: Vec<NamedTensors> = updates.iter().map(|&u| one(u)).collect();
        // Weights are ignored: a client claiming a billion examples counts once.
        let weighted = updates.iter().enumerate().map(|(i, u)| (u, if i == 0 { 1_000_000_000 } else { 1 }));
        aggregate(strategy, &one([0.0, 0.0]), weighted).unwrap().global.get("w").unwrap().values.clone()
    }

    #[test]
    fn median_by_hand() {
        assert_eq!(run(&FedMedian, &[[1e9, -5.0], [1.0, 2.0], [3.0, 1.0]]), vec![3.0, 1.0]);
        assert_eq!(run(&FedMedian, &[[1.0, 0.0], [2.0, 10.0], [4.0, 20.0], [100.0, 30.0]]), vec![3.0, 15.0]);
    }

    #[test]
    fn trimmed_mean_by_hand() {
        // Five clients, beta 0.2: one dropped from each end of every coordinate.
        let updates = [[1e9, 1.0], [1.0, 2.0], [2.0, 3.0], [3.0, 4.0], [-1e9, 100.0]];
        assert_eq!(run(&FedTrimmedAvg { beta: 0.2 }, &updates), vec![2.0, 3.0]);
        // beta 0: the plain (unweighted) mean.
        assert_eq!(run(&FedTrimmedAvg { beta: 0.0 }, &[[1.0, 2.0], [3.0, 6.0]]), vec![2.0, 4.0]);
    }

    #[test]
    fn robust_rules_refuse_an_empty_round() {
        let r = aggregate(&FedMedian, &one([0.0, 0.0]), std::iter::empty::<(&NamedTensors, u64)>());
        assert_eq!(r, Err(AggregateError::NoUpdates));
    }
}
