//! SCAFFOLD (Karimireddy et al., "SCAFFOLD: Stochastic Controlled Averaging for Federated Learning", ICML 2020,
//! Algorithm 1, option II). The server keeps a control variate `c` and one per client, `c_i`, by the client's shard
//! (so a volunteer who reloads the page finds its own again); client i adds `c - c_i` to the direction of every
//! local step, which cancels its drift towards its own data's optimum. With `x` the global model, `y_i` client i's
//! trained model and `s_i` the sum of the learning rates of its round's steps, option II's new variate
//! `c_i+ = c_i - c + (x - y_i) / s_i` is computed here from the update itself, so only the model travels up (the
//! paper's clients also send `c_i+ - c_i`). Then, unweighted as in the paper,
//! `x += server_lr * mean_i (y_i - x)` and `c += |S| / N * mean_i (c_i+ - c_i)` over the round's clients `S` of `N`.
//! With an adaptive local optimizer (AdamW here) a step's direction is the optimizer's step per unit of learning
//! rate; `(x - y_i) / s_i` is then the mean corrected direction, exactly as with SGD, and the variates are in
//! those units.

use std::collections::BTreeMap;
use std::sync::Arc;

use super::exact::{ExactSum, in_range, out_of_range};
use super::interface::{Aggregation, Contribution, Step, Strategy};
use crate::error::AggregateError;
use crate::protocol::StrategyParams;
use crate::tensors::NamedTensors;

/// Where one server-wide set of tensors and one set per client live among named tensors: `<server><tensor>` and
/// `<client><client id>/<tensor>`.
#[derive(Clone, Copy)]
struct Layout {
    server: &'static str,
    client: &'static str,
}

/// The saved state: `c` and each client's `c_i`.
const STATE: Layout = Layout { server: "c/", client: "client/" };
/// Reserved names in the aggregate, from the round to [`Strategy::step`]: the mean of `c_i+ - c_i`, and each
/// client's new variate.
const ROUND: Layout = Layout { server: "scaffold/dc/", client: "scaffold/client/" };

impl Layout {
    /// Writes `server` and `clients` into `out`.
    fn pack<'a>(
        self,
        out: &mut NamedTensors,
        server: &NamedTensors,
        clients: impl IntoIterator<Item = (u64, &'a NamedTensors)>,
    ) {
        for (name, t) in server.iter() {
            out.insert(format!("{}{name}", self.server), t.shape.clone(), t.values.clone()).expect("a tensor's shape");
        }
        for (client, tensors) in clients {
            for (name, t) in tensors.iter() {
                let key = format!("{}{client}/{name}", self.client);
                out.insert(key, t.shape.clone(), t.values.clone()).expect("a tensor's shape");
            }
        }
    }

    /// What [`Layout::pack`] wrote into `tensors` (other names are left alone).
    fn unpack(self, tensors: &NamedTensors) -> (NamedTensors, BTreeMap<u64, NamedTensors>) {
        let mut server = NamedTensors::new();
        let mut clients: BTreeMap<u64, NamedTensors> = BTreeMap::new();
        for (name, t) in tensors.iter() {
            let (into, tensor) = if let Some(tensor) = name.strip_prefix(self.server) {
                (&mut server, tensor)
            } else if let Some((client, tensor)) = name.strip_prefix(self.client).and_then(split_client) {
                (clients.entry(client).or_default(), tensor)
            } else {
                continue;
            };
            into.insert(tensor, t.shape.clone(), t.values.clone()).expect("a tensor's shape");
        }
        (server, clients)
    }
}

pub struct Scaffold {
    pub server_lr: f64,
    /// `N`, the federation's clients: a round of `|S|` of them moves `c` by `|S| / N` of their mean change.
    pub clients: usize,
    /// `c`; empty (zeros) until a round has been committed.
    control: Arc<NamedTensors>,
    variates: BTreeMap<u64, Arc<NamedTensors>>,
}

impl Scaffold {
    pub fn new(server_lr: f64, clients: usize) -> Self {
        Self { server_lr, clients: clients.max(1), control: Arc::default(), variates: BTreeMap::new() }
    }
}

