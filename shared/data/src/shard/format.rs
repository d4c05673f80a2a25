//! What a shard is, on disk and on the wire: its format name, how it is built ([`ShardSpec`]), its manifest (in
//! the file's metadata, and the sidecar `<name>.manifest.json` with the file's size and SHA-256), and the content
//! hash both the builder and the reader compute.

use std::path::{Path, PathBuf};

use safetensors::tensor::Dtype;
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use crate::partition::PartitionConfig;

pub const SHARD_FORMAT: &str = "fedvla-shard/1";
pub(super) const MANIFEST_KEY: &str = "fedvla.manifest";

/// Turns a task string into token ids (the policy's tokenizer lives outside this crate).
pub type Tokenizer<'a> = &'a dyn Fn(&str) -> Vec<u32>;

/// How a shard is built.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ShardSpec {
    /// The policy's image input size (SmolVLA: 512x512); frames are resized-with-pad to it.
    pub image_width: u32,
    pub image_height: u32,
    /// Token budget per task string (SmolVLA: 48); shorter strings are padded on the right.
    pub tokenizer_max_length: usize,
    pub pad_token_id: u32,
}

impl ShardSpec {
    /// One task's token ids as a shard stores them (`task_tokens`, `task_attention_mask`): each position up to
    /// `tokenizer_max_length` as its id, the pad id past the task's end, and whether it is the task's.
    pub fn padded_task_tokens<'t>(&self, tokens: &'t [u32]) -> impl Iterator<Item = (i64, u8)> + use<'t> {
        let pad = self.pad_token_id;
        (0..self.tokenizer_max_length)
            .map(move |p| (i64::from(tokens.get(p).copied().unwrap_or(pad)), u8::from(p < tokens.len())))
    }
}

/// Describes a shard; stored inside it (safetensors metadata) and in the sidecar file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ShardManifest {
    pub format: String,
    pub client_index: usize,
    pub partition: PartitionConfig,
    pub robot_type: Option<String>,
    pub fps: u32,
    /// Camera feature keys, in tensor order.
    pub cameras: Vec<String>,
    pub image_width: u32,
    pub image_height: u32,
    pub state_dim: usize,
    pub action_dim: usize,
    pub num_frames: usize,
    pub train_episodes: Vec<usize>,
    pub held_out_episodes: Vec<usize>,
    /// Task strings; `task_index` values index this list.
    pub tasks: Vec<String>,
    pub tokenized: bool,
    pub tokenizer_max_length: usize,
    /// SHA-256 (hex) over the tensors in name order (name, dtype, shape, bytes).
    pub content_sha256: String,
}

/// The sidecar `<name>.manifest.json`: what a browser fetches first.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ShardFileManifest {
    /// File name of the shard, next to this manifest.
    pub file: String,
    pub file_bytes: u64,
    pub file_sha256: String,
    pub manifest: ShardManifest,
}

/// SHA-256 over (name, dtype, shape, bytes) of each tensor, in name order: independent of file layout.
pub(super) fn content_hash<'a>(tensors: impl Iterator<Item = (&'a str, Dtype, &'a [usize], &'a [u8])>) -> String {
    let mut sorted: Vec<_> = tensors.collect();
    sorted.sort_by(|a, b| a.0.cmp(b.0));
    let mut hasher = Sha256::new();
    for (name, dtype, shape, data) in sorted {
        hasher.update(name.as_bytes());
        hasher.update([0]);
        hasher.update(format!("{dtype:?}").as_bytes());
        for d in shape {
            hasher.update((*d as u64).to_le_bytes());
        }
        hasher.update((data.len() as u64).to_le_bytes());
        hasher.update(data);
    }
    hex(&hasher.finalize())
}

pub(super) fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// `client-000.safetensors` -> `client-000.manifest.json`.
pub fn sidecar_path(shard: &Path) -> PathBuf {
    shard.with_extension("manifest.json")
}
