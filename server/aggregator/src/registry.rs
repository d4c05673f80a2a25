//! Who trains on which shard: what a workload offers volunteers ([`VolunteerOffer`]: its shards with their
//! training examples, the policy, the frozen weights, what an own dataset must match) and the registry of volunteer names, their shards and the
//! client ids handed out ([`Volunteers`]), bounded, and persisted in the run directory (`volunteers.json`) so a
//! restarted server keeps every volunteer on its shard and never hands out an id twice.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::{Mutex, MutexGuard};

use bytes::Bytes;
use fedvla_federation::protocol::MAX_NAME_BYTES;
use fedvla_federation::{DatasetSignature, ErrorCode, NormalizationStats, OwnDataset, RolloutTasks, WorkloadKind};
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use crate::records::DataSource;
use crate::run_dir::{RunDir, RunDirError, write_atomic};

/// The registry's file in the run directory.
pub const VOLUNTEERS_FILE: &str = "volunteers.json";

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
    /// The frozen tensors as safetensors, when the workload has any.
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
            Self::UnknownShard { .. } | Self::NoFile { .. } => ErrorCode::UnknownShard,
            Self::NoOwnData | Self::IncompatibleDataset(_) => ErrorCode::IncompatibleDataset,
        }
    }
}

/// Checks a volunteer name: it keys the shard registry and appears in logs, metrics and the console.
pub fn check_name(name: &str) -> Result<(), VolunteerError> {
    if name.is_empty() || name.len() > MAX_NAME_BYTES || name.chars().any(char::is_control) {
        return Err(VolunteerError::InvalidName { len: name.len() });
    }
    Ok(())
}

/// Which shard each named volunteer was given and which client ids are spent: `volunteers.json` in the run
/// directory, so a restarted server keeps both.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Registry {
    /// The next shard handed out round-robin.
    pub next_shard: usize,
    /// Client ids below this were (or may have been) handed out.
    pub reserved_client_ids: u64,
    /// Shard by volunteer name, with the order in which names were first bound (the oldest is pruned first).
    pub assignments: BTreeMap<String, Assignment>,
    /// Counter behind `Assignment::order`.
    pub bindings: u64,
    /// The next client id (not persisted: a restart continues after the reservation).
    #[serde(skip)]
    next_client_id: u64,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Assignment {
    pub shard: usize,
    pub order: u64,
}

/// The offer as served: the frozen weights' content tag, and the registry of names, shards and client ids
/// (round-robin, sticky by name, at most `max_names` names).
pub struct Volunteers {
    offer: VolunteerOffer,
    /// Hex SHA-256 prefix of the frozen safetensors; part of their URL.
    frozen_tag: Option<String>,
    registry: Mutex<Registry>,
    max_names: usize,
    /// The most an own dataset's updates weigh.
    own_data_max_examples: u64,
    run_dir: RunDir,
    /// Held while the registry is written, so the last write is the newest state.
    writing: Mutex<()>,
}

impl Volunteers {
    /// The volunteers of the run in `run_dir`, continuing its saved registry if it has one; own datasets weigh at
    /// most `own_data_max_examples` (0: as much as the largest shard).
    pub fn new(
        offer: VolunteerOffer,
        run_dir: RunDir,
        max_names: usize,
        own_data_max_examples: u64,
    ) -> Result<Self, RunDirError> {
        let frozen_tag = offer.frozen.as_ref().map(|bytes| {
            let digest = Sha256::digest(bytes);
            digest[..8].iter().map(|b| format!("{b:02x}")).collect()
        });
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
        let own_data_max_examples = match own_data_max_examples {
            0 => offer.shards.iter().map(|s| s.train_examples).max().unwrap_or(0),
            cap => cap,
        };
        Ok(Self {
            offer,
            frozen_tag,
            registry: Mutex::new(registry),
            max_names,
            own_data_max_examples,
            run_dir,
            writing: Mutex::default(),
        })
    }

    /// The shard of volunteer `name`: `requested` when given (it becomes the name's shard), else the name's
    /// shard, else the next one round-robin; `None` when the workload offers no shards. Also says whether the
    /// registry changed (and so should be persisted).
    pub fn assign(
        &self,
        name: Option<&str>,
        requested: Option<usize>,
    ) -> Result<(Option<ShardBinding>, bool), VolunteerError> {
        if let Some(name) = name {
            check_name(name)?;
        }
        let count = self.offer.shards.len();
        if let Some(index) = requested.filter(|&i| i >= count) {
            return Err(VolunteerError::UnknownShard { index, count });
        }
        if count == 0 {
            return Ok((None, false));
        }
        let mut registry = self.registry();
        let (index, changed) = match name {
            Some(name) => {
                let current = registry.assignments.get(name).map(|a| a.shard);
                let index = match (requested, current) {
                    (Some(index), _) | (None, Some(index)) => index,
                    (None, None) => registry.round_robin(count),
                };
                (index, registry.bind(name, index, self.max_names))
            }
            None => (requested.unwrap_or_else(|| registry.round_robin(count)), false),
        };
        Ok((Some(ShardBinding { index, train_examples: self.offer.shards[index].train_examples }), changed))
    }

    /// A joining client: its (never reused) id, what it trains on (its own dataset, checked against the run's,
    /// or the shard [`Volunteers::assign`] picks), and whether the registry must be persisted before the client is
    /// welcomed.
    pub fn join(
        &self,
        name: &str,
        requested: Option<u32>,
        own: Option<&OwnDataset>,
    ) -> Result<(u64, Option<DataSource>, bool), VolunteerError> {
        let (data, changed) = match own {
            Some(own) => {
                check_name(name)?;
                (Some(self.own_data(own)?), false)
            }
            None => {
                let (shard, changed) = self.assign(Some(name), requested.map(|s| s as usize))?;
                let data = shard.map(|s| DataSource::Shard { index: s.index, examples: s.train_examples });
                (data, changed)
            }
        };
        let mut registry = self.registry();
        let id = registry.next_client_id;
        registry.next_client_id += 1;
        Ok((id, data, changed || registry.next_client_id + CLIENT_ID_BLOCK / 2 >= registry.reserved_client_ids))
    }

    /// An own dataset, if it fits the run: weighed by its claimed training examples, at most the cap.
    fn own_data(&self, own: &OwnDataset) -> Result<DataSource, VolunteerError> {
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

    /// Hex SHA-256 prefix of the frozen safetensors: part of their URL, so caches never go stale.
    pub fn frozen_tag(&self) -> Option<&str> {
        self.frozen_tag.as_deref()
    }
}

impl Registry {
    fn round_robin(&mut self, count: usize) -> usize {
        let index = self.next_shard % count;
        self.next_shard = (index + 1) % count;
        index
    }

    /// Records `name`'s shard, dropping the name bound first when the registry is full; false when the name
    /// already had that shard.
    fn bind(&mut self, name: &str, shard: usize, max_names: usize) -> bool {
        if let Some(a) = self.assignments.get_mut(name) {
            return std::mem::replace(&mut a.shard, shard) != shard;
        }
        if self.assignments.len() >= max_names.max(1) {
            let oldest = self.assignments.iter().min_by_key(|(_, a)| a.order).map(|(n, _)| n.clone());
            if let Some(oldest) = oldest {
                tracing::info!(name = %oldest, max_names, "volunteer registry full: forgetting the oldest name");
                self.assignments.remove(&oldest);
            }
        }
        self.bindings += 1;
        self.assignments.insert(name.to_owned(), Assignment { shard, order: self.bindings });
        true
    }
}
