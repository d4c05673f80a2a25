//! Who trains on which shard: what a workload offers volunteers ([`VolunteerOffer`]: its shards with their
//! training examples, the policy, the frozen weights, what an own dataset must match, and the setup a volunteer is
//! admitted with) and the registry of volunteers ([`Volunteers`]): each public key's name and shard, and the client
//! ids handed out, bounded, and persisted in the run directory (`volunteers.json`) so a restarted server keeps
//! every key on its shard and never hands out an id twice. A name belongs to the first key that uses it, a shard
//! asked for is granted only when no other key holds it, and a closed federation admits only the keys of its
//! allow-list (`allowed-keys`).

use std::collections::{BTreeMap, HashMap, HashSet};
use std::path::{Path, PathBuf};
use std::sync::{Mutex, MutexGuard};

use bytes::Bytes;
use fedvla_federation::identity::{PUBLIC_KEY_BYTES, from_hex, to_hex};
use fedvla_federation::protocol::MAX_NAME_BYTES;
use fedvla_federation::{
    DatasetSignature, ErrorCode, NormalizationStats, OwnDataset, PROTOCOL_VERSION, RolloutTasks, VolunteerSetup,
    WorkloadKind, routes,
};
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use crate::records::DataSource;
use crate::run_dir::{RunDir, RunDirError, write_atomic};

/// The registry's file in the run directory.
pub const VOLUNTEERS_FILE: &str = "volunteers.json";

/// The frozen weights volunteers download, in the run directory.
pub const FROZEN_FILE: &str = "frozen.safetensors";

/// Client ids are reserved (and the reservation persisted) this many at a time, so a restarted server never hands
/// out an id it gave before (the `evaluate/round_N/client_K/` directories stay one client's each).
const CLIENT_ID_BLOCK: u64 = 1024;

/// One shard a workload offers: its file (none for shards a client generates from its index, as linreg's) and the
/// training examples in it, which weigh every update of the client training on it.
#[derive(Debug, Clone, PartialEq)]
pub struct ShardOffer {
    pub file: Option<PathBuf>,
    pub train_examples: u64,
}

/// What a workload offers volunteers.
#[derive(Debug, Clone)]
pub struct VolunteerOffer {
    pub workload: WorkloadKind,
    /// Client shards by shard index (a file's `.manifest.json` sidecar beside it).
    pub shards: Vec<ShardOffer>,
    /// The workload's configuration for volunteers (see [`fedvla_federation::VolunteerSetup::policy`]).
    pub policy: serde_json::Value,
    /// The frozen tensors as safetensors, when the workload has any: [`Volunteers::new`] writes them into the run
    /// directory ([`FROZEN_FILE`]) and lets these bytes go.
    pub frozen: Option<Bytes>,
    /// The sim tasks rollouts cycle through, with their instructions' token ids.
    pub rollout_tasks: RolloutTasks,
    /// What a volunteer's own dataset must match; `None`: the run takes no own datasets.
    pub signature: Option<DatasetSignature>,
    /// The dataset's normalisation statistics, when the workload normalises.
    pub norm_stats: Option<NormalizationStats>,
    /// The run's tokenizer (`tokenizer.json`), for volunteers that tokenize their own tasks.
    pub tokenizer: Option<Bytes>,
}

impl VolunteerOffer {
    /// An offer of `shards` and nothing else: no configuration, no weights to download, no own datasets.
    pub fn shards_only(workload: WorkloadKind, shards: Vec<ShardOffer>) -> Self {
        Self {
            workload,
            shards,
            policy: serde_json::Value::Null,
            frozen: None,
            rollout_tasks: RolloutTasks::default(),
            signature: None,
            norm_stats: None,
            tokenizer: None,
        }
    }
}

/// The shard a joined client trains on, as the server knows it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ShardBinding {
    pub index: usize,
    /// The weight of the client's updates.
    pub train_examples: u64,
}

