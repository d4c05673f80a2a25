//! Splitting a dataset's episodes among N federated clients.
//!
//! First the server's global held-out set is drawn from all episodes; the rest is dealt to clients
//! by one of four strategies; then every client sets aside its own held-out share, which it
//! evaluates on and never trains on. Everything is a pure function of the episode list and the
//! config (including its seed), so the server and every client derive the same partition, and no
//! episode is ever in two places.

use rand::SeedableRng;
use rand::rngs::StdRng;
use rand::seq::SliceRandom;
use rand_distr::{Distribution, Gamma};
use serde::{Deserialize, Serialize};

use crate::error::{DataError, Result};
#[cfg(feature = "read")]
use crate::reader::LeRobotDataset;

/// How the episodes left after the server's held-out set are dealt to clients.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum PartitionStrategy {
    /// Client `episode_index % N` (the simplest IID-ish split).
    EpisodeModulo,
    /// Episodes in index order, cut into N contiguous runs of (nearly) equal size.
    Contiguous,
    /// Episodes in the order the caller lists them (e.g. by where the sim put the cube), cut into N contiguous runs
    /// of (nearly) equal size: each client holds one region of that order.
    ContiguousInGivenOrder,
    /// Every task goes whole to one client; tasks are dealt round-robin in a seeded order.
    ByTask,
    /// Per task, client shares drawn from Dirichlet(alpha): small alpha = very skewed clients.
    Dirichlet { alpha: f64 },
}

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PartitionConfig {
    pub num_clients: usize,
    pub strategy: PartitionStrategy,
    /// Share of each client's episodes it holds out (rounded to the nearest episode).
    pub client_held_out_fraction: f64,
    /// Share of all episodes the server keeps as a global held-out set (rounded to the nearest episode).
    pub server_held_out_fraction: f64,
    pub seed: u64,
}

/// An episode as the partitioner sees it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct EpisodeTask {
    pub episode_index: usize,
    pub task_index: usize,
}

#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct ClientSplit {
    /// Episode indices the client trains on (sorted).
    pub train: Vec<usize>,
    /// Episode indices the client only evaluates on (sorted).
    pub held_out: Vec<usize>,
}

