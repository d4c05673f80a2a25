//! Client shards: one client's episodes packed into a single safetensors file for the browser, with
//! images already resized to the policy's input size (u8), state, the per-frame action table with
//! episode boundaries (clients cut action chunks themselves, padding like LeRobot), task token ids,
//! normalization stats, and a JSON manifest. The manifest rides in the file's metadata together with
//! a SHA-256 of the tensor contents; a sidecar `<name>.manifest.json` adds the file size and the
//! SHA-256 of the whole file, so a browser can show progress and verify its download.
//!
//! Tensors (F frames, E episodes, T tasks, L tokens, D joints):
//! `observation.images.<cam>` u8 [F,H,W,3]; `observation.state`, `action` f32 [F,D];
//! `frame_index`, `task_index` i64 [F] (task ids index `manifest.tasks`);
//! `episodes` i64 [E,4] = (dataset episode index, first row, end row, held out 0/1);
//! `task_tokens` i64 [T,L] and `task_attention_mask` u8 [T,L] (when a tokenizer was given);
//! `stats/<feature>/<stat>` f32 [D] for `observation.state` and `action`.

#[cfg(feature = "read")]
mod build;
mod format;

use std::collections::BTreeMap;
use std::path::Path;

use safetensors::tensor::{Dtype, SafeTensors};
use sha2::{Digest, Sha256};

use crate::error::{DataError, Result};

#[cfg(feature = "io")]
pub use build::build_shard;
#[cfg(feature = "read")]
pub use build::pack_shard;
use format::{MANIFEST_KEY, content_hash, hex};
pub use format::{SHARD_FORMAT, ShardFileManifest, ShardManifest, ShardSpec, Tokenizer, sidecar_path};

/// One episode inside a shard: rows `[start, end)`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ShardEpisode {
    pub episode_index: usize,
    pub start: usize,
    pub end: usize,
    pub held_out: bool,
}

/// A shard read back and verified.
#[derive(Debug, Clone, PartialEq)]
pub struct ClientShard {
    pub manifest: ShardManifest,
    /// By camera key: u8 [F, H, W, 3].
    pub images: BTreeMap<String, Vec<u8>>,
    pub state: Vec<f32>,
    pub action: Vec<f32>,
    pub frame_index: Vec<i64>,
    pub task_index: Vec<i64>,
    pub episodes: Vec<ShardEpisode>,
    /// [T, L] token ids and attention mask, when tokenized.
    pub task_tokens: Option<(Vec<i64>, Vec<u8>)>,
    /// `stats[feature][stat]`.
    pub stats: BTreeMap<String, BTreeMap<String, Vec<f32>>>,
}

/// Checks a downloaded shard file against its sidecar manifest (size, then SHA-256 of the whole file).
pub fn verify_shard_file(path: &Path, expected: &ShardFileManifest) -> Result<()> {
    let bytes = std::fs::read(path).map_err(|e| DataError::io(path, e))?;
    verify_shard_bytes(path, &bytes, expected)
}

/// [`verify_shard_file`] for a shard already in memory (a browser's download); `path` only names the
/// source in errors.
pub fn verify_shard_bytes(path: &Path, bytes: &[u8], expected: &ShardFileManifest) -> Result<()> {
    if bytes.len() as u64 != expected.file_bytes {
        return Err(DataError::BadShard {
            path: path.to_path_buf(),
            reason: format!("{} bytes, the manifest says {}", bytes.len(), expected.file_bytes),
        });
    }
    let actual = hex(&Sha256::digest(bytes));
    if actual != expected.file_sha256 {
        return Err(DataError::ChecksumMismatch {
            path: path.to_path_buf(),
            expected: expected.file_sha256.clone(),
            actual,
        });
    }
    Ok(())
}

impl ClientShard {
    /// Reads a shard and verifies its content checksum against its embedded manifest.
    pub fn read(path: &Path) -> Result<Self> {
        let bytes = std::fs::read(path).map_err(|e| DataError::io(path, e))?;
        Self::from_bytes(path, &bytes)
    }

