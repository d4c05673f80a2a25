//! Robust rules: statistics of the round's client models that a few wild updates cannot drag far. FedMedian is
//! Yin et al. 2018's coordinate-wise median; FedTrimmedAvg drops the `beta` fraction of largest and of smallest
//! values of every coordinate and averages the rest (Yin et al. 2018's trimmed mean); both are unweighted.
//! Krum (Blanchard et al. 2017) picks the update closest to its `n - f - 2` nearest neighbours, Multi-Krum
//! averages the `keep` best by that score (example-weighted, as Flower's). Bulyan (El Mhamdi et al. 2018) picks
//! `n - 2f` updates by Krum one at a time, then averages, per coordinate, the `n - 4f` picked values nearest
//! their median, so an attacker can neither win Krum's vote nor pull single coordinates. All need every update of
//! the round at once, so they buffer them: memory of one model per update, bounded by the clients the round
//! sampled (the server takes one update from each), where the streaming rules keep one sum. They decide on the
//! updates in a canonical order (by client, then by value), so their aggregate, ties included, does not depend on
//! the order the updates arrived in.

use super::interface::{Aggregation, Contribution, Strategy};
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

/// Krum (`keep` = 1) or Multi-Krum, tolerating `f` Byzantine clients; needs `n >= 2f + 3` updates a round.
#[derive(Debug, Clone, Copy)]
pub struct Krum {
    pub f: usize,
    pub keep: usize,
}

impl Krum {
    /// Updates a round needs for `f` tolerated attackers.
    pub fn min_updates(f: usize) -> usize {
        2 * f + 3
    }
}

/// Bulyan over Krum, tolerating `f` Byzantine clients; needs `n >= 4f + 3` updates a round.
#[derive(Debug, Clone, Copy)]
pub struct Bulyan {
    pub f: usize,
}

impl Bulyan {
    /// Updates a round needs for `f` tolerated attackers.
    pub fn min_updates(f: usize) -> usize {
        4 * f + 3
    }
}

impl Strategy for Bulyan {
    fn client_params(&self) -> StrategyParams {
        StrategyParams::plain("bulyan")
    }

    fn begin(&self, global: &NamedTensors) -> Box<dyn Aggregation> {
        Box::new(Buffered::new(global, Rule::Bulyan(*self)))
    }
}

impl Strategy for Krum {
    fn client_params(&self) -> StrategyParams {
        let name = if self.keep == 1 { "krum" } else { "multi-krum" };
        StrategyParams::plain(name)
    }

    fn begin(&self, global: &NamedTensors) -> Box<dyn Aggregation> {
        Box::new(Buffered::new(global, Rule::Krum(*self)))
    }
}

impl Strategy for FedMedian {
    fn client_params(&self) -> StrategyParams {
        StrategyParams::plain("median")
    }

    fn begin(&self, global: &NamedTensors) -> Box<dyn Aggregation> {
        Box::new(Buffered::new(global, Rule::Coordinate(Statistic::Median)))
    }
}

impl Strategy for FedTrimmedAvg {
    fn client_params(&self) -> StrategyParams {
        StrategyParams::plain("trimmed-mean")
    }

