//! The frozen-feature cache. With the backbone frozen (LeRobot's default `train_expert_only`), a training row's
//! context keys and values (its camera frames through the vision tower and the connector, then with its task's
//! tokens through every text layer: ~93% of a step's FLOPs at the `base` size) never change, so they are computed
//! on the row's first batch and reused by every later step and round; a step then runs only the state token row
//! and the expert. In memory within a byte budget: rows beyond it are computed afresh each time. A cache belongs
//! to one trainer, so to one shard and one set of frozen weights, and cannot go stale.

use std::collections::HashMap;

use fedvla_policy::vlm_with_expert::ContextKv;
use fedvla_policy::{Batch, PolicyError, Trainer};

/// Default budget: what a native volunteer gives the cache.
pub const DEFAULT_CACHE_BYTES: usize = if cfg!(target_arch = "wasm32") { 512 << 20 } else { 1 << 30 };

/// Context keys and values by shard row.
pub struct FeatureCache {
    rows: HashMap<usize, ContextKv>,
    bytes: usize,
    budget: usize,
    /// Rows served from the cache, and rows computed (kept or not), since it was made.
    pub hits: u64,
    pub misses: u64,
}

impl FeatureCache {
    pub fn new(budget_bytes: usize) -> Self {
        Self { rows: HashMap::new(), bytes: 0, budget: budget_bytes, hits: 0, misses: 0 }
    }

    /// Bytes held.
    pub fn bytes(&self) -> usize {
        self.bytes
    }

    /// The context of `batch`, the batch of shard rows `rows` (in its order): each row's kept keys and values, the
    /// others computed one sample at a time (and kept while the budget allows), stacked to the batch's context
    /// length.
    pub fn context(&mut self, trainer: &Trainer, rows: &[usize], batch: &Batch) -> Result<ContextKv, PolicyError> {
        let mut fresh: HashMap<usize, ContextKv> = HashMap::new();
        for (sample, &row) in rows.iter().enumerate() {
            if self.rows.contains_key(&row) || fresh.contains_key(&row) {
                self.hits += 1;
                continue;
            }
            self.misses += 1;
            let context = trainer.context_kv(&batch.rows(&[sample]))?;
            if self.bytes + context.bytes() <= self.budget {
                self.bytes += context.bytes();
                self.rows.insert(row, context);
            } else {
                fresh.insert(row, context);
            }
        }
        let contexts: Vec<&ContextKv> =
            rows.iter().map(|row| self.rows.get(row).or_else(|| fresh.get(row)).expect("computed above")).collect();
        Ok(ContextKv::stack(&contexts))
    }
}
