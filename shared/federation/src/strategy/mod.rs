//! Aggregation strategies, one interface for all: a round opens an [`Aggregation`] from the global model its
//! clients trained from, folds their updates into it one at a time as they arrive (a streaming rule keeps an exact
//! running sum, [`exact`], so its memory is one model's whatever the number of clients and its aggregate the same
//! in any arrival order; a robust rule buffers every update of the round, its memory growing with the round's
//! clients, and orders them canonically before it decides), closes it into the round's aggregate, and the strategy turns that into the next global model. What the strategy carries from round to
//! round (server moments, control variates, a clipping norm, the rounds a privacy accountant counts) changes only when the server commits the round, so
//! a round retried or skipped leaves it as it was, and it is saved with each round for `--resume`.

mod clipping;
mod dp;
mod exact;
mod interface;
mod mean;
mod qffl;
mod robust;
mod scaffold;
mod server_opt;

pub use clipping::{ClipNorm, ClippedUpdates};
pub use dp::{DpFedAvg, PrivacyReport};
pub use interface::{Aggregation, Contribution, Step, Strategy, aggregate, conclude};
pub use mean::{FedAvg, FedProx, WeightedMean};
pub use qffl::QFedAvg;
pub use robust::{Bulyan, FedMedian, FedTrimmedAvg, Krum};
pub use scaffold::Scaffold;
pub use server_opt::{Adaptivity, FedAdaptive, FedAvgM};

#[cfg(test)]
mod tests {
    use super::*;
    use crate::tensors::NamedTensors;

    /// Eight clients' models of two tensors, seeded values of mixed magnitudes (where an f64 running sum rounds
    /// differently in another order).
    fn updates() -> Vec<NamedTensors> {
        let mut state = 7u64;
        let mut next = move || {
            state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            let unit = (state >> 40) as f32 / (1u64 << 24) as f32 - 0.5;
            unit * [1e-6, 1e-2, 1.0, 300.0][(state >> 20) as usize % 4]
        };
        (0..8)
            .map(|_| {
                let mut t = NamedTensors::new();
                t.insert("a", vec![64], (0..64).map(|_| next()).collect()).unwrap();
                t.insert("b", vec![3, 5], (0..15).map(|_| next()).collect()).unwrap();
                t
            })
            .collect()
    }

    #[test]
    fn every_strategy_aggregates_the_same_bits_in_any_arrival_order() {
        let updates = updates();
        let global = updates[0].zip_map(&updates[1], |a, b| (a + b) / 2.0).unwrap();
        let strategies: Vec<(&str, Box<dyn Strategy>)> = vec![
            ("fedavg", Box::new(FedAvg)),
            ("fedavgm", Box::new(FedAvgM::new(1.0, 0.9))),
            ("fedadam", Box::new(FedAdaptive::new(Adaptivity::Adam, 0.1, 0.9, 0.99, 1e-3))),
            ("scaffold", Box::new(Scaffold::new(1.0, 8))),
            ("qfedavg", Box::new(QFedAvg { q: 0.2, lr: 0.1 })),
            ("clipped", Box::new(ClippedUpdates::fixed(Box::new(FedAvg), 50.0))),
            ("clipped-adaptive", Box::new(ClippedUpdates::adaptive(Box::new(FedAvg), 50.0, 0.5, 0.2))),
            ("dp", Box::new(DpFedAvg::new(Box::new(FedAvg), 0.5, ClipNorm::Fixed(50.0), 1.0, 1e-5, 3))),
            ("median", Box::new(FedMedian)),
            ("trimmed-mean", Box::new(FedTrimmedAvg { beta: 0.2 })),
            ("multi-krum", Box::new(Krum { f: 1, keep: 3 })),
            ("bulyan", Box::new(Bulyan { f: 1 })),
        ];
        let contributions = |order: &[usize]| -> Vec<Contribution<'_>> {
            order
                .iter()
                .map(|&i| Contribution {
                    train_loss: Some(0.1 * (i + 1) as f64),
                    client: Some(i as u64),
                    lr_sum: Some(0.5),
                    ..(&updates[i], 100 + 37 * i as u64).into()
                })
                .collect()
        };
        let forward: Vec<usize> = (0..8).collect();
        let shuffled = [5, 2, 7, 0, 3, 6, 1, 4];
        for (name, strategy) in &strategies {
            let a = aggregate(strategy.as_ref(), &global, contributions(&forward)).unwrap();
            let b = aggregate(strategy.as_ref(), &global, contributions(&shuffled)).unwrap();
            for ((n, x), (_, y)) in a.global.iter().zip(b.global.iter()) {
                let bits = |t: &crate::tensors::Tensor| t.values.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
                assert_eq!(bits(x), bits(y), "{name}: tensor {n}");
            }
            assert_eq!(a.state, b.state, "{name}: the state it leaves");
        }
    }
}
