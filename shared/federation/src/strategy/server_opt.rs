//! Server optimizers: the round's example-weighted mean of the clients' models is turned into a pseudo-gradient
//! `delta = mean - global` and applied with the server's own optimizer, whose moments persist from round to round
//! (the strategy state saved with each round). FedAvgM is Hsu et al. 2019; FedAdagrad, FedYogi and FedAdam are
//! Algorithm 2 of Reddi et al., "Adaptive Federated Optimization", ICLR 2021 (no bias correction, `v` starting at
//! `tau^2`, as written there).

use super::interface::{Aggregation, Step, Strategy};
use super::mean::WeightedMean;
use crate::error::AggregateError;
use crate::protocol::StrategyParams;
use crate::tensors::NamedTensors;

/// FedAvgM: `v = momentum * v + delta; x = x + lr * v` (with momentum 0 and lr 1, FedAvg).
#[derive(Debug, Clone)]
pub struct FedAvgM {
    pub server_lr: f64,
    pub momentum: f64,
    velocity: NamedTensors,
}

impl FedAvgM {
    pub fn new(server_lr: f64, momentum: f64) -> Self {
        Self { server_lr, momentum, velocity: NamedTensors::new() }
    }
}

/// The adaptive rule of [`FedAdaptive`]'s second moment.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Adaptivity {
    /// `v = v + delta^2`.
    Adagrad,
    /// `v = v - (1 - beta2) * delta^2 * sign(v - delta^2)`.
    Yogi,
    /// `v = beta2 * v + (1 - beta2) * delta^2`.
    Adam,
}

/// FedAdagrad, FedYogi or FedAdam: `m = beta1 * m + (1 - beta1) * delta`, `v` by its rule,
/// `x = x + lr * m / (sqrt(v) + tau)`.
#[derive(Debug, Clone)]
pub struct FedAdaptive {
    pub rule: Adaptivity,
    pub server_lr: f64,
    pub beta1: f64,
    pub beta2: f64,
    pub tau: f64,
    /// `m/<name>` and `v/<name>` per tensor, once a round has been committed.
    moments: NamedTensors,
}

impl FedAdaptive {
    pub fn new(rule: Adaptivity, server_lr: f64, beta1: f64, beta2: f64, tau: f64) -> Self {
        Self { rule, server_lr, beta1, beta2, tau, moments: NamedTensors::new() }
    }

    fn name(&self) -> &'static str {
        match self.rule {
            Adaptivity::Adagrad => "fedadagrad",
            Adaptivity::Yogi => "fedyogi",
            Adaptivity::Adam => "fedadam",
        }
    }
}

/// `state`'s tensor `key`, or `fill` of `global`'s tensor `name`'s length when the state has none yet.
fn moment(state: &NamedTensors, key: &str, len: usize, fill: f64) -> Vec<f64> {
    state.get(key).map_or_else(|| vec![fill; len], |t| t.values.iter().map(|&v| f64::from(v)).collect())
}

impl Strategy for FedAvgM {
    fn client_params(&self) -> StrategyParams {
        StrategyParams::plain("fedavgm")
    }

    fn begin(&self, global: &NamedTensors) -> Box<dyn Aggregation> {
        Box::new(WeightedMean::new(global))
    }

    fn step(&self, global: &NamedTensors, aggregate: NamedTensors) -> Result<Step, AggregateError> {
        let (mut next, mut state) = (NamedTensors::new(), NamedTensors::new());
        for (name, x) in global.iter() {
            let mean = &aggregate.get(name).expect("the aggregate has the global model's tensors").values;
            let mut v = moment(&self.velocity, name, x.values.len(), 0.0);
            let mut out = Vec::with_capacity(v.len());
            for ((v, &x), &mean) in v.iter_mut().zip(&x.values).zip(mean) {
                *v = self.momentum * *v + (f64::from(mean) - f64::from(x));
                out.push((f64::from(x) + self.server_lr * *v) as f32);
            }
            next.insert(name, x.shape.clone(), out).expect("global shape");
            state.insert(name, x.shape.clone(), v.into_iter().map(|v| v as f32).collect()).expect("global shape");
        }
        Ok(Step { global: next, state })
    }

    fn commit(&mut self, state: NamedTensors) {
        self.velocity = state;
    }

    fn state(&self) -> NamedTensors {
        self.velocity.clone()
    }
}

impl Strategy for FedAdaptive {
    fn client_params(&self) -> StrategyParams {
        StrategyParams::plain(self.name())
    }

    fn begin(&self, global: &NamedTensors) -> Box<dyn Aggregation> {
        Box::new(WeightedMean::new(global))
    }