impl Strategy for Scaffold {
    fn client_params(&self) -> StrategyParams {
        StrategyParams { control_variates: true, ..StrategyParams::plain("scaffold") }
    }

    fn begin(&self, global: &NamedTensors) -> Box<dyn Aggregation> {
        let len = global.iter().map(|(_, t)| t.values.len()).sum();
        Box::new(ScaffoldRound {
            global: global.clone(),
            control: Arc::clone(&self.control),
            variates: self.variates.clone(),
            sum_models: ExactSum::zeros(len),
            sum_variate_change: ExactSum::zeros(len),
            new_variates: Vec::new(),
        })
    }

    fn step(&self, global: &NamedTensors, aggregate: NamedTensors) -> Result<Step, AggregateError> {
        let (mean_variate_change, new_variates) = ROUND.unpack(&aggregate);
        let mut next = NamedTensors::new();
        let mut control = NamedTensors::new();
        let share = new_variates.len() as f64 / self.clients.max(new_variates.len()) as f64;
        for (name, x) in global.iter() {
            let mean = &aggregate.get(name).expect("the round's mean of the global model's tensors").values;
            let moved = x
                .values
                .iter()
                .zip(mean)
                .map(|(&x, &y)| (f64::from(x) + self.server_lr * (f64::from(y) - f64::from(x))) as f32);
            next.insert(name, x.shape.clone(), moved.collect()).expect("global shape");
            let dc = &mean_variate_change.get(name).expect("the round's mean variate change").values;
            let c = self.control.get(name).map(|t| t.values.as_slice());
            let c_next = (0..dc.len()).map(|k| (c.map_or(0.0, |c| f64::from(c[k])) + share * f64::from(dc[k])) as f32);
            control.insert(name, x.shape.clone(), c_next.collect()).expect("global shape");
        }
        let mut variates: BTreeMap<u64, &NamedTensors> =
            self.variates.iter().map(|(&client, v)| (client, v.as_ref())).collect();
        variates.extend(new_variates.iter().map(|(&client, v)| (client, v)));
        let mut state = NamedTensors::new();
        STATE.pack(&mut state, &control, variates);
        Ok(Step { global: next, state })
    }

    fn commit(&mut self, state: NamedTensors) {
        let (control, variates) = STATE.unpack(&state);
        self.control = Arc::new(control);
        self.variates = variates.into_iter().map(|(client, v)| (client, Arc::new(v))).collect();
    }

    fn state(&self) -> NamedTensors {
        let mut state = NamedTensors::new();
        STATE.pack(&mut state, &self.control, self.variates.iter().map(|(&client, v)| (client, v.as_ref())));
        state
    }

    /// `c - c_i`, a missing variate counting as zeros; empty while both are.
    fn client_correction(&self, client: u64) -> Option<NamedTensors> {
        let own = self.variates.get(&client);
        let shapes = if self.control.is_empty() { own.map(Arc::as_ref) } else { Some(self.control.as_ref()) };
        let Some(shapes) = shapes else { return Some(NamedTensors::new()) };
        let mut correction = NamedTensors::new();
        for (name, t) in shapes.iter() {
            let c = self.control.get(name).map(|t| t.values.as_slice());
            let c_i = own.and_then(|v| v.get(name)).map(|t| t.values.as_slice());
            let values = (0..t.values.len()).map(|k| c.map_or(0.0, |c| c[k]) - c_i.map_or(0.0, |c_i| c_i[k])).collect();
            correction.insert(name, t.shape.clone(), values).expect("a tensor's shape");
        }
        Some(correction)
    }
}

/// `"<client>/<tensor>"` into its parts.
fn split_client(name: &str) -> Option<(u64, &str)> {
    let (client, tensor) = name.split_once('/')?;
    Some((client.parse().ok()?, tensor))
}

/// The round's exact running sums ([`super::exact`], in the global model's order) of `y_i` and of `c_i+ - c_i`,
/// and each client's new variate (the state SCAFFOLD keeps per client anyway).
struct ScaffoldRound {
    global: NamedTensors,
    control: Arc<NamedTensors>,
    variates: BTreeMap<u64, Arc<NamedTensors>>,
    sum_models: ExactSum,
    sum_variate_change: ExactSum,
    new_variates: Vec<(u64, NamedTensors)>,
}