/// Why a volunteer was refused.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum VolunteerError {
    #[error("volunteer name of {len} bytes: names are 1 to {MAX_NAME_BYTES} bytes without control characters")]
    InvalidName { len: usize },
    #[error("the name {name:?} belongs to another key: choose another name (or use that name's key)")]
    NameTaken { name: String },
    #[error("shard {index} is held by another key: leave the shard to the server")]
    ShardTaken { index: usize },
    #[error("this federation admits only the keys of its allow-list, and not this one")]
    NotAllowed,
    #[error("no shard {index}: this run has {count}")]
    UnknownShard { index: usize, count: usize },
    #[error("shard {index} has no file: clients generate it from its index")]
    NoFile { index: usize },
    #[error("this run takes no own datasets (its workload has no dataset to match them against)")]
    NoOwnData,
    #[error("{0}")]
    IncompatibleDataset(String),
}

impl VolunteerError {
    pub fn code(&self) -> ErrorCode {
        match self {
            Self::InvalidName { .. } => ErrorCode::InvalidName,
            Self::NameTaken { .. } => ErrorCode::NameTaken,
            Self::ShardTaken { .. } => ErrorCode::ShardTaken,
            Self::NotAllowed => ErrorCode::Unauthorized,
            Self::UnknownShard { .. } | Self::NoFile { .. } => ErrorCode::UnknownShard,
            Self::NoOwnData | Self::IncompatibleDataset(_) => ErrorCode::IncompatibleDataset,
        }
    }
}

/// Checks a volunteer name: it is one key's, and appears in logs, metrics and the console.
pub fn check_name(name: &str) -> Result<(), VolunteerError> {
    if name.is_empty() || name.len() > MAX_NAME_BYTES || name.chars().any(char::is_control) {
        return Err(VolunteerError::InvalidName { len: name.len() });
    }
    Ok(())
}

/// Each key's name and shard, and which client ids are spent: `volunteers.json` in the run directory, so a
/// restarted server keeps both. (A registry of protocol 5, keyed by names, resumes with its client ids and without
/// its names: no key proved them.)
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Registry {
    /// The next shard handed out round-robin.
    pub next_shard: usize,
    /// Client ids below this were (or may have been) handed out.
    pub reserved_client_ids: u64,
    /// By public key (hex): the volunteer's name and shard, and the order in which keys were first bound (the
    /// oldest is pruned first).
    #[serde(default)]
    pub volunteers: BTreeMap<String, Binding>,
    /// Counter behind `Binding::order`.
    pub bindings: u64,
    /// The next client id (not persisted: a restart continues after the reservation).
    #[serde(skip)]
    next_client_id: u64,
    /// The key of each name in `volunteers`.
    #[serde(skip)]
    key_by_name: HashMap<String, String>,
}

/// What a key is bound to.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Binding {
    pub name: String,
    /// `None` for a volunteer on its own dataset (or a workload without shards).
    pub shard: Option<usize>,
    pub order: u64,
}

/// What a proven key is admitted with.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Admitted {
    /// Never handed out before, in this run.
    pub client_id: u64,
    /// The shard bound to the key; `None` for a volunteer on its own dataset, or a workload without shards.
    pub shard: Option<ShardBinding>,
    /// Whether the registry changed (or needs the next block of client ids) and must be persisted before the
    /// client is admitted.
    pub persist: bool,
}

/// The frozen weights as served: a file of the run directory, streamed to each volunteer that asks, so that the
/// server holds no copy of them in memory (at full size 0.7 GB in bf16, for the whole run).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FrozenFile {
    pub path: PathBuf,
    pub len: u64,
    /// Hex SHA-256 prefix of the file; part of its URL, so caches never go stale.
    pub tag: String,
}

impl FrozenFile {
    /// Writes `bytes` atomically to `path` and tags them.
    fn write(path: PathBuf, bytes: &[u8]) -> Result<Self, RunDirError> {
        write_atomic(&path, bytes)?;
        let tag = to_hex(&Sha256::digest(bytes)[..8]);
        Ok(Self { path, len: bytes.len() as u64, tag })
    }
}