    fn step(&self, global: &NamedTensors, aggregate: NamedTensors) -> Result<Step, AggregateError> {
        let (mut next, mut state) = (NamedTensors::new(), NamedTensors::new());
        let (b1, b2, tau) = (self.beta1, self.beta2, self.tau);
        for (name, x) in global.iter() {
            let mean = &aggregate.get(name).expect("the aggregate has the global model's tensors").values;
            let n = x.values.len();
            let mut m = moment(&self.moments, &format!("m/{name}"), n, 0.0);
            let mut v = moment(&self.moments, &format!("v/{name}"), n, tau * tau);
            let mut out = Vec::with_capacity(n);
            for (i, (&x, &mean)) in x.values.iter().zip(mean).enumerate() {
                let delta = f64::from(mean) - f64::from(x);
                let d2 = delta * delta;
                m[i] = b1 * m[i] + (1.0 - b1) * delta;
                v[i] = match self.rule {
                    Adaptivity::Adagrad => v[i] + d2,
                    Adaptivity::Yogi => v[i] - (1.0 - b2) * d2 * (v[i] - d2).signum(),
                    Adaptivity::Adam => b2 * v[i] + (1.0 - b2) * d2,
                };
                out.push((f64::from(x) + self.server_lr * m[i] / (v[i].sqrt() + tau)) as f32);
            }
            next.insert(name, x.shape.clone(), out).expect("global shape");
            let f32s = |values: Vec<f64>| values.into_iter().map(|v| v as f32).collect();
            state.insert(format!("m/{name}"), x.shape.clone(), f32s(m)).expect("global shape");
            state.insert(format!("v/{name}"), x.shape.clone(), f32s(v)).expect("global shape");
        }
        Ok(Step { global: next, state })
    }

    fn commit(&mut self, state: NamedTensors) {
        self.moments = state;
    }

    fn state(&self) -> NamedTensors {
        self.moments.clone()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::strategy::interface::{aggregate, one};

    /// Two rounds of `strategy`, committing in between: the two globals.
    fn two_rounds(strategy: &mut dyn Strategy, rounds: [[(NamedTensors, u64); 2]; 2]) -> [Vec<f32>; 2] {
        let mut global = one([1.0, -1.0]);
        let mut out = Vec::new();
        for updates in &rounds {
            let step = aggregate(strategy, &global, updates.iter().map(|(t, n)| (t, *n))).unwrap();
            strategy.commit(step.state);
            global = step.global;
            out.push(global.get("w").unwrap().values.clone());
        }
        [out[0].clone(), out[1].clone()]
    }

    fn close(got: &[f32], want: &[f64]) {
        for (g, w) in got.iter().zip(want) {
            assert!((f64::from(*g) - w).abs() < 1e-5, "{got:?} != {want:?}");
        }
    }

    // Round 1: mean of [3, 1] (x1) and [1, -3] (x1) = [2, -1], delta = [1, 0]. Round 2 from the new global.

    #[test]
    fn fedavgm_by_hand() {
        let mut s = FedAvgM::new(0.5, 0.9);
        let [r1, r2] = two_rounds(
            &mut s,
            [[(one([3.0, 1.0]), 1), (one([1.0, -3.0]), 1)], [(one([2.5, -1.0]), 1), (one([1.5, -1.0]), 1)]],
        );
        // v = [1, 0]; x = [1, -1] + 0.5 * [1, 0] = [1.5, -1].
        close(&r1, &[1.5, -1.0]);
        // mean [2, -1], delta [0.5, 0]; v = 0.9 * [1, 0] + [0.5, 0] = [1.4, 0]; x = [1.5 + 0.7, -1].
        close(&r2, &[2.2, -1.0]);
        assert_eq!(s.state().get("w").unwrap().values, vec![1.4, 0.0]);
    }

    #[test]
    fn fedadam_fedyogi_fedadagrad_by_hand() {
        let rounds = || [[(one([3.0, 1.0]), 1), (one([1.0, -3.0]), 1)], [(one([3.0, 0.0]), 1), (one([3.0, -2.0]), 1)]];
        let (lr, b1, b2, tau) = (0.1, 0.9, 0.99, 1e-3);
        // Round 1: delta = [1, 0]; m = [0.1, 0]. v0 = tau^2 = 1e-6.
        let m1 = 0.1;
        let x1 = |v: f64| 1.0 + lr * m1 / (v.sqrt() + tau);
        // Round 2: global [x1, -1], mean [3, -1], delta [3 - x1, 0]; m = 0.9 * 0.1 + 0.1 * d.
        let second = |x1: f64, v1: f64, rule: Adaptivity| {
            let d = 3.0 - x1;
            let m = b1 * m1 + (1.0 - b1) * d;
            let v = match rule {
                Adaptivity::Adagrad => v1 + d * d,
                Adaptivity::Yogi => v1 - (1.0 - b2) * d * d * (v1 - d * d).signum(),
                Adaptivity::Adam => b2 * v1 + (1.0 - b2) * d * d,
            };
            x1 + lr * m / (v.sqrt() + tau)
        };
        for (rule, v1) in [
            (Adaptivity::Adagrad, 1e-6 + 1.0),
            (Adaptivity::Yogi, 1e-6 - 0.01 * (1e-6f64 - 1.0).signum()),
            (Adaptivity::Adam, 0.99 * 1e-6 + 0.01),
        ] {
            let mut s = FedAdaptive::new(rule, lr, b1, b2, tau);
            let [r1, r2] = two_rounds(&mut s, rounds());
            close(&r1, &[x1(v1), -1.0]);
            // The second coordinate never moves: delta 0 there in both rounds, so m stays 0.
            close(&r2, &[second(f64::from(r1[0]), v1, rule), -1.0]);
        }
    }

    #[test]
    fn an_uncommitted_step_leaves_the_moments_as_they_were() {
        let s = FedAdaptive::new(Adaptivity::Adam, 0.1, 0.9, 0.99, 1e-3);
        let global = one([0.0, 0.0]);
        let update = one([1.0, 1.0]);
        let a = aggregate(&s, &global, [(&update, 1)]).unwrap();
        let b = aggregate(&s, &global, [(&update, 1)]).unwrap();
        assert_eq!(a, b, "retrying a round gives the same step");
        assert!(s.state().is_empty());
    }
}
