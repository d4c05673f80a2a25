//! q-FedAvg (Li et al., "Fair Resource Allocation in Federated Learning", ICLR 2020, Algorithm 2): the round's
//! step weighs each client by its loss to the power `q`, so the clients the global model serves worst pull hardest
//! (`q = 0`: the unweighted mean of the clients' models). With `L = 1/lr` the estimate of the loss's Lipschitz
//! constant and `F_k` client k's loss,
//! `dw_k = L (w - w_k)`, `D_k = F_k^q dw_k`, `h_k = q F_k^(q-1) ||dw_k||^2 + L F_k^q`, `w' = w - sum D_k / sum h_k`.
//! As in Flower's QFedAvg, `F_k` is the loss the client reports with its update (here the mean loss of its local
//! steps, not a second pass over its shard) plus 1e-10; example counts play no part.

use super::exact::{ExactSum, out_of_range};
use super::interface::{Aggregation, Contribution, Strategy};
use crate::error::AggregateError;
use crate::protocol::StrategyParams;
use crate::tensors::NamedTensors;

#[derive(Debug, Clone, Copy)]
pub struct QFedAvg {
    pub q: f64,
    /// The paper's step size, `1/L`.
    pub lr: f64,
}

impl Strategy for QFedAvg {
    fn client_params(&self) -> StrategyParams {
        StrategyParams::plain("qfedavg")
    }

    fn begin(&self, global: &NamedTensors) -> Box<dyn Aggregation> {
        let len = global.iter().map(|(_, t)| t.values.len()).sum();
        Box::new(QFairRound { rule: *self, global: global.clone(), steps: ExactSum::zeros(len), h: Vec::new() })
    }
}

/// The exact running sum of `D_k` ([`super::exact`], in the global model's order), and each `h_k`, summed in
/// ascending order at the end: the step is the same in any arrival order.
struct QFairRound {
    rule: QFedAvg,
    global: NamedTensors,
    steps: ExactSum,
    h: Vec<f64>,
}

impl Aggregation for QFairRound {
    fn fold(&mut self, update: Contribution<'_>) -> Result<(), AggregateError> {
        let index = self.h.len();
        update.tensors.validate(&self.global.spec()).map_err(|source| AggregateError::Mismatch { index, source })?;
        let loss = match update.train_loss {
            Some(loss) if loss.is_finite() && loss >= 0.0 => loss + 1e-10,
            loss => return Err(AggregateError::Loss { index, rule: "qfedavg", loss }),
        };
        let QFedAvg { q, lr } = self.rule;
        let lipschitz = 1.0 / lr;
        let weight = loss.powf(q);
        let global = &self.global;
        let dw = || {
            global.iter().flat_map(move |(name, global)| {
                let local = &update.tensors.get(name).expect("validated against the global spec").values;
                global.values.iter().zip(local).map(move |(&w, &w_k)| lipschitz * (f64::from(w) - f64::from(w_k)))
            })
        };
        let norm_sq: f64 = dw().map(|d| d * d).sum();
        self.steps.add(0, 1, || dw().map(|d| weight * d)).map_err(out_of_range(index))?;
        self.h.push(q * loss.powf(q - 1.0) * norm_sq + lipschitz * weight);
        Ok(())
    }

    fn finish(self: Box<Self>) -> Result<NamedTensors, AggregateError> {
        if self.h.is_empty() {
            return Err(AggregateError::NoUpdates);
        }
        let mut h = self.h;
        h.sort_by(f64::total_cmp);
        let h_sum: f64 = h.iter().sum();
        let mut steps = self.steps.divided_by(h_sum)?;
        let mut out = NamedTensors::new();
        for (name, global) in self.global.iter() {
            let values = global.values.iter().zip(steps.by_ref()).map(|(&w, s)| (f64::from(w) - s) as f32).collect();
            out.insert(name, global.shape.clone(), values).expect("shape taken from the global model");
        }
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::strategy::interface::{aggregate, one};

    fn qfedavg(q: f64, lr: f64, global: [f32; 2], updates: &[([f32; 2], f64)]) -> Result<Vec<f32>, AggregateError> {
        let tensors: Vec<NamedTensors> = updates.iter().map(|(u, _)| one(*u)).collect();
        let contributions = tensors
            .iter()
            .zip(updates)
            .map(|(tensors, (_, loss))| Contribution { train_loss: Some(*loss), ..(tensors, 1).into() });
        aggregate(&QFedAvg { q, lr }, &one(global), contributions).map(|s| s.global.get("w").unwrap().values.clone())
    }

    #[test]
    fn q_zero_is_the_unweighted_mean_of_the_clients_models() {
        // h_k = L for every k, so w' = w - sum L (w - w_k) / (n L) = mean w_k, whatever the losses and examples.
        let out = qfedavg(0.0, 0.1, [1.0, 1.0], &[([3.0, 0.0], 0.5), ([0.0, 4.0], 2.0)]).unwrap();
        assert_eq!(out, vec![1.5, 2.0]);
    }

    #[test]
    fn the_client_with_the_higher_loss_pulls_harder() {
        // q = 1, lr = 0.5 (L = 2), w = (0, 0); client 1: w_1 = (1, 0), F = 1; client 2: w_2 = (0, 1), F = 3.
        // dw_1 = (-2, 0), dw_2 = (0, -2); D = 1 dw_1 + 3 dw_2 = (-2, -6);
        // h_k = q F^(q-1) ||dw||^2 + L F^q: h_1 = 4 + 2 = 6, h_2 = 4 + 6 = 10.
        // w' = -(-2, -6) / 16 = (0.125, 0.375).
        let out = qfedavg(1.0, 0.5, [0.0, 0.0], &[([1.0, 0.0], 1.0), ([0.0, 1.0], 3.0)]).unwrap();
        let expected = [0.125, 0.375];
        for (o, e) in out.iter().zip(expected) {
            assert!((o - e).abs() < 1e-6, "{out:?} != {expected:?}");
        }
    }

    #[test]
    fn an_update_without_a_usable_loss_is_refused_by_index() {
        for loss in [f64::NAN, -1.0] {
            let err = qfedavg(0.2, 0.1, [0.0, 0.0], &[([1.0, 0.0], 1.0), ([0.0, 1.0], loss)]).unwrap_err();
            assert!(matches!(err, AggregateError::Loss { index: 1, rule: "qfedavg", .. }), "{err:?}");
        }
        let err = aggregate(&QFedAvg { q: 0.2, lr: 0.1 }, &one([0.0, 0.0]), [(&one([1.0, 0.0]), 1)]).unwrap_err();
        assert!(matches!(err, AggregateError::Loss { index: 0, loss: None, .. }), "{err:?}");
    }
}