impl Aggregation for ScaffoldRound {
    fn fold(&mut self, update: Contribution<'_>) -> Result<(), AggregateError> {
        let index = self.new_variates.len();
        update.tensors.validate(&self.global.spec()).map_err(|source| AggregateError::Mismatch { index, source })?;
        let unknown = |what| AggregateError::Unknown { index, rule: "scaffold", what };
        let client = update.client.ok_or_else(|| unknown("the client it came from"))?;
        let lr_sum =
            update.lr_sum.filter(|s| s.is_finite() && *s > 0.0).ok_or_else(|| unknown("its learning rates"))?;
        let Self { global, control, variates, sum_models, sum_variate_change, new_variates } = self;
        let (global, control, own) = (&*global, control.as_ref(), variates.get(&client));
        // Per tensor: x, y_i, and `c_i+ - c_i = (x - y_i) / s_i - c` per value.
        let tensors = || {
            global.iter().map(move |(name, x)| {
                let y = &update.tensors.get(name).expect("validated against the global spec").values;
                let c = control.get(name).map(|t| t.values.as_slice());
                let variate_change = move |k: usize| {
                    (f64::from(x.values[k]) - f64::from(y[k])) / lr_sum - c.map_or(0.0, |c| f64::from(c[k]))
                };
                (name, x, y, variate_change)
            })
        };
        // Every value checked before any is added, so a refused update leaves the sums as they were.
        for (_, x, y, variate_change) in tensors() {
            in_range(y.iter().map(|&v| f64::from(v))).map_err(out_of_range(index))?;
            in_range((0..x.values.len()).map(variate_change)).map_err(out_of_range(index))?;
        }
        let mut variate = NamedTensors::new();
        let mut offset = 0;
        for (name, x, y, variate_change) in tensors() {
            let n = x.values.len();
            sum_models.add(offset, 1, || y.iter().map(|&v| f64::from(v))).map_err(out_of_range(index))?;
            sum_variate_change.add(offset, 1, || (0..n).map(variate_change)).map_err(out_of_range(index))?;
            let c_i = own.and_then(|v| v.get(name)).map(|t| t.values.as_slice());
            let new = (0..n).map(|k| (c_i.map_or(0.0, |c_i| f64::from(c_i[k])) + variate_change(k)) as f32);
            variate.insert(name, x.shape.clone(), new.collect()).expect("global shape");
            offset += n;
        }
        new_variates.push((client, variate));
        Ok(())
    }

