//! A volunteer's own LeRobot dataset, packed where it lies into the shard the shared trainer reads, natively
//! (`fedvla join --dataset`, from a directory) and in the browser (from the folder the page picked) alike: checked
//! against the run's signature before anything is decoded, limited to the episodes whose examples fit a byte budget,
//! split into training and held-out episodes (a seeded fifth held out, as a server shard does), its tasks
//! tokenized with the run's tokenizer. Only its signature, its claimed size and the moments of its state and action
//! reach the server (see [`fedvla_federation::DataReport`]); no frame, state or action does.

use fedvla_data::{
    ClientShard, DatasetInfo, EpisodeMeta, LeRobotDataset, PartitionConfig, PartitionStrategy, ShardSpec,
    episode_tasks, pack_shard, partition,
};
use fedvla_federation::data_report::NORMALISED_FEATURES;
use fedvla_federation::{BoxError, DatasetSignature};
use fedvla_policy::{SmolVlaConfig, Tokenizer};

use crate::examples::{dataset_signature, shard_spec, task_token_ids};

/// Share of the dataset's episodes the volunteer keeps for its own held-out evaluation (as a server shard does).
const HELD_OUT_FRACTION: f64 = 0.2;

/// An own dataset packed for the run.
pub struct OwnShard {
    pub shard: ClientShard,
    pub signature: DatasetSignature,
}

/// The signature of the dataset of `info`, if it fits the run's (`run`, which the server checks again on join):
/// else an error naming every difference. Needs only `meta/info.json`, so it comes before anything is decoded.
pub fn check_fits_run(info: &DatasetInfo, run: &DatasetSignature) -> Result<DatasetSignature, String> {
    let signature = dataset_signature(info);
    signature.check_fits(run)?;
    Ok(signature)
}

/// Bytes one frame of the dataset of `info` costs in memory while its examples are built for a policy of `cfg`:
/// its camera pictures as decoded, their copies at the policy's input size in the shard, its state and action,
/// and its frame and task indices.
pub fn bytes_per_frame(info: &DatasetInfo, cfg: &SmolVlaConfig) -> u64 {
    let spec = shard_spec(cfg);
    let packed_picture = u64::from(spec.image_width) * u64::from(spec.image_height) * 3;
    let cameras: u64 = info
        .features
        .0
        .iter()
        .filter(|(_, f)| f.dtype == "video")
        .map(|(_, f)| f.width() as u64 + packed_picture)
        .sum();
    let vectors: u64 =
        NORMALISED_FEATURES.iter().filter_map(|k| info.features.get(k)).map(|f| f.width() as u64 * 4).sum();
    cameras + vectors + 2 * 8
}

/// The episodes, in the dataset's order, whose frames fit `budget_bytes` at `bytes_per_frame` each: the first
/// ones, up to the first that would not fit.
pub fn episodes_within(episodes: &[EpisodeMeta], bytes_per_frame: u64, budget_bytes: u64) -> Vec<usize> {
    let mut used = 0u64;
    episodes
        .iter()
        .map_while(|e| {
            used += e.length as u64 * bytes_per_frame;
            (used <= budget_bytes).then_some(e.episode_index)
        })
        .collect()
}

/// Packs `episodes` of `dataset` (whose signature `signature` fits the run) for a run of policy `cfg` tokenizing
/// with the run's `tokenizer`, a seeded fifth of them held out. `on_episode` hears of every episode packed. Errors
/// name the dataset.
pub fn pack_own_dataset(
    dataset: &LeRobotDataset,
    episodes: &[usize],
    signature: DatasetSignature,
    cfg: &SmolVlaConfig,
    tokenizer: &Tokenizer,
    seed: u64,
    on_episode: &mut dyn FnMut(&EpisodeMeta),
) -> Result<OwnShard, BoxError> {
    let named = |e: &dyn std::fmt::Display| format!("own dataset {}: {e}", dataset.root().display());
    if episodes.is_empty() {
        return Err(named(&"no episode to train on (none fits the memory budget, or the dataset has none)").into());
    }
    let config = PartitionConfig {
        num_clients: 1,
        strategy: PartitionStrategy::EpisodeModulo,
        client_held_out_fraction: HELD_OUT_FRACTION,
        server_held_out_fraction: 0.0,
        seed,
    };
    let chosen: Vec<_> = episode_tasks(dataset).into_iter().filter(|e| episodes.contains(&e.episode_index)).collect();
    let parts = partition(&chosen, &config).map_err(|e| named(&e))?;
    let task_ids = task_token_ids(tokenizer, dataset.tasks(), cfg).map_err(|e| named(&e))?;
    let tokenize = |task: &str| -> Vec<u32> { task_ids.get(task).cloned().unwrap_or_default() };
    let spec: ShardSpec = shard_spec(cfg);
    let (_, bytes) = pack_shard(dataset, &parts, 0, &spec, Some(&tokenize), on_episode).map_err(|e| named(&e))?;
    let shard = ClientShard::from_bytes(dataset.root(), &bytes).map_err(|e| named(&e))?;
    Ok(OwnShard { shard, signature })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn episode(episode_index: usize, length: usize) -> EpisodeMeta {
        EpisodeMeta {
            episode_index,
            tasks: Vec::new(),
            length,
            dataset_from_index: 0,
            dataset_to_index: length,
            videos: Default::default(),
            stats: Default::default(),
        }
    }

    #[test]
    fn the_budget_takes_the_first_episodes_that_fit() {
        let episodes = [episode(0, 10), episode(1, 20), episode(2, 5)];
        assert_eq!(episodes_within(&episodes, 100, 3000), [0, 1]);
        assert_eq!(episodes_within(&episodes, 100, 3499), [0, 1]);
        assert_eq!(episodes_within(&episodes, 100, 3500), [0, 1, 2]);
        assert!(episodes_within(&episodes, 100, 999).is_empty());
    }
}
