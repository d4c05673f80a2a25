//! Packing a client's shard from a dataset, in memory (feature `read`), and writing it as a shard file with its
//! sidecar manifest (feature `io`).

use std::borrow::Cow;
use std::collections::{BTreeMap, BTreeSet, HashMap};
#[cfg(feature = "io")]
use std::path::Path;

use safetensors::tensor::{Dtype, View};
#[cfg(feature = "io")]
use sha2::{Digest, Sha256};

use super::format::{MANIFEST_KEY, SHARD_FORMAT, ShardManifest, ShardSpec, Tokenizer, content_hash};
#[cfg(feature = "io")]
use super::format::{ShardFileManifest, hex, sidecar_path};
use crate::error::{DataError, Result};
use crate::partition::Partition;
use crate::reader::{EpisodeMeta, LeRobotDataset};
use crate::stats::FeatureStats;

/// The vector features a shard carries, in tensor order.
const VECTOR_FEATURES: [&str; 2] = ["observation.state", "action"];

struct OwnedTensor {
    dtype: Dtype,
    shape: Vec<usize>,
    data: Vec<u8>,
}

impl View for &OwnedTensor {
    fn dtype(&self) -> Dtype {
        self.dtype
    }
    fn shape(&self) -> &[usize] {
        &self.shape
    }
    fn data(&self) -> Cow<'_, [u8]> {
        Cow::Borrowed(&self.data)
    }
    fn data_len(&self) -> usize {
        self.data.len()
    }
}

fn f32_tensor(values: &[f32], shape: Vec<usize>) -> OwnedTensor {
    OwnedTensor { dtype: Dtype::F32, shape, data: values.iter().flat_map(|v| v.to_le_bytes()).collect() }
}

fn i64_tensor(values: &[i64], shape: Vec<usize>) -> OwnedTensor {
    OwnedTensor { dtype: Dtype::I64, shape, data: values.iter().flat_map(|v| v.to_le_bytes()).collect() }
}

/// Builds client `client`'s shard of `partition` from `dataset` at `out` (a `.safetensors` path) and
/// writes the sidecar manifest next to it. `tokenize` turns a task string into token ids. `on_episode`
/// hears of every episode packed (decoding its videos is the slow part).
#[cfg(feature = "io")]
pub fn build_shard(
    dataset: &LeRobotDataset,
    partition: &Partition,
    client: usize,
    spec: &ShardSpec,
    tokenize: Option<Tokenizer>,
    out: &Path,
    on_episode: &mut dyn FnMut(&EpisodeMeta),
) -> Result<ShardFileManifest> {
    let (manifest, bytes) =
        pack_shard(dataset, partition, client, spec, tokenize, on_episode).map_err(|e| match e {
            DataError::BadShard { reason, .. } => DataError::BadShard { path: out.to_path_buf(), reason },
            other => other,
        })?;
    if let Some(dir) = out.parent() {
        std::fs::create_dir_all(dir).map_err(|e| DataError::io(dir, e))?;
    }
    fedvla_fs::write_atomic(out, &bytes).map_err(|e| DataError::io(out, e))?;
    let file_manifest = ShardFileManifest {
        file: out.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default(),
        file_bytes: bytes.len() as u64,
        file_sha256: hex(&Sha256::digest(&bytes)),
        manifest,
    };
    crate::info::write_json(&sidecar_path(out), &file_manifest)?;
    Ok(file_manifest)
}

