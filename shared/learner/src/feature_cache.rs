//! The frozen-feature cache. With the backbone frozen (LeRobot's default `train_expert_only`), a training row's
//! context keys and values (its camera frames through the vision tower and the connector, then with its task's
//! tokens through every text layer: ~93% of a step's FLOPs at the `base` size) never change, so they are computed
//! on the row's first batch and reused by every later step and round; a step then runs only the state token row
//! and the expert. Kept in memory within a byte budget; natively, rows beyond it spill to files within a second
//! budget ([`FeatureCache::with_spill`]), in a directory named by the content hashes of the frozen weights and of
//! the shard, so that nothing computed for other weights or data is ever read back (and a restarted volunteer
//! finds its rows again). Rows beyond both are computed afresh each time.

use std::collections::HashMap;
#[cfg(not(target_arch = "wasm32"))]
use std::path::{Path, PathBuf};

use fedvla_policy::vlm_with_expert::ContextKv;
use fedvla_policy::{Batch, PolicyError, Trainer};

/// Default budgets: memory (what a volunteer gives the cache) and, natively, files.
pub const DEFAULT_CACHE_BYTES: usize = if cfg!(target_arch = "wasm32") { 512 << 20 } else { 1 << 30 };
pub const DEFAULT_SPILL_BYTES: u64 = 8 << 30;

/// Context keys and values by shard row.
pub struct FeatureCache {
    rows: HashMap<usize, ContextKv>,
    bytes: usize,
    budget: usize,
    #[cfg(not(target_arch = "wasm32"))]
    spill: Option<Spill>,
    /// Rows served from the cache (memory or files), and rows computed (kept or not), since it was made.
    pub hits: u64,
    pub misses: u64,
}

impl FeatureCache {
    pub fn new(budget_bytes: usize) -> Self {
        Self {
            rows: HashMap::new(),
            bytes: 0,
            budget: budget_bytes,
            #[cfg(not(target_arch = "wasm32"))]
            spill: None,
            hits: 0,
            misses: 0,
        }
    }

    /// Bytes held in memory.
    pub fn bytes(&self) -> usize {
        self.bytes
    }

    /// The context of `batch`, the batch of shard rows `rows` (in its order): each row's kept keys and values, the
    /// others computed one sample at a time (and kept while a budget allows), stacked to the batch's context
    /// length.
    pub fn context(&mut self, trainer: &Trainer, rows: &[usize], batch: &Batch) -> Result<ContextKv, PolicyError> {
        let mut fresh: HashMap<usize, ContextKv> = HashMap::new();
        for (sample, &row) in rows.iter().enumerate() {
            if self.rows.contains_key(&row) || fresh.contains_key(&row) {
                self.hits += 1;
                continue;
            }
            #[cfg(not(target_arch = "wasm32"))]
            if let Some(context) = self.spill.as_ref().and_then(|s| s.load(row, trainer.device())) {
                self.hits += 1;
                fresh.insert(row, context);
                continue;
            }
            self.misses += 1;
            let context = trainer.context_kv(&batch.rows(&[sample]))?;
            if self.bytes + context.bytes() <= self.budget {
                self.bytes += context.bytes();
                self.rows.insert(row, context);
                continue;
            }
            #[cfg(not(target_arch = "wasm32"))]
            if let Some(spill) = &mut self.spill {
                spill.store(row, &context);
            }
            fresh.insert(row, context);
        }
        let contexts: Vec<&ContextKv> =
            rows.iter().map(|row| self.rows.get(row).or_else(|| fresh.get(row)).expect("computed above")).collect();
        Ok(ContextKv::stack(&contexts))
    }
}

#[cfg(not(target_arch = "wasm32"))]
impl FeatureCache {
    /// Rows beyond the memory budget go to files in `base/<frozen>-<shard>/` (the content hashes of the frozen
    /// weights and of the shard), at most `budget_bytes` of them; rows a previous trainer of the same weights
    /// and shard left there are read back.
    pub fn with_spill(mut self, base: &Path, frozen: &str, shard: &str, budget_bytes: u64) -> Self {
        let short = |hash: &str| hash.chars().filter(char::is_ascii_alphanumeric).take(16).collect::<String>();
        let dir = base.join(format!("{}-{}", short(frozen), short(shard)));
        self.spill = Some(Spill::open(dir, budget_bytes));
        self
    }