/// The offer as served: the frozen weights' file, the registry of keys, names, shards and client ids (round-robin,
/// sticky by key, at most `max_names` keys), and the allow-list of a closed federation.
pub struct Volunteers {
    offer: VolunteerOffer,
    frozen: Option<FrozenFile>,
    registry: Mutex<Registry>,
    max_names: usize,
    /// The public keys (lowercase hex) a closed federation admits; `None`: any key.
    allowed_keys: Option<HashSet<String>>,
    /// The most an own dataset's updates weigh.
    own_data_max_examples: u64,
    run_dir: RunDir,
    /// Held while the registry is written, so the last write is the newest state.
    writing: Mutex<()>,
}

impl Volunteers {
    /// The volunteers of the run in `run_dir`, continuing its saved registry if it has one; own datasets weigh at
    /// most `own_data_max_examples` (0: as much as the largest shard). The offer's frozen weights are written into
    /// the run directory and served from there.
    pub fn new(
        mut offer: VolunteerOffer,
        run_dir: RunDir,
        max_names: usize,
        own_data_max_examples: u64,
    ) -> Result<Self, RunDirError> {
        let frozen = offer.frozen.take().map(|bytes| FrozenFile::write(run_dir.path().join(FROZEN_FILE), &bytes));
        let frozen = frozen.transpose()?;
        let path = run_dir.path().join(VOLUNTEERS_FILE);
        let mut registry: Registry = match std::fs::read(&path) {
            Ok(bytes) => serde_json::from_slice(&bytes).map_err(|e| RunDirError::Metrics {
                path: path.clone(),
                line: e.line(),
                message: e.to_string(),
            })?,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Registry::default(),
            Err(source) => return Err(RunDirError::Io { path, source }),
        };
        registry.next_client_id = registry.reserved_client_ids.max(1);
        registry.key_by_name = registry.volunteers.iter().map(|(key, b)| (b.name.clone(), key.clone())).collect();
        let own_data_max_examples = match own_data_max_examples {
            0 => offer.shards.iter().map(|s| s.train_examples).max().unwrap_or(0),
            cap => cap,
        };
        Ok(Self {
            offer,
            frozen,
            registry: Mutex::new(registry),
            max_names,
            allowed_keys: None,
            own_data_max_examples,
            run_dir,
            writing: Mutex::default(),
        })
    }

    /// Admits only the public keys of `keys` (see [`read_allowed_keys`]).
    pub fn with_allowed_keys(mut self, keys: HashSet<String>) -> Self {
        self.allowed_keys = Some(keys);
        self
    }

    /// Admits the volunteer whose proven key is `key` (hex) as `name`: a name another key holds is refused, and a
    /// key outside the allow-list. A volunteer on a shard (`own_dataset` false) trains on `requested` when it
    /// names one no other key holds, else on its key's shard, else a new key gets the next one round-robin. Each
    /// admission gets a client id never handed out before.
    pub fn admit(
        &self,
        key: &str,
        name: &str,
        requested: Option<u32>,
        own_dataset: bool,
    ) -> Result<Admitted, VolunteerError> {
        check_name(name)?;
        if self.allowed_keys.as_ref().is_some_and(|allowed| !allowed.contains(key)) {
            return Err(VolunteerError::NotAllowed);
        }
        let count = self.offer.shards.len();
        let requested = requested.map(|s| s as usize);
        if let Some(index) = requested.filter(|&i| i >= count) {
            return Err(VolunteerError::UnknownShard { index, count });
        }
        let mut registry = self.registry();
        if registry.key_by_name.get(name).is_some_and(|holder| holder != key) {
            return Err(VolunteerError::NameTaken { name: name.to_owned() });
        }
        let current = registry.volunteers.get(key).and_then(|b| b.shard);
        let shard = match (requested, current) {
            _ if own_dataset || count == 0 => current,
            (Some(index), _) if registry.held_by_another(index, key) => {
                return Err(VolunteerError::ShardTaken { index });
            }
            (Some(index), _) | (None, Some(index)) => Some(index),
            (None, None) => Some(registry.round_robin(count)),
        };
        let changed = registry.bind(key, name, shard, self.max_names);
        let client_id = registry.next_client_id;
        registry.next_client_id += 1;
        let persist = changed || registry.next_client_id + CLIENT_ID_BLOCK / 2 >= registry.reserved_client_ids;
        let shard = shard
            .filter(|_| !own_dataset)
            .map(|index| ShardBinding { index, train_examples: self.offer.shards[index].train_examples });
        Ok(Admitted { client_id, shard, persist })
    }

