//! Aggregation strategies.

use crate::error::AggregateError;
use crate::protocol::StrategyParams;
use crate::tensors::NamedTensors;

/// Turns the clients' updates of one round into the next global model.
///
/// `&mut self` lets stateful strategies (FedAdam's moments, FedProx schedules) keep state across rounds; the
/// server owns its strategy in a single task.
pub trait Strategy {
    /// Parameters clients need for local training, sent in every task.
    fn client_params(&self) -> StrategyParams;

    /// `updates` are the clients' trained tensors with their example counts, in a deterministic order.
    fn aggregate(
        &mut self,
        global: &NamedTensors,
        updates: &[(NamedTensors, u64)],
    ) -> Result<NamedTensors, AggregateError>;
}

/// Federated averaging: the example-weighted mean of the clients' tensors, accumulated in f64. The example total
/// is summed in u128, so no set of u64 weights can wrap it.
#[derive(Debug, Clone, Copy, Default)]
pub struct FedAvg;

impl Strategy for FedAvg {
    fn client_params(&self) -> StrategyParams {
        StrategyParams { name: "fedavg".into(), proximal_mu: 0.0 }
    }

    fn aggregate(
        &mut self,
        global: &NamedTensors,
        updates: &[(NamedTensors, u64)],
    ) -> Result<NamedTensors, AggregateError> {
        if updates.is_empty() {
            return Err(AggregateError::NoUpdates);
        }
        let spec = global.spec();
        for (index, (update, _)) in updates.iter().enumerate() {
            update.validate(&spec).map_err(|source| AggregateError::Mismatch { index, source })?;
        }
        let total: u128 = updates.iter().map(|(_, n)| u128::from(*n)).sum();
        if total == 0 {
            return Err(AggregateError::ZeroExamples);
        }
        let mut out = NamedTensors::new();
        for (name, t) in global.iter() {
            let mut acc = vec![0f64; t.values.len()];
            for (update, n) in updates {
                let w = *n as f64;
                let values = &update.get(name).expect("validated against the global spec").values;
                for (a, v) in acc.iter_mut().zip(values) {
                    *a += w * f64::from(*v);
                }
            }
            let values = acc.into_iter().map(|a| (a / total as f64) as f32).collect();
            out.insert(name, t.shape.clone(), values).expect("shape taken from the global model");
        }
        // Finite inputs average to finite values; the check keeps that promise for every strategy's output.
        out.validate(&spec).map_err(AggregateError::Aggregate)?;
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn one(v: [f32; 2]) -> NamedTensors {
        let mut t = NamedTensors::new();
        t.insert("w", vec![2], v.to_vec()).unwrap();
        t
    }

    #[test]
    fn fedavg_is_example_weighted_mean() {
        let global = one([0.0, 0.0]);
        let updates = [(one([1.0, 10.0]), 1), (one([4.0, -2.0]), 3)];
        let out = FedAvg.aggregate(&global, &updates).unwrap();
        assert_eq!(out.get("w").unwrap().values, vec![3.25, 1.0]);
    }

    #[test]
    fn fedavg_accumulates_in_f64() {
        // Summed in f32, 1e8 + 1 rounds back to 1e8 and the mean would come out 0.
        let global = one([0.0, 0.0]);
        let updates = [(one([1.0e8, 1.0]), 1), (one([1.0, 1.0e8]), 1), (one([-1.0e8, -1.0e8]), 1)];
        let out = FedAvg.aggregate(&global, &updates).unwrap();
        assert_eq!(out.get("w").unwrap().values, vec![1.0 / 3.0, 1.0 / 3.0]);
    }

    #[test]
    fn fedavg_example_total_cannot_wrap() {
        // 2^63 + 2^63 wraps a u64 sum to 0; the weights are equal, so the mean is the midpoint.
        let global = one([0.0, 0.0]);
        let updates = [(one([1.0, 2.0]), 1 << 63), (one([3.0, 4.0]), 1 << 63)];
        let out = FedAvg.aggregate(&global, &updates).unwrap();
        assert_eq!(out.get("w").unwrap().values, vec![2.0, 3.0]);
        let updates = [(one([1.0, 2.0]), u64::MAX - 46), (one([3.0, 4.0]), 48)];
        let out = FedAvg.aggregate(&global, &updates).unwrap();
        assert!(out.get("w").unwrap().values.iter().all(|v| v.is_finite()));
    }

    #[test]
    fn fedavg_refuses_empty_zero_and_mismatched() {
        let global = one([0.0, 0.0]);
        assert_eq!(FedAvg.aggregate(&global, &[]), Err(AggregateError::NoUpdates));
        assert_eq!(FedAvg.aggregate(&global, &[(one([1.0, 1.0]), 0)]), Err(AggregateError::ZeroExamples));
        let mut other = NamedTensors::new();
        other.insert("v", vec![2], vec![0.0, 0.0]).unwrap();
        assert!(matches!(
            FedAvg.aggregate(&global, &[(one([1.0, 1.0]), 1), (other, 1)]),
            Err(AggregateError::Mismatch { index: 1, .. })
        ));
    }
}