impl ClientSplit {
    pub fn all(&self) -> impl Iterator<Item = usize> + '_ {
        self.train.iter().chain(&self.held_out).copied()
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Partition {
    pub config: PartitionConfig,
    /// One entry per client, in client order.
    pub clients: Vec<ClientSplit>,
    /// Episodes no client sees: the server's global evaluation set (sorted).
    pub server_held_out: Vec<usize>,
}

/// `fraction` of `n` items, rounded to the nearest whole item. A positive fraction of two or more
/// items holds out at least one and keeps at least one: a held-out set must exist to be evaluated on,
/// and a client must have something to train on.
pub fn held_out_count(n: usize, fraction: f64) -> usize {
    let k = ((n as f64 * fraction).round() as usize).min(n);
    if fraction > 0.0 && n >= 2 { k.clamp(1, n - 1) } else { k }
}

/// The (episode, task) list of a dataset, an episode's task being its first listed task.
#[cfg(feature = "read")]
pub fn episode_tasks(dataset: &LeRobotDataset) -> Vec<EpisodeTask> {
    dataset
        .episodes()
        .iter()
        .map(|e| EpisodeTask {
            episode_index: e.episode_index,
            task_index: e.tasks.first().and_then(|t| dataset.tasks().iter().position(|k| k == t)).unwrap_or(0),
        })
        .collect()
}

/// Partitions `episodes` (each listed once) according to `config`.
pub fn partition(episodes: &[EpisodeTask], config: &PartitionConfig) -> Result<Partition> {
    let n = config.num_clients;
    if n == 0 {
        return Err(DataError::InvalidInput("a partition needs at least one client".into()));
    }
    for (name, f) in [
        ("client_held_out_fraction", config.client_held_out_fraction),
        ("server_held_out_fraction", config.server_held_out_fraction),
    ] {
        if !(0.0..=1.0).contains(&f) {
            return Err(DataError::InvalidInput(format!("{name} must lie in [0, 1], got {f}")));
        }
    }
    if let PartitionStrategy::Dirichlet { alpha } = config.strategy
        && !(alpha > 0.0 && alpha.is_finite())
    {
        return Err(DataError::InvalidInput(format!("Dirichlet alpha must be positive and finite, got {alpha}")));
    }
    let mut sorted = episodes.to_vec();
    sorted.sort_by_key(|e| e.episode_index);
    if sorted.windows(2).any(|w| w[0].episode_index == w[1].episode_index) {
        return Err(DataError::InvalidInput("an episode index is listed twice".into()));
    }

    let mut rng = StdRng::seed_from_u64(config.seed);
    let mut shuffled = sorted.clone();
    shuffled.shuffle(&mut rng);
    let server_count = held_out_count(sorted.len(), config.server_held_out_fraction);
    let mut server_held_out: Vec<usize> = shuffled[..server_count].iter().map(|e| e.episode_index).collect();
    server_held_out.sort_unstable();
    let remaining: Vec<EpisodeTask> =
        sorted.into_iter().filter(|e| server_held_out.binary_search(&e.episode_index).is_err()).collect();

    let assigned = match config.strategy {
        PartitionStrategy::EpisodeModulo => {
            let mut out = vec![Vec::new(); n];
            for e in &remaining {
                out[e.episode_index % n].push(e.episode_index);
            }
            out
        }
        PartitionStrategy::Contiguous => {
            let indices: Vec<usize> = remaining.iter().map(|e| e.episode_index).collect();
            split_by_counts(&indices, &even_counts(indices.len(), n))
        }
        PartitionStrategy::ContiguousInGivenOrder => {
            let kept: Vec<usize> = episodes
                .iter()
                .map(|e| e.episode_index)
                .filter(|i| server_held_out.binary_search(i).is_err())
                .collect();
            split_by_counts(&kept, &even_counts(kept.len(), n))
        }
        PartitionStrategy::ByTask => {
            let mut tasks = distinct_tasks(&remaining);
            tasks.shuffle(&mut rng);
            let mut out = vec![Vec::new(); n];
            for (i, task) in tasks.iter().enumerate() {
                out[i % n].extend(remaining.iter().filter(|e| e.task_index == *task).map(|e| e.episode_index));
            }
            out
        }
        PartitionStrategy::Dirichlet { alpha } => {
            let gamma =
                Gamma::new(alpha, 1.0).map_err(|e| DataError::InvalidInput(format!("Dirichlet alpha {alpha}: {e}")))?;
            let mut out = vec![Vec::new(); n];
            for task in distinct_tasks(&remaining) {
                let mut members: Vec<usize> =
                    remaining.iter().filter(|e| e.task_index == task).map(|e| e.episode_index).collect();
                members.shuffle(&mut rng);
                let mut weights: Vec<f64> = (0..n).map(|_| gamma.sample(&mut rng)).collect();
                let total: f64 = weights.iter().sum();
                if total > 0.0 && total.is_finite() {
                    for w in &mut weights {
                        *w /= total;
                    }
                } else {
                    // Every draw underflowed (tiny alpha): the whole task goes to one client.
                    let pick = task % n;
                    weights = (0..n).map(|c| if c == pick { 1.0 } else { 0.0 }).collect();
                }
                for (c, part) in
                    split_by_counts(&members, &proportional_counts(members.len(), &weights)).into_iter().enumerate()
                {
                    out[c].extend(part);
                }
            }
            out
        }
    };

    let clients = assigned
        .into_iter()
        .map(|mut episodes| {
            episodes.shuffle(&mut rng);
            let k = held_out_count(episodes.len(), config.client_held_out_fraction);
            let mut held_out = episodes[..k].to_vec();
            let mut train = episodes[k..].to_vec();
            held_out.sort_unstable();
            train.sort_unstable();
            ClientSplit { train, held_out }
        })
        .collect();
    Ok(Partition { config: *config, clients, server_held_out })
}

fn distinct_tasks(episodes: &[EpisodeTask]) -> Vec<usize> {
    let mut tasks: Vec<usize> = episodes.iter().map(|e| e.task_index).collect();
    tasks.sort_unstable();
    tasks.dedup();
    tasks
}

/// `total` split into `parts` counts differing by at most one, larger ones first.
fn even_counts(total: usize, parts: usize) -> Vec<usize> {
    (0..parts).map(|i| total / parts + usize::from(i < total % parts)).collect()
}

/// `total` split by `weights` (summing to 1) with the largest-remainder method, so counts sum to `total`.
fn proportional_counts(total: usize, weights: &[f64]) -> Vec<usize> {
    let exact: Vec<f64> = weights.iter().map(|w| w * total as f64).collect();
    let mut counts: Vec<usize> = exact.iter().map(|x| x.floor() as usize).collect();
    let mut order: Vec<usize> = (0..weights.len()).collect();
    order.sort_by(|&a, &b| (exact[b] - exact[b].floor()).total_cmp(&(exact[a] - exact[a].floor())).then(a.cmp(&b)));
    let missing = total.saturating_sub(counts.iter().sum());
    for &i in order.iter().cycle().take(missing) {
        counts[i] += 1;
    }
    counts
}

fn split_by_counts(items: &[usize], counts: &[usize]) -> Vec<Vec<usize>> {
    let mut start = 0;
    counts
        .iter()
        .map(|&c| {
            let part = items[start..start + c].to_vec();
            start += c;
            part
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn strategy() -> impl Strategy<Value = PartitionStrategy> {
        prop_oneof![
            Just(PartitionStrategy::EpisodeModulo),
            Just(PartitionStrategy::Contiguous),
            Just(PartitionStrategy::ContiguousInGivenOrder),
            Just(PartitionStrategy::ByTask),
            (0.05f64..5.0).prop_map(|alpha| PartitionStrategy::Dirichlet { alpha }),
        ]
    }

    fn setup() -> impl Strategy<Value = (Vec<EpisodeTask>, PartitionConfig)> {
        (1usize..120, 1usize..6, 1usize..9, strategy(), 0.0f64..0.5, 0.0f64..0.3, any::<u64>()).prop_map(
            |(episodes, tasks, num_clients, strategy, client_held_out_fraction, server_held_out_fraction, seed)| {
                // Sparse, shuffled episode indices: a dataset subset need not be 0..n.
                let list = (0..episodes)
                    .map(|i| EpisodeTask { episode_index: 3 * i + 1, task_index: (i * 7) % tasks })
                    .rev()
                    .collect();
                (
                    list,
                    PartitionConfig { num_clients, strategy, client_held_out_fraction, server_held_out_fraction, seed },
                )
            },
        )
    }

    proptest! {
        #[test]
        fn partitions_are_disjoint_and_cover_all_episodes((episodes, config) in setup()) {
            let p = partition(&episodes, &config).expect("valid config");
            prop_assert_eq!(p.clients.len(), config.num_clients);
            let mut seen: Vec<usize> = p.clients.iter().flat_map(ClientSplit::all).chain(p.server_held_out.iter().copied()).collect();
            seen.sort_unstable();
            let mut all: Vec<usize> = episodes.iter().map(|e| e.episode_index).collect();
            all.sort_unstable();
            // Equal sorted lists: every episode appears exactly once across all train/held-out sets.
            prop_assert_eq!(seen, all);
        }

        #[test]
        fn held_out_shares_are_kept((episodes, config) in setup()) {
            let p = partition(&episodes, &config).expect("valid config");
            prop_assert_eq!(p.server_held_out.len(), held_out_count(episodes.len(), config.server_held_out_fraction));
            for c in &p.clients {
                let n = c.train.len() + c.held_out.len();
                prop_assert_eq!(c.held_out.len(), held_out_count(n, config.client_held_out_fraction));
            }
        }

        #[test]
        fn same_seed_same_partition((episodes, config) in setup()) {
            let a = partition(&episodes, &config).expect("valid config");
            let b = partition(&episodes, &config).expect("valid config");
            prop_assert_eq!(a, b);
        }

        #[test]
        fn strategies_follow_their_rule((episodes, config) in setup()) {
            let p = partition(&episodes, &config).expect("valid config");
            let task_of = |ep: usize| episodes.iter().find(|e| e.episode_index == ep).map(|e| e.task_index);
            match config.strategy {
                PartitionStrategy::EpisodeModulo => {
                    for (c, split) in p.clients.iter().enumerate() {
                        prop_assert!(split.all().all(|ep| ep % config.num_clients == c));
                    }
                }
                PartitionStrategy::ByTask => {
                    let mut owner = std::collections::BTreeMap::new();
                    for (c, split) in p.clients.iter().enumerate() {
                        for ep in split.all() {
                            let previous = owner.insert(task_of(ep), c);
                            prop_assert!(previous.is_none() || previous == Some(c), "a task is split across clients");
                        }
                    }
                }
                PartitionStrategy::Contiguous => {
                    let sizes: Vec<usize> = p.clients.iter().map(|c| c.train.len() + c.held_out.len()).collect();
                    let (min, max) = (sizes.iter().min().copied().unwrap_or(0), sizes.iter().max().copied().unwrap_or(0));
                    prop_assert!(max - min <= 1, "contiguous sizes {:?}", sizes);
                    let ranges: Vec<(usize, usize)> = p.clients.iter().filter_map(|c| Some((c.all().min()?, c.all().max()?))).collect();
                    prop_assert!(ranges.windows(2).all(|w| w[0].1 < w[1].0), "runs overlap: {:?}", ranges);
                }
                PartitionStrategy::ContiguousInGivenOrder => {
                    // In the caller's order (here: descending index), each client holds one run.
                    let position = |ep: usize| episodes.iter().position(|e| e.episode_index == ep).unwrap();
                    let ranges: Vec<(usize, usize)> = p
                        .clients
                        .iter()
                        .filter_map(|c| Some((c.all().map(position).min()?, c.all().map(position).max()?)))
                        .collect();
                    prop_assert!(ranges.windows(2).all(|w| w[0].1 < w[1].0), "runs overlap: {:?}", ranges);
                }
                PartitionStrategy::Dirichlet { .. } => {}
            }
        }
    }

    #[test]
    fn different_seeds_give_different_dirichlet_splits() {
        let episodes: Vec<EpisodeTask> = (0..60).map(|i| EpisodeTask { episode_index: i, task_index: i % 3 }).collect();
        let config = |seed| PartitionConfig {
            num_clients: 4,
            strategy: PartitionStrategy::Dirichlet { alpha: 0.5 },
            client_held_out_fraction: 0.1,
            server_held_out_fraction: 0.1,
            seed,
        };
        let a = partition(&episodes, &config(1)).expect("valid");
        let b = partition(&episodes, &config(2)).expect("valid");
        assert_ne!(a.clients, b.clients);
    }

    #[test]
    fn invalid_configs_are_rejected() {
        let episodes = [EpisodeTask { episode_index: 0, task_index: 0 }];
        let base = PartitionConfig {
            num_clients: 2,
            strategy: PartitionStrategy::EpisodeModulo,
            client_held_out_fraction: 0.1,
            server_held_out_fraction: 0.1,
            seed: 0,
        };
        assert!(partition(&episodes, &PartitionConfig { num_clients: 0, ..base }).is_err());
        assert!(partition(&episodes, &PartitionConfig { client_held_out_fraction: 1.5, ..base }).is_err());
        assert!(
            partition(&episodes, &PartitionConfig { strategy: PartitionStrategy::Dirichlet { alpha: 0.0 }, ..base })
                .is_err()
        );
        let twice = [episodes[0], episodes[0]];
        assert!(partition(&twice, &base).is_err());
    }
}