    /// What a volunteer admitted with `shard` is offered, at global model version `model_version`.
    pub fn setup(&self, shard: Option<ShardBinding>, model_version: u64) -> VolunteerSetup {
        let offer = &self.offer;
        let index = shard.map_or(0, |b| b.index) as u32;
        VolunteerSetup {
            protocol_version: PROTOCOL_VERSION,
            workload: offer.workload,
            shard_index: index,
            shard_count: offer.shards.len() as u32,
            shard_url: routes::shard(index),
            shard_manifest_url: routes::shard_manifest(index),
            policy: offer.policy.clone(),
            frozen_url: self.frozen.as_ref().map(|f| routes::frozen(&f.tag)),
            frozen_bytes: self.frozen.as_ref().map_or(0, |f| f.len),
            rollout_tasks: offer.rollout_tasks.clone(),
            model_version,
            tokenizer_url: offer.tokenizer.as_ref().map(|_| routes::TOKENIZER.to_owned()),
            dataset_signature: offer.signature.clone(),
        }
    }

    /// An own dataset, if it fits the run: weighed by its claimed training examples, at most the cap.
    pub fn own_data(&self, own: &OwnDataset) -> Result<DataSource, VolunteerError> {
        let run = self.offer.signature.as_ref().ok_or(VolunteerError::NoOwnData)?;
        own.signature.check_fits(run).map_err(VolunteerError::IncompatibleDataset)?;
        let weight = own.train_examples.min(self.own_data_max_examples);
        Ok(DataSource::Own { claimed_examples: own.train_examples, weight })
    }

    /// Writes the registry (`volunteers.json`), reserving the next block of client ids when the current one is
    /// half used. Blocking: call it off the async runtime.
    pub fn persist(&self) -> Result<(), RunDirError> {
        let _writing = self.writing.lock().expect("registry writer lock");
        let snapshot = {
            let mut registry = self.registry();
            if registry.next_client_id + CLIENT_ID_BLOCK / 2 >= registry.reserved_client_ids {
                registry.reserved_client_ids = registry.next_client_id + CLIENT_ID_BLOCK;
            }
            registry.clone()
        };
        let bytes = serde_json::to_vec(&snapshot).expect("the registry serializes");
        write_atomic(&self.run_dir.path().join(VOLUNTEERS_FILE), &bytes)
    }

    fn registry(&self) -> MutexGuard<'_, Registry> {
        self.registry.lock().expect("volunteer registry lock")
    }

    /// The file of shard `index`.
    pub fn shard_file(&self, index: usize) -> Result<&PathBuf, VolunteerError> {
        let count = self.offer.shards.len();
        let shard = self.offer.shards.get(index).ok_or(VolunteerError::UnknownShard { index, count })?;
        shard.file.as_ref().ok_or(VolunteerError::NoFile { index })
    }

    pub fn offer(&self) -> &VolunteerOffer {
        &self.offer
    }

    /// The frozen weights' file, when the workload has any.
    pub fn frozen(&self) -> Option<&FrozenFile> {
        self.frozen.as_ref()
    }
}

impl Registry {
    fn round_robin(&mut self, count: usize) -> usize {
        let index = self.next_shard % count;
        self.next_shard = (index + 1) % count;
        index
    }

    /// Whether a key other than `key` is bound to shard `index`.
    fn held_by_another(&self, index: usize, key: &str) -> bool {
        self.volunteers.iter().any(|(other, b)| other != key && b.shard == Some(index))
    }