    /// Bytes in spill files.
    pub fn spilled_bytes(&self) -> u64 {
        self.spill.as_ref().map_or(0, |s| s.bytes)
    }
}

/// Spilled rows: `row_<N>.f32`, a header of four little-endian u32 (layers, context length, KV heads, head
/// dimension) and then, per layer, the keys' and the values' f32 values.
#[cfg(not(target_arch = "wasm32"))]
struct Spill {
    dir: PathBuf,
    budget: u64,
    bytes: u64,
    rows: std::collections::HashSet<usize>,
}

#[cfg(not(target_arch = "wasm32"))]
impl Spill {
    fn open(dir: PathBuf, budget: u64) -> Self {
        let mut spill = Self { dir, budget, bytes: 0, rows: Default::default() };
        for entry in std::fs::read_dir(&spill.dir).into_iter().flatten().flatten() {
            let name = entry.file_name();
            let row = name.to_str().and_then(|n| n.strip_prefix("row_")?.strip_suffix(".f32")?.parse().ok());
            if let (Some(row), Ok(meta)) = (row, entry.metadata()) {
                spill.rows.insert(row);
                spill.bytes += meta.len();
            }
        }
        spill
    }

    fn path(&self, row: usize) -> PathBuf {
        self.dir.join(format!("row_{row}.f32"))
    }

    /// Writes `context` as row `row` when the budget allows; a failed write only costs the row its file.
    fn store(&mut self, row: usize, context: &ContextKv) {
        let Some(first) = context.keys.first() else { return };
        let [_, len, heads, dim] = first.dims();
        let mut bytes = Vec::with_capacity(16 + context.bytes());
        for n in [context.keys.len(), len, heads, dim] {
            bytes.extend_from_slice(&(n as u32).to_le_bytes());
        }
        for (k, v) in context.keys.iter().zip(&context.values) {
            for t in [k, v] {
                let Ok(values) = t.to_data().convert::<f32>().try_into_vec::<f32>() else { return };
                bytes.extend(values.iter().flat_map(|x| x.to_le_bytes()));
            }
        }
        if self.bytes + bytes.len() as u64 > self.budget {
            return;
        }
        let (path, tmp) = (self.path(row), self.dir.join(format!(".row_{row}.tmp")));
        let written = std::fs::create_dir_all(&self.dir)
            .and_then(|()| std::fs::write(&tmp, &bytes))
            .and_then(|()| std::fs::rename(&tmp, &path));
        match written {
            Ok(()) => {
                self.bytes += bytes.len() as u64;
                self.rows.insert(row);
            }
            Err(e) => {
                let _ = std::fs::remove_file(&tmp);
                eprintln!("feature cache: {} not written ({e}); the row will be computed again", path.display());
            }
        }
    }

    /// Row `row`'s keys and values on `device`, if its file is there and whole.
    fn load(&self, row: usize, device: &burn::tensor::Device) -> Option<ContextKv> {
        use burn::tensor::{Tensor, TensorData};
        if !self.rows.contains(&row) {
            return None;
        }
        let bytes = std::fs::read(self.path(row)).ok()?;
        let header: Vec<usize> =
            bytes.get(..16)?.chunks_exact(4).map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as usize).collect();
        let (layers, shape) = (header[0], [1, header[1], header[2], header[3]]);
        let per = shape.iter().product::<usize>();
        let values: Vec<f32> =
            bytes[16..].chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect();
        if values.len() != 2 * layers * per {
            return None;
        }
        let tensor =
            |i: usize| Tensor::<4>::from_data(TensorData::new(values[i * per..(i + 1) * per].to_vec(), shape), device);
        Some(ContextKv {
            keys: (0..layers).map(|n| tensor(2 * n)).collect(),
            values: (0..layers).map(|n| tensor(2 * n + 1)).collect(),
        })
    }
}