    fn finish(self: Box<Self>) -> Result<NamedTensors, AggregateError> {
        let n = self.new_variates.len();
        if n == 0 {
            return Err(AggregateError::NoUpdates);
        }
        let (mut out, mut mean_variate_change) = (NamedTensors::new(), NamedTensors::new());
        let mut means = self.sum_models.divided_by(n as f64)?;
        let mut changes = self.sum_variate_change.divided_by(n as f64)?;
        for (name, x) in self.global.iter() {
            let len = x.values.len();
            out.insert(name, x.shape.clone(), means.by_ref().take(len).map(|m| m as f32).collect())
                .expect("global shape");
            let dc = changes.by_ref().take(len).map(|d| d as f32).collect();
            mean_variate_change.insert(name, x.shape.clone(), dc).expect("global shape");
        }
        // In the order of the clients, not of their arrival: the state saved is the same either way.
        let mut new_variates = self.new_variates;
        new_variates.sort_by_key(|(client, _)| *client);
        ROUND.pack(&mut out, &mean_variate_change, new_variates.iter().map(|(client, v)| (*client, v)));
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::strategy::interface::{aggregate, one};

    fn round(strategy: &mut Scaffold, global: [f32; 2], updates: &[(u64, [f32; 2], f64)]) -> Vec<f32> {
        let tensors: Vec<NamedTensors> = updates.iter().map(|(_, y, _)| one(*y)).collect();
        let contributions = tensors.iter().zip(updates).map(|(tensors, (client, _, lr_sum))| Contribution {
            client: Some(*client),
            lr_sum: Some(*lr_sum),
            ..(tensors, 1).into()
        });
        let step = aggregate(strategy, &one(global), contributions).unwrap();
        strategy.commit(step.state);
        step.global.get("w").unwrap().values.clone()
    }

    fn correction(strategy: &Scaffold, client: u64) -> Vec<f32> {
        strategy.client_correction(client).unwrap().get("w").unwrap().values.clone()
    }

    #[test]
    fn option_two_variates_and_the_server_steps_by_hand() {
        let mut scaffold = Scaffold::new(1.0, 2);
        assert!(scaffold.client_correction(10).unwrap().is_empty(), "no correction before the first round");
        // Round 1, x = 0, c = c_i = 0. Client 10: y = (-1, 0), s = 0.5: (x - y) / s = (2, 0) = c_10.
        // Client 20: y = (0, -2), s = 0.5: c_20 = (0, 4). x' = mean y = (-0.5, -1); c' = 2/2 * mean = (1, 2).
        let x = round(&mut scaffold, [0.0, 0.0], &[(10, [-1.0, 0.0], 0.5), (20, [0.0, -2.0], 0.5)]);
        assert_eq!(x, vec![-0.5, -1.0]);
        assert_eq!(correction(&scaffold, 10), vec![-1.0, 2.0], "c - c_10");
        assert_eq!(correction(&scaffold, 20), vec![1.0, -2.0], "c - c_20");
        assert_eq!(correction(&scaffold, 30), vec![1.0, 2.0], "a client not seen yet: c");
        // Round 2, client 10 alone (|S| = 1 of N = 2): y = (-1.5, -1), s = 1: (x - y) / s = (1, 0);
        // c_10+ = c_10 - c + (1, 0) = (2, 0) - (1, 2) + (1, 0) = (2, -2); c' = c + 1/2 (c_10+ - c_10) = (1, 1);
        // x' = y at server-lr 1. c stays the mean of the variates: ((2, -2) + (0, 4)) / 2.
        let x = round(&mut scaffold, [-0.5, -1.0], &[(10, [-1.5, -1.0], 1.0)]);
        assert_eq!(x, vec![-1.5, -1.0]);
        assert_eq!(correction(&scaffold, 10), vec![-1.0, 3.0], "(1, 1) - (2, -2)");
        assert_eq!(correction(&scaffold, 20), vec![1.0, -3.0], "(1, 1) - (0, 4), kept through its absence");
    }

    #[test]
    fn the_server_learning_rate_scales_the_mean_change_and_state_survives_a_restart() {
        let mut scaffold = Scaffold::new(0.5, 2);
        let x = round(&mut scaffold, [0.0, 0.0], &[(10, [-1.0, 0.0], 0.5), (20, [0.0, -2.0], 0.5)]);
        assert_eq!(x, vec![-0.25, -0.5]);
        let mut restarted = Scaffold::new(0.5, 2);
        restarted.commit(scaffold.state());
        for client in [10, 20, 30] {
            assert_eq!(correction(&restarted, client), correction(&scaffold, client));
        }
    }

    #[test]
    fn an_update_of_an_unknown_client_or_without_learning_rates_is_refused_by_index() {
        let scaffold = Scaffold::new(1.0, 2);
        let (a, b) = (one([1.0, 0.0]), one([0.0, 1.0]));
        let known = Contribution { client: Some(1), lr_sum: Some(1.0), ..(&a, 1).into() };
        let err = aggregate(&scaffold, &one([0.0, 0.0]), [known, (&b, 1).into()]).unwrap_err();
        assert!(matches!(err, AggregateError::Unknown { index: 1, rule: "scaffold", .. }), "{err:?}");
        let no_rates = Contribution { lr_sum: Some(0.0), ..known };
        let err = aggregate(&scaffold, &one([0.0, 0.0]), [no_rates]).unwrap_err();
        assert!(matches!(err, AggregateError::Unknown { index: 0, .. }), "{err:?}");
    }
}