    /// Binds `key` to `name` and `shard`, dropping the key bound first when the registry is full; false when
    /// nothing changed. The caller checked that no other key holds `name`.
    fn bind(&mut self, key: &str, name: &str, shard: Option<usize>, max_names: usize) -> bool {
        if let Some(b) = self.volunteers.get_mut(key) {
            if (b.name.as_str(), b.shard) == (name, shard) {
                return false;
            }
            let old = std::mem::replace(&mut b.name, name.to_owned());
            b.shard = shard;
            self.key_by_name.remove(&old);
            self.key_by_name.insert(name.to_owned(), key.to_owned());
            return true;
        }
        if self.volunteers.len() >= max_names.max(1) {
            let oldest = self.volunteers.iter().min_by_key(|(_, b)| b.order).map(|(k, _)| k.clone());
            if let Some(b) = oldest.and_then(|k| self.volunteers.remove(&k)) {
                tracing::info!(name = %b.name, max_names, "volunteer registry full: forgetting the oldest key");
                self.key_by_name.remove(&b.name);
            }
        }
        self.bindings += 1;
        self.volunteers.insert(key.to_owned(), Binding { name: name.to_owned(), shard, order: self.bindings });
        self.key_by_name.insert(name.to_owned(), key.to_owned());
        true
    }
}

/// The allow-list of a closed federation (`allowed-keys`): a file of hex Ed25519 public keys, one a line (blank
/// lines and `#` comments skipped), as lowercase hex.
pub fn read_allowed_keys(path: &Path) -> Result<HashSet<String>, RunDirError> {
    let text = std::fs::read_to_string(path).map_err(|source| RunDirError::Io { path: path.to_owned(), source })?;
    let mut keys = HashSet::new();
    for (number, line) in text.lines().enumerate() {
        let line = line.split('#').next().unwrap_or_default().trim();
        if line.is_empty() {
            continue;
        }
        let key: [u8; PUBLIC_KEY_BYTES] = from_hex("public key", line).map_err(|e| RunDirError::Metrics {
            path: path.to_owned(),
            line: number + 1,
            message: e.to_string(),
        })?;
        keys.insert(to_hex(&key));
    }
    Ok(keys)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::RunConfig;

    /// The frozen weights are written into the run directory once, tagged by their content, and served from there:
    /// the registry keeps no copy of their bytes.
    #[test]
    fn frozen_weights_are_served_from_a_file_of_the_run_directory() {
        let base = tempfile::tempdir().unwrap();
        let run_dir = RunDir::create(base.path(), &RunConfig::default()).unwrap();
        let bytes = Bytes::from((0..=255u8).cycle().take(10_000).collect::<Vec<u8>>());
        let offer = VolunteerOffer {
            frozen: Some(bytes.clone()),
            ..VolunteerOffer::shards_only(WorkloadKind::Smolvla, Vec::new())
        };
        let volunteers = Volunteers::new(offer, run_dir.clone(), 4, 0).unwrap();
        let frozen = volunteers.frozen().expect("the offer has frozen weights").clone();
        assert_eq!(frozen.path, run_dir.path().join(FROZEN_FILE));
        assert_eq!(std::fs::read(&frozen.path).unwrap(), bytes);
        assert_eq!(frozen.tag, to_hex(&Sha256::digest(&bytes)[..8]));
        assert!(volunteers.offer().frozen.is_none(), "the bytes are let go once written");
        let setup = volunteers.setup(None, 0);
        assert_eq!(setup.frozen_url, Some(routes::frozen(&frozen.tag)));
        assert_eq!(setup.frozen_bytes, bytes.len() as u64);
        // A restarted server writes the same file under the same tag.
        let offer =
            VolunteerOffer { frozen: Some(bytes), ..VolunteerOffer::shards_only(WorkloadKind::Smolvla, vec![]) };
        assert_eq!(Volunteers::new(offer, run_dir, 4, 0).unwrap().frozen(), Some(&frozen));
    }
}