/// Packs client `client`'s shard of `partition` from `dataset` in memory: its manifest and the shard's bytes
/// (what [`crate::ClientShard::from_bytes`] reads). `tokenize` turns a task string into token ids. `on_episode`
/// hears of every episode packed (decoding its videos is the slow part).
pub fn pack_shard(
    dataset: &LeRobotDataset,
    partition: &Partition,
    client: usize,
    spec: &ShardSpec,
    tokenize: Option<Tokenizer>,
    on_episode: &mut dyn FnMut(&EpisodeMeta),
) -> Result<(ShardManifest, Vec<u8>)> {
    let split = partition.clients.get(client).ok_or_else(|| {
        DataError::InvalidInput(format!(
            "client {client} is not in the partition ({} clients)",
            partition.clients.len()
        ))
    })?;
    let held_out: BTreeSet<usize> = split.held_out.iter().copied().collect();
    let mut episode_ids: Vec<usize> = split.all().collect();
    episode_ids.sort_unstable();
    let by_index: HashMap<usize, &EpisodeMeta> = dataset.episodes().iter().map(|e| (e.episode_index, e)).collect();
    let cameras = dataset.camera_keys();
    let dims: Vec<usize> = VECTOR_FEATURES
        .iter()
        .map(|k| {
            dataset
                .info()
                .features
                .get(k)
                .map(crate::info::Feature::width)
                .ok_or_else(|| DataError::InvalidInput(format!("dataset has no {k} feature")))
        })
        .collect::<Result<_>>()?;

    let mut images: Vec<Vec<u8>> = vec![Vec::new(); cameras.len()];
    let mut vectors: Vec<Vec<f32>> = vec![Vec::new(); VECTOR_FEATURES.len()];
    let (mut frame_index, mut task_rows, mut episode_rows) = (Vec::new(), Vec::new(), Vec::new());
    let mut tasks: Vec<String> = Vec::new();
    let mut rows = 0usize;
    for ep_id in &episode_ids {
        let episode = by_index.get(ep_id).ok_or_else(|| {
            DataError::InvalidInput(format!("episode {ep_id} of the partition is not in the dataset"))
        })?;
        let indices: Vec<usize> = (episode.dataset_from_index..episode.dataset_to_index).collect();
        for (c, camera) in cameras.iter().enumerate() {
            for frame in dataset.camera_frames(camera, episode, &indices)? {
                images[c].extend_from_slice(&frame.resized_with_pad(spec.image_width, spec.image_height).data);
            }
        }
        for &i in &indices {
            for (k, key) in VECTOR_FEATURES.iter().enumerate() {
                let row = dataset.vector(key, i).ok_or(DataError::IndexOutOfRange { index: i, len: dataset.len() })?;
                vectors[k].extend_from_slice(row);
            }
            let task = dataset.task_index(i).and_then(|t| dataset.tasks().get(t)).cloned().unwrap_or_default();
            let local = tasks.iter().position(|t| *t == task).unwrap_or_else(|| {
                tasks.push(task);
                tasks.len() - 1
            });
            task_rows.push(local as i64);
            frame_index.push((i - episode.dataset_from_index) as i64);
        }
        episode_rows.extend([
            *ep_id as i64,
            rows as i64,
            (rows + indices.len()) as i64,
            i64::from(held_out.contains(ep_id)),
        ]);
        rows += indices.len();
        on_episode(episode);
    }

    let mut tensors: BTreeMap<String, OwnedTensor> = BTreeMap::new();
    let (w, h) = (spec.image_width as usize, spec.image_height as usize);
    for (camera, data) in cameras.iter().zip(images) {
        tensors.insert(camera.clone(), OwnedTensor { dtype: Dtype::U8, shape: vec![rows, h, w, 3], data });
    }
    for ((key, values), dim) in VECTOR_FEATURES.iter().zip(&vectors).zip(&dims) {
        tensors.insert((*key).to_string(), f32_tensor(values, vec![rows, *dim]));
        let stats = match dataset.stats().and_then(|s| s.get(*key)) {
            Some(s) => s.clone(),
            None => {
                let all: Vec<Vec<f64>> = (0..dataset.len())
                    .filter_map(|i| dataset.vector(key, i))
                    .map(|r| r.iter().map(|&v| f64::from(v)).collect())
                    .collect();
                FeatureStats::from_rows(&all, *dim)
            }
        };
        for (name, values) in stats.named_values() {
            if values.len() == *dim {
                let as_f32: Vec<f32> = values.iter().map(|&v| v as f32).collect();
                tensors.insert(format!("stats/{key}/{name}"), f32_tensor(&as_f32, vec![*dim]));
            }
        }
    }
    tensors.insert("frame_index".into(), i64_tensor(&frame_index, vec![rows]));
    tensors.insert("task_index".into(), i64_tensor(&task_rows, vec![rows]));
    tensors.insert("episodes".into(), i64_tensor(&episode_rows, vec![episode_ids.len(), 4]));
    if let Some(tokenize) = tokenize {
        let l = spec.tokenizer_max_length;
        let (mut ids, mut mask) = (Vec::with_capacity(tasks.len() * l), Vec::with_capacity(tasks.len() * l));
        for task in &tasks {
            let tokens = tokenize(task);
            for (id, is_task) in spec.padded_task_tokens(&tokens) {
                ids.push(id);
                mask.push(is_task);
            }
        }
        tensors.insert("task_tokens".into(), i64_tensor(&ids, vec![tasks.len(), l]));
        tensors.insert(
            "task_attention_mask".into(),
            OwnedTensor { dtype: Dtype::U8, shape: vec![tasks.len(), l], data: mask },
        );
    }

    let manifest = ShardManifest {
        format: SHARD_FORMAT.into(),
        client_index: client,
        partition: partition.config,
        robot_type: dataset.info().robot_type.clone(),
        fps: dataset.fps(),
        cameras,
        image_width: spec.image_width,
        image_height: spec.image_height,
        state_dim: dims[0],
        action_dim: dims[1],
        num_frames: rows,
        train_episodes: split.train.clone(),
        held_out_episodes: split.held_out.clone(),
        tasks,
        tokenized: tokenize.is_some(),
        tokenizer_max_length: spec.tokenizer_max_length,
        content_sha256: content_hash(
            tensors.iter().map(|(n, t)| (n.as_str(), t.dtype, t.shape.as_slice(), t.data.as_slice())),
        ),
    };
    let manifest_json = serde_json::to_string(&manifest).map_err(|e| DataError::InvalidInput(e.to_string()))?;
    let bytes = safetensors::serialize(
        tensors.iter().map(|(n, t)| (n.as_str(), t)),
        Some(HashMap::from([(MANIFEST_KEY.to_string(), manifest_json)])),
    )
    .map_err(|e| DataError::BadShard { path: dataset.root().to_path_buf(), reason: e.to_string() })?;
    Ok((manifest, bytes))
}