    /// Parses shard bytes (`path` only names the source in errors).
    pub fn from_bytes(path: &Path, bytes: &[u8]) -> Result<Self> {
        let bad = |reason: String| DataError::BadShard { path: path.to_path_buf(), reason };
        let (_, metadata) = SafeTensors::read_metadata(bytes).map_err(|e| bad(e.to_string()))?;
        let manifest_json = metadata
            .metadata()
            .as_ref()
            .and_then(|m| m.get(MANIFEST_KEY))
            .ok_or_else(|| bad("no manifest in the metadata".into()))?;
        let manifest: ShardManifest = serde_json::from_str(manifest_json).map_err(|e| bad(format!("manifest: {e}")))?;
        if manifest.format != SHARD_FORMAT {
            return Err(bad(format!("format {:?}, expected {SHARD_FORMAT:?}", manifest.format)));
        }
        let st = SafeTensors::deserialize(bytes).map_err(|e| bad(e.to_string()))?;
        let views = st.tensors();
        let actual = content_hash(views.iter().map(|(n, v)| (n.as_str(), v.dtype(), v.shape(), v.data())));
        if actual != manifest.content_sha256 {
            return Err(DataError::ChecksumMismatch {
                path: path.to_path_buf(),
                expected: manifest.content_sha256.clone(),
                actual,
            });
        }
        let raw = |name: &str, dtype: Dtype| -> Result<&[u8]> {
            let view = views
                .iter()
                .find(|(n, _)| n == name)
                .map(|(_, v)| v)
                .ok_or_else(|| bad(format!("tensor {name} missing")))?;
            if view.dtype() != dtype {
                return Err(bad(format!("tensor {name} is {:?}, expected {dtype:?}", view.dtype())));
            }
            Ok(view.data())
        };
        let f32s = |name: &str| -> Result<Vec<f32>> {
            Ok(raw(name, Dtype::F32)?.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect())
        };
        let i64s = |name: &str| -> Result<Vec<i64>> {
            Ok(raw(name, Dtype::I64)?
                .chunks_exact(8)
                .map(|c| i64::from_le_bytes(c.try_into().unwrap_or([0; 8])))
                .collect())
        };
        let images =
            manifest.cameras.iter().map(|c| Ok((c.clone(), raw(c, Dtype::U8)?.to_vec()))).collect::<Result<_>>()?;
        let episodes = i64s("episodes")?
            .chunks_exact(4)
            .map(|r| ShardEpisode {
                episode_index: r[0] as usize,
                start: r[1] as usize,
                end: r[2] as usize,
                held_out: r[3] != 0,
            })
            .collect();
        let task_tokens = if manifest.tokenized {
            Some((i64s("task_tokens")?, raw("task_attention_mask", Dtype::U8)?.to_vec()))
        } else {
            None
        };
        let mut stats: BTreeMap<String, BTreeMap<String, Vec<f32>>> = BTreeMap::new();
        for (name, _) in &views {
            if let Some((feature, stat)) = name.strip_prefix("stats/").and_then(|s| s.rsplit_once('/')) {
                stats.entry(feature.to_string()).or_default().insert(stat.to_string(), f32s(name)?);
            }
        }
        Ok(ClientShard {
            state: f32s("observation.state")?,
            action: f32s("action")?,
            frame_index: i64s("frame_index")?,
            task_index: i64s("task_index")?,
            images,
            episodes,
            task_tokens,
            stats,
            manifest,
        })
    }

    /// Row `row`'s `horizon` actions ahead within its episode, past-the-end steps repeating the last
    /// action, and the matching `action_is_pad` flags (LeRobot's chunk semantics).
    pub fn action_chunk(&self, row: usize, horizon: usize) -> Option<(Vec<f32>, Vec<bool>)> {
        let episode = self.episodes.iter().find(|e| e.start <= row && row < e.end)?;
        let d = self.manifest.action_dim;
        let mut values = Vec::with_capacity(horizon * d);
        let mut pad = Vec::with_capacity(horizon);
        for k in 0..horizon {
            let r = (row + k).min(episode.end - 1);
            values.extend_from_slice(&self.action[r * d..(r + 1) * d]);
            pad.push(row + k >= episode.end);
        }
        Some((values, pad))
    }

    /// Camera `camera`'s image at `row` (u8 HWC at the shard's image size).
    pub fn image(&self, camera: &str, row: usize) -> Option<&[u8]> {
        let size = self.manifest.image_width as usize * self.manifest.image_height as usize * 3;
        self.images.get(camera)?.get(row * size..(row + 1) * size)
    }
}
