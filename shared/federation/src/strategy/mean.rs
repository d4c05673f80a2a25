//! The example-weighted mean of the clients' models: FedAvg, and FedProx, whose difference is on the clients.

use super::interface::{Aggregation, Contribution, Strategy};
use crate::error::AggregateError;
use crate::protocol::StrategyParams;
use crate::tensors::NamedTensors;

/// Federated averaging: the example-weighted mean of the clients' tensors, accumulated in f64 as updates arrive
/// (memory: one f64 per value, whatever the number of clients). The example total is summed in u128, so no set
/// of u64 weights can wrap it.
#[derive(Debug, Clone, Copy, Default)]
pub struct FedAvg;

impl Strategy for FedAvg {
    fn client_params(&self) -> StrategyParams {
        StrategyParams::plain("fedavg")
    }

    fn begin(&self, global: &NamedTensors) -> Box<dyn Aggregation> {
        Box::new(WeightedMean::new(global))
    }
}

/// FedProx (Li et al. 2020): FedAvg's aggregation, with clients adding `mu/2 * ||w - w_global||^2` to their
/// local loss (the SmolVLA trainer and linreg do, from the task's [`StrategyParams::proximal_mu`]).
#[derive(Debug, Clone, Copy)]
pub struct FedProx {
    pub mu: f64,
}

impl Strategy for FedProx {
    fn client_params(&self) -> StrategyParams {
        StrategyParams { proximal_mu: self.mu, ..StrategyParams::plain("fedprox") }
    }

    fn begin(&self, global: &NamedTensors) -> Box<dyn Aggregation> {
        Box::new(WeightedMean::new(global))
    }
}

/// The running example-weighted sum of a round's updates.
pub struct WeightedMean {
    /// Names and shapes of the global model, and the sum per value.
    sums: Vec<(String, Vec<usize>, Vec<f64>)>,
    spec: crate::tensors::TensorSpec,
    total: u128,
    folded: usize,
}

impl WeightedMean {
    pub fn new(global: &NamedTensors) -> Self {
        let sums =
            global.iter().map(|(name, t)| (name.to_owned(), t.shape.clone(), vec![0f64; t.values.len()])).collect();
        Self { sums, spec: global.spec(), total: 0, folded: 0 }
    }
}

impl Aggregation for WeightedMean {
    fn fold(&mut self, Contribution { tensors, examples, .. }: Contribution<'_>) -> Result<(), AggregateError> {
        tensors.validate(&self.spec).map_err(|source| AggregateError::Mismatch { index: self.folded, source })?;
        let w = examples as f64;
        for (name, _, sum) in &mut self.sums {
            let values = &tensors.get(name).expect("validated against the global spec").values;
            for (a, v) in sum.iter_mut().zip(values) {
                *a += w * f64::from(*v);
            }
        }
        self.total += u128::from(examples);
        self.folded += 1;
        Ok(())
    }

    fn finish(self: Box<Self>) -> Result<NamedTensors, AggregateError> {
        if self.folded == 0 {
            return Err(AggregateError::NoUpdates);
        }
        if self.total == 0 {
            return Err(AggregateError::ZeroExamples);
        }
        let total = self.total as f64;
        let mut out = NamedTensors::new();
        for (name, shape, sum) in self.sums {
            let values = sum.into_iter().map(|a| (a / total) as f32).collect();
            out.insert(name, shape, values).expect("shape taken from the global model");
        }
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::strategy::interface::{aggregate, one};

    fn fedavg(global: &NamedTensors, updates: &[(NamedTensors, u64)]) -> Result<NamedTensors, AggregateError> {
        aggregate(&FedAvg, global, updates.iter().map(|(t, n)| (t, *n))).map(|step| step.global)
    }

    #[test]
    fn fedavg_is_example_weighted_mean() {
        let global = one([0.0, 0.0]);
        let updates = [(one([1.0, 10.0]), 1), (one([4.0, -2.0]), 3)];
        let out = fedavg(&global, &updates).unwrap();
        assert_eq!(out.get("w").unwrap().values, vec![3.25, 1.0]);
    }

    #[test]
    fn fedavg_accumulates_in_f64() {
        // Summed in f32, 1e8 + 1 rounds back to 1e8 and the mean would come out 0.
        let global = one([0.0, 0.0]);
        let updates = [(one([1.0e8, 1.0]), 1), (one([1.0, 1.0e8]), 1), (one([-1.0e8, -1.0e8]), 1)];
        let out = fedavg(&global, &updates).unwrap();
        assert_eq!(out.get("w").unwrap().values, vec![1.0 / 3.0, 1.0 / 3.0]);
    }

    #[test]
    fn fedavg_example_total_cannot_wrap() {
        // 2^63 + 2^63 wraps a u64 sum to 0; the weights are equal, so the mean is the midpoint.
        let global = one([0.0, 0.0]);
        let updates = [(one([1.0, 2.0]), 1 << 63), (one([3.0, 4.0]), 1 << 63)];
        let out = fedavg(&global, &updates).unwrap();
        assert_eq!(out.get("w").unwrap().values, vec![2.0, 3.0]);
        let updates = [(one([1.0, 2.0]), u64::MAX - 46), (one([3.0, 4.0]), 48)];
        let out = fedavg(&global, &updates).unwrap();
        assert!(out.get("w").unwrap().values.iter().all(|v| v.is_finite()));
    }

    #[test]
    fn fedavg_refuses_empty_zero_and_mismatched() {
        let global = one([0.0, 0.0]);
        assert_eq!(fedavg(&global, &[]), Err(AggregateError::NoUpdates));
        assert_eq!(fedavg(&global, &[(one([1.0, 1.0]), 0)]), Err(AggregateError::ZeroExamples));
        let mut other = NamedTensors::new();
        other.insert("v", vec![2], vec![0.0, 0.0]).unwrap();
        assert!(matches!(
            fedavg(&global, &[(one([1.0, 1.0]), 1), (other, 1)]),
            Err(AggregateError::Mismatch { index: 1, .. })
        ));
    }
}
