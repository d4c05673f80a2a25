//! The example-weighted mean of the clients' models: FedAvg, and FedProx, whose difference is on the clients.

use super::exact::{ExactSum, out_of_range};
use super::interface::{Aggregation, Contribution, Strategy};
use crate::error::AggregateError;
use crate::protocol::StrategyParams;
use crate::tensors::NamedTensors;

/// Federated averaging: the example-weighted mean of the clients' tensors, summed exactly as updates arrive
/// ([`super::exact`]: memory of 8 bytes a value whatever the number of clients, and the same aggregate in any
/// arrival order). The example total is summed in u128, so no set of u64 weights can wrap it.
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

/// The running example-weighted sum of a round's updates, exact and order-independent. It keeps the global
/// model's names and shapes, not its values, which no mean needs.
pub struct WeightedMean {
    spec: crate::tensors::TensorSpec,
    sum: ExactSum,
    total: u128,
    folded: usize,
}

impl WeightedMean {
    pub fn new(global: &NamedTensors) -> Self {
        let len = global.iter().map(|(_, t)| t.values.len()).sum();
        Self { spec: global.spec(), sum: ExactSum::zeros(len), total: 0, folded: 0 }
    }
}

impl Aggregation for WeightedMean {
    fn fold(&mut self, Contribution { tensors, examples, .. }: Contribution<'_>) -> Result<(), AggregateError> {
        let index = self.folded;
        tensors.validate(&self.spec).map_err(|source| AggregateError::Mismatch { index, source })?;
        // All values first: an out-of-range one leaves the sum as it was.
        let spec = &self.spec;
        let values = || {
            spec.iter()
                .flat_map(|(name, _)| &tensors.get(name).expect("validated against the global spec").values)
                .map(|&v| f64::from(v))
        };
        self.sum.add(0, examples, values).map_err(out_of_range(index))?;
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
        let mut means = self.sum.divided_by(self.total as f64)?;
        let mut out = NamedTensors::new();
        for (name, shape) in self.spec.iter() {
            let values = means.by_ref().take(shape.iter().product()).map(|m| m as f32).collect();
            out.insert(name, shape.to_vec(), values).expect("shape taken from the global model");
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
    fn fedavg_sums_exactly_in_any_order() {
        // Summed in f32 (or f64 in this order), 3e4 + 2^-30 rounds back to 3e4 and the mean would come out 0.
        let global = one([0.0, 0.0]);
        let tiny = 2f32.powi(-30);
        let updates = [(one([3.0e4, tiny]), 1), (one([tiny, 3.0e4]), 1), (one([-3.0e4, -3.0e4]), 1)];
        let want = vec![tiny / 3.0, tiny / 3.0];
        for order in [[0, 1, 2], [2, 1, 0], [1, 2, 0]] {
            let permuted: Vec<_> = order.iter().map(|&i| updates[i].clone()).collect();
            assert_eq!(fedavg(&global, &permuted).unwrap().get("w").unwrap().values, want);
        }
    }

    #[test]
    fn fedavg_refuses_values_no_model_holds() {
        let global = one([0.0, 0.0]);
        let err = fedavg(&global, &[(one([1.0, 1.0]), 1), (one([1.0, 1.0e30]), 1)]).unwrap_err();
        assert!(matches!(err, AggregateError::OutOfRange { index: 1, .. }), "{err:?}");
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