    fn begin(&self, global: &NamedTensors) -> Box<dyn Aggregation> {
        Box::new(Buffered::new(global, Rule::Coordinate(Statistic::TrimmedMean(self.beta))))
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

#[derive(Debug, Clone, Copy)]
enum Rule {
    Coordinate(Statistic),
    Krum(Krum),
    Bulyan(Bulyan),
}

/// The squared Euclidean distance between every two of `flat`, computed once for every round of Krum.
fn squared_distances(flat: &[Vec<f32>]) -> Vec<Vec<f64>> {
    let n = flat.len();
    let mut d = vec![vec![0.0; n]; n];
    for i in 0..n {
        for j in i + 1..n {
            let dij = flat[i].iter().zip(&flat[j]).map(|(x, y)| (f64::from(*x) - f64::from(*y)).powi(2)).sum::<f64>();
            (d[i][j], d[j][i]) = (dij, dij);
        }
    }
    d
}

/// Krum's score of each of `candidates`: the sum of its squared distances to its `len - f - 2` nearest other
/// candidates (at least the nearest one, as Flower's Bulyan scores its last few candidates).
fn krum_scores(distances: &[Vec<f64>], candidates: &[usize], f: usize) -> Vec<f64> {
    let n = candidates.len();
    let closest = n.saturating_sub(f + 2).max(1).min(n - 1);
    candidates
        .iter()
        .map(|&i| {
            let mut d: Vec<f64> = candidates.iter().filter(|&&j| j != i).map(|&j| distances[i][j]).collect();
            d.sort_unstable_by(f64::total_cmp);
            d[..closest].iter().sum()
        })
        .collect()
}

/// A round's updates (with their weights and, when known, their clients), kept whole until the round closes.
struct Buffered {
    global: NamedTensors,
    spec: TensorSpec,
    rule: Rule,
    updates: Vec<(NamedTensors, u64)>,
    clients: Vec<Option<u64>>,
}

impl Buffered {
    fn new(global: &NamedTensors, rule: Rule) -> Self {
        Self { global: global.clone(), spec: global.spec(), rule, updates: Vec::new(), clients: Vec::new() }
    }

    /// The updates in the canonical order: by client, then by their values (then weights) as the global model lists
    /// them.
    fn into_canonical_order(self) -> Self {
        let Self { global, spec, rule, updates, clients } = self;
        let values = |u: &NamedTensors| -> Vec<f32> {
            global.iter().flat_map(|(name, _)| u.get(name).expect("validated").values.iter().copied()).collect()
        };
        let mut keyed: Vec<_> =
            updates.into_iter().zip(clients).map(|((u, examples), client)| (client, values(&u), examples, u)).collect();
        keyed.sort_by(|a, b| {
            let by_value = || a.1.iter().zip(&b.1).map(|(x, y)| x.total_cmp(y)).find(|o| o.is_ne());
            a.0.cmp(&b.0).then_with(|| by_value().unwrap_or(std::cmp::Ordering::Equal)).then(a.2.cmp(&b.2))
        });
        let clients = keyed.iter().map(|k| k.0).collect();
        let updates = keyed.into_iter().map(|(_, _, examples, u)| (u, examples)).collect();
        Self { global, spec, rule, updates, clients }
    }

    /// Every update as one vector, in the global model's tensor order.
    fn flattened(&self) -> Vec<Vec<f32>> {
        self.updates
            .iter()
            .map(|(u, _)| {
                self.global.iter().flat_map(|(name, _)| u.get(name).expect("validated").values.clone()).collect()
            })
            .collect()
    }

    fn coordinate_wise(&self, statistic: Statistic) -> NamedTensors {
        let mut out = NamedTensors::new();
        let mut column = Vec::with_capacity(self.updates.len());
        for (name, t) in self.global.iter() {
            let values = (0..t.values.len())
                .map(|i| {
                    column.clear();
                    column.extend(self.updates.iter().map(|(u, _)| u.get(name).expect("validated").values[i]));
                    statistic.of(&mut column)
                })
                .collect();
            out.insert(name, t.shape.clone(), values).expect("global shape");
        }
        out
    }

    /// The example-weighted mean of the `keep` updates with the lowest Krum score: the sum of squared distances to
    /// their `n - f - 2` nearest others.
    fn krum(&self, Krum { f, keep }: Krum) -> Result<NamedTensors, AggregateError> {
        let n = self.updates.len();
        let need = Krum::min_updates(f);
        if n < need {
            let rule = if keep == 1 { "krum" } else { "multi-krum" };
            return Err(AggregateError::TooFew { rule, need, got: n });
        }
        let all: Vec<usize> = (0..n).collect();
        let scores = krum_scores(&squared_distances(&self.flattened()), &all, f);
        let mut order: Vec<usize> = (0..n).collect();
        order.sort_by(|&a, &b| scores[a].total_cmp(&scores[b]));
        let mut mean = super::mean::WeightedMean::new(&self.global);
        for &i in &order[..keep.clamp(1, n)] {
            let (update, examples) = &self.updates[i];
            mean.fold((update, (*examples).max(1)).into())?;
        }
        Box::new(mean).finish()
    }

    /// Bulyan: `n - 2f` updates chosen by Krum one at a time (each round of Krum among those not yet chosen),
    /// then per coordinate the unweighted mean of the `n - 4f` chosen values nearest the chosen values' median.
    fn bulyan(&self, Bulyan { f }: Bulyan) -> Result<NamedTensors, AggregateError> {
        let n = self.updates.len();
        let need = Bulyan::min_updates(f);
        if n < need {
            return Err(AggregateError::TooFew { rule: "bulyan", need, got: n });
        }
        let flat = self.flattened();
        let distances = squared_distances(&flat);
        let mut remaining: Vec<usize> = (0..n).collect();
        let mut chosen = Vec::with_capacity(n - 2 * f);
        while chosen.len() < n - 2 * f {
            let scores = krum_scores(&distances, &remaining, f);
            let best = (0..remaining.len()).min_by(|&a, &b| scores[a].total_cmp(&scores[b])).expect("candidates left");
            chosen.push(remaining.remove(best));
        }
        let keep = n - 4 * f;
        let mut offset = 0;
        let mut out = NamedTensors::new();
        let mut column: Vec<f32> = Vec::with_capacity(chosen.len());
        for (name, t) in self.global.iter() {
            let values = (offset..offset + t.values.len())
                .map(|i| {
                    column.clear();
                    column.extend(chosen.iter().map(|&k| flat[k][i]));
                    let median = Statistic::Median.of(&mut column);
                    column.sort_by(|a, b| (a - median).abs().total_cmp(&(b - median).abs()));
                    (column[..keep].iter().map(|&v| f64::from(v)).sum::<f64>() / keep as f64) as f32
                })
                .collect();
            offset += t.values.len();
            out.insert(name, t.shape.clone(), values).expect("global shape");
        }
        Ok(out)
    }
}

impl Aggregation for Buffered {
    fn fold(&mut self, Contribution { tensors, examples, client, .. }: Contribution<'_>) -> Result<(), AggregateError> {
        tensors
            .validate(&self.spec)
            .map_err(|source| AggregateError::Mismatch { index: self.updates.len(), source })?;
        self.updates.push((tensors.clone(), examples));
        self.clients.push(client);
        Ok(())
    }

    fn finish(self: Box<Self>) -> Result<NamedTensors, AggregateError> {
        if self.updates.is_empty() {
            return Err(AggregateError::NoUpdates);
        }
        let this = self.into_canonical_order();
        match this.rule {
            Rule::Coordinate(statistic) => Ok(this.coordinate_wise(statistic)),
            Rule::Krum(krum) => this.krum(krum),
            Rule::Bulyan(bulyan) => this.bulyan(bulyan),
        }
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
    fn krum_and_multi_krum_by_hand() {
        // With f = 1, each score sums the 2 nearest squared distances: a 1+2 = 3, b 1+1 = 2, c 2+4 = 6, d 1+2 = 3,
        // and the attacker e's are in the tens of thousands.
        let updates = [[0.0, 0.0], [1.0, 0.0], [0.0, 2.0], [1.0, 1.0], [100.0, 100.0]];
        assert_eq!(run(&Krum { f: 1, keep: 1 }, &updates), vec![1.0, 0.0], "b");
        // Multi-Krum keeps b, a and d (a before d at equal scores) and averages them; a's weight is the claim of
        // a billion examples, as `run` gives the first update.
        let multi = run(&Krum { f: 1, keep: 3 }, &updates);
        let w = 1e9f64;
        let expected = [(1.0 + 0.0 * w + 1.0) / (w + 2.0), 1.0 / (w + 2.0)];
        assert!((f64::from(multi[0]) - expected[0]).abs() < 1e-6 && (f64::from(multi[1]) - expected[1]).abs() < 1e-6);
        // Fewer than 2f + 3 updates: refused, naming both numbers.
        let r = aggregate(&Krum { f: 1, keep: 1 }, &one([0.0, 0.0]), [(&one([1.0, 1.0]), 1)]);
        assert_eq!(r, Err(AggregateError::TooFew { rule: "krum", need: 5, got: 1 }));
    }

    #[test]
    fn bulyan_by_hand() {
        // f = 1, n = 7: Krum picks 5 of the 7 one at a time, then each coordinate averages the 3 picked values
        // nearest their median. The two attackers lose Krum's vote; of the honest five, coordinate 0's values
        // 1, 2, 3, 4, 10 keep 2, 3, 4 (median 3) and coordinate 1's 0, 1, 1, 0, 1 keep the three 1s (median 1).
        let updates = [[1.0, 0.0], [2.0, 1.0], [3.0, 1.0], [4.0, 0.0], [10.0, 1.0], [1e6, -1e6], [-1e6, 1e6]];
        assert_eq!(run(&Bulyan { f: 1 }, &updates), vec![3.0, 1.0]);
        // Fewer than 4f + 3 updates: refused, naming both numbers.
        let five: Vec<NamedTensors> = (0..5).map(|i| one([i as f32, 0.0])).collect();
        let r = aggregate(&Bulyan { f: 1 }, &one([0.0, 0.0]), five.iter().map(|u| (u, 1)));
        assert_eq!(r, Err(AggregateError::TooFew { rule: "bulyan", need: 7, got: 5 }));
    }

    #[test]
    fn robust_rules_refuse_an_empty_round() {
        let r = aggregate(&FedMedian, &one([0.0, 0.0]), std::iter::empty::<(&NamedTensors, u64)>());
        assert_eq!(r, Err(AggregateError::NoUpdates));
    }
}
