//! A volunteer's own LeRobot dataset (`fedvla join URL --dataset PATH`): read where it lies (v3.0 or v2.1, H.264
//! or AV1 as the reader decodes them), split into training and held-out episodes and packed, on the volunteer's
//! machine, into the shard the shared trainer reads. Only its signature, its claimed size and the moments of its
//! state and action reach the server (see [`fedvla_federation::DataReport`]); no frame, state or action does.

use std::path::Path;
use std::sync::atomic::{AtomicU64, Ordering};

use fedvla_data::{
    ClientShard, LeRobotDataset, PartitionConfig, PartitionStrategy, build_shard, episode_tasks, partition,
};
use fedvla_federation::{BoxError, DatasetSignature};
use fedvla_learner::examples::{dataset_signature, shard_spec, task_token_ids};
use fedvla_policy::{SmolVlaConfig, Tokenizer};

/// Share of the dataset's episodes the volunteer keeps for its own held-out evaluation (as a server shard does).
const HELD_OUT_FRACTION: f64 = 0.2;

/// Distinguishes the packing directories of concurrent volunteers in one process.
static PACKINGS: AtomicU64 = AtomicU64::new(0);

/// An own dataset packed for the run.
pub struct OwnShard {
    pub shard: ClientShard,
    pub signature: DatasetSignature,
}

/// Packs the LeRobot dataset at `root` for a run of policy `cfg` tokenizing with the run's `tokenizer`: every
/// episode, a seeded fifth of them held out. A dataset that does not fit `run` (the run's signature, which the
/// server checks again on join) is refused before anything is decoded, naming every difference. Errors name the
/// dataset.
pub fn pack_own_dataset(
    root: &Path,
    run: &DatasetSignature,
    cfg: &SmolVlaConfig,
    tokenizer: &Tokenizer,
    seed: u64,
) -> Result<OwnShard, BoxError> {
    let dataset = LeRobotDataset::open(root).map_err(|e| format!("own dataset {}: {e}", root.display()))?;
    let signature = dataset_signature(dataset.info());
    signature.check_fits(run).map_err(|e| format!("own dataset {}: {e}", root.display()))?;
    let config = PartitionConfig {
        num_clients: 1,
        strategy: PartitionStrategy::EpisodeModulo,
        client_held_out_fraction: HELD_OUT_FRACTION,
        server_held_out_fraction: 0.0,
        seed,
    };
    let parts =
        partition(&episode_tasks(&dataset), &config).map_err(|e| format!("own dataset {}: {e}", root.display()))?;
    let spec = shard_spec(cfg);
    let task_ids =
        task_token_ids(tokenizer, dataset.tasks(), cfg).map_err(|e| format!("own dataset {}: {e}", root.display()))?;
    let tokenize = |task: &str| -> Vec<u32> { task_ids.get(task).cloned().unwrap_or_default() };
    // Packed into a file of the volunteer's temporary directory, read back and removed: the shard reader and
    // writer are the ones server shards use.
    let dir = std::env::temp_dir().join(format!(
        "fedvla-own-dataset-{}-{}",
        std::process::id(),
        PACKINGS.fetch_add(1, Ordering::Relaxed)
    ));
    std::fs::create_dir_all(&dir).map_err(|e| format!("{}: {e}", dir.display()))?;
    let path = dir.join("own.safetensors");
    let packed = build_shard(&dataset, &parts, 0, &spec, Some(&tokenize), &path, &mut |episode| {
        tracing::debug!(episode = episode.episode_index, "own episode packed");
    })
    .map_err(|e| -> BoxError { format!("packing own dataset {}: {e}", root.display()).into() })
    .and_then(|_| Ok(ClientShard::read(&path)?));
    let _ = std::fs::remove_dir_all(&dir);
    Ok(OwnShard { shard: packed?, signature })
}
