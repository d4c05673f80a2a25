//! SmolVLA as a federated client's `LocalTrainer`: the trainable tensors (expert + projections)
//! are the update; the frozen backbone stays on the client. The same code runs natively and in
//! the browser; only the burn device differs.

use burn::tensor::Device;
use fedvla_federation::{
    BoxError, Capabilities, EvalOutput, LocalTrainer, NamedTensors, NormalizationStats, RolloutEpisode, RolloutOutput,
    RolloutRequest, RoundTask, TrainOutput,
};
use fedvla_policy::weights::ParamStore;
use fedvla_policy::{SmolVla, SmolVlaConfig, Trainer, WeightMap};
use rand::SeedableRng;
use rand::rngs::StdRng;
use rand::seq::SliceRandom;

use crate::examples::ShardExamples;
use crate::feature_cache::{DEFAULT_CACHE_BYTES, FeatureCache};
use crate::heldout::{HeldOut, heldout_metrics};
use crate::rollout::{Episode, EpisodeResult, SimPolicy, SimTasks, run_episode};
use crate::tensors::{into_named, to_weights};

/// Where a round's local training stands, after each step.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepProgress {
    pub step: u32,
    pub steps: u32,
    pub loss: f32,
}

/// A client's trainer over its shard.
pub struct SmolVlaTrainer {
    trainer: Trainer,
    /// The global model on the CPU without autodiff, for held-out evaluation and rollouts: it needs no reads
    /// from the training device (which a browser's GPU could only do asynchronously) and no graph. On the CPU its
    /// frozen tensors are the trainer's own.
    global_cpu: SmolVla,
    examples: ShardExamples,
    held_out: HeldOut,
    backend: String,
    /// The run's rollout tasks and their instructions' tokens; without them the client does not roll out.
    rollout_tasks: Option<SimTasks>,
    /// Each row's context keys and values, when the backbone is frozen (see [`FeatureCache`]).
    cache: Option<FeatureCache>,
}

impl SmolVlaTrainer {
    /// Poisons this client's training rows for a simulated attacker (see [`ShardExamples::shuffle_labels`]).
    pub fn shuffle_labels(&mut self, seed: u64) {
        self.examples.shuffle_labels(seed);
    }

    /// `weights` is the full initial checkpoint (frozen + trainable), which the trainer takes; `seed` drives this
    /// client's flow-matching noise and times; `backend` names the device for the server's client table.
    pub fn new(
        cfg: &SmolVlaConfig,
        weights: WeightMap,
        examples: ShardExamples,
        seed: u64,
        device: &Device,
        backend: &str,
    ) -> Result<Self, BoxError> {
        // Training on the CPU, the evaluation model shares the trainer's tensors (at the base size 1.8 GB of f32 not
        // held twice); on a GPU it keeps its own copy on the CPU.
        let cpu = Device::flex();
        let on_cpu = *device == cpu;
        let own_copy = (!on_cpu).then(|| ParamStore::upload(weights.iter(), &cpu, false));
        let trainer = Trainer::taking(cfg, weights, device, seed)?;
        Ok(Self::around(trainer, own_copy, examples, backend))
    }

    /// [`SmolVlaTrainer::new`] on the CPU (`device`, autodiff enabled) from the frozen tensors already there, in
    /// the dtype they are stored in (bf16 kept bf16: a browser's CPU fallback holds `smolvla_base`'s in 0.7 GB,
    /// not 1.4), and the trainable ones, which it takes. The evaluation model shares both with the trainer.
    pub fn on_cpu_with_frozen(
        cfg: &SmolVlaConfig,
        frozen: ParamStore,
        trainable: WeightMap,
        examples: ShardExamples,
        seed: u64,
        device: &Device,
        backend: &str,
    ) -> Result<Self, BoxError> {
        if *device != Device::flex() {
            return Err(format!("frozen tensors held once need the CPU, not {device:?}").into());
        }
        let trainer = Trainer::with_frozen(cfg, frozen, trainable, device, seed)?;
        Ok(Self::around(trainer, None, examples, backend))
    }

    /// The trainer with its evaluation model: `own_copy` (the whole model on the CPU) when training elsewhere,
    /// otherwise the trainer's own tensors.
    fn around(trainer: Trainer, own_copy: Option<ParamStore>, examples: ShardExamples, backend: &str) -> Self {
        let cfg = trainer.model.cfg.clone();
        let store = own_copy.unwrap_or_else(|| trainer.frozen_store().overlaid(&trainer.trainable_store()));
        let held_out = HeldOut::new(&examples.held_out_rows);
        Self {
            trainer,
            global_cpu: SmolVla::new(&cfg, &store),
            examples,
            held_out,
            backend: backend.into(),
            rollout_tasks: None,
            cache: cfg.backbone_frozen().then(|| FeatureCache::new(DEFAULT_CACHE_BYTES)),
        }
    }

    /// With a frozen-feature cache of `budget_bytes` (0: none, every step computes its context afresh), when the
    /// backbone is frozen.
    pub fn with_feature_cache(mut self, budget_bytes: usize) -> Self {
        let frozen = self.trainer.model.cfg.backbone_frozen();
        self.cache = (frozen && budget_bytes > 0).then(|| FeatureCache::new(budget_bytes));
        self
    }

    /// Lets the frozen-feature cache spill rows beyond its memory budget to files under `base` (see
    /// [`FeatureCache::with_spill`]); `frozen` is the frozen weights' content hash (the server names them by it).
    #[cfg(not(target_arch = "wasm32"))]
    pub fn spill_feature_cache(mut self, base: &std::path::Path, frozen: &str, budget_bytes: u64) -> Self {
        let shard = self.examples.content_sha256().to_owned();
        self.cache = self.cache.map(|cache| cache.with_spill(base, frozen, &shard, budget_bytes));
        self
    }

    /// The frozen-feature cache, when it has one.
    pub fn feature_cache(&self) -> Option<&FeatureCache> {
        self.cache.as_ref()
    }

    /// Lets this client roll the global model out in the sim when a task asks.
    pub fn with_rollouts(mut self, tasks: SimTasks) -> Self {
        self.rollout_tasks = Some(tasks);
        self
    }

    /// Its data (for [`fedvla_federation::ClientOptions::data`]).
    pub fn examples(&self) -> &ShardExamples {
        &self.examples
    }

    pub fn config(&self) -> &SmolVlaConfig {
        &self.trainer.model.cfg
    }

    /// The global model last set, as a sim policy on the CPU; `None` without the run's rollout tasks.
    pub fn sim_policy(&self) -> Result<Option<SimPolicy>, BoxError> {
        let Some(tasks) = &self.rollout_tasks else { return Ok(None) };
        Ok(Some(SimPolicy::from_model(self.global_cpu.clone(), self.examples.stats().clone(), tasks.clone())?))
    }

    /// [`LocalTrainer::train`], awaiting `after_step` after every step (the browser redraws its progress and
    /// yields to the page there).
    pub async fn train_with(
        &mut self,
        task: &RoundTask,
        mut after_step: impl AsyncFnMut(StepProgress),
    ) -> Result<TrainOutput, BoxError> {
        let rows = &self.examples.train_rows;
        if rows.is_empty() {
            return Err("this client's shard has no training episodes".into());
        }
        if !task.keep_optimizer_state {
            self.trainer.reset_optimizer();
        }
        // FedProx: the round's steps are pulled towards the global model they start from (mu 0: plain FedAvg).
        self.trainer.set_proximal(task.strategy.proximal_mu);
        let chunk = self.trainer.model.cfg.chunk_size;
        let batch_size = (task.batch_size as usize).clamp(1, rows.len());
        let mut rng = StdRng::seed_from_u64(task.seed);
        let mut order = self.examples.training_draws(task.opening_frames);
        let mut cursor = order.len();
        let mut loss_sum = 0.0;
        for step in 0..task.local_steps {
            let mut picked = Vec::with_capacity(batch_size);
            while picked.len() < batch_size {
                if cursor == order.len() {
                    order.shuffle(&mut rng);
                    cursor = 0;
                }
                picked.push(order[cursor]);
                cursor += 1;
            }
            let batch = self.examples.batch(&picked, chunk)?;
            let context = match &mut self.cache {
                Some(cache) => Some(cache.context(&self.trainer, &picked, &batch)?),
                None => None,
            };
            let loss = self.trainer.train_step_async_from(&batch, context.as_ref(), task.lr_at(step)).await?.loss;
            loss_sum += loss as f64;
            after_step(StepProgress { step: step + 1, steps: task.local_steps, loss }).await;
        }
        if !task.keep_optimizer_state {
            // The next round starts its moments afresh: they go now rather than then (at the base size twice the
            // trainable tensors, 0.8 GB, no longer held while the update is sent and the server evaluates it).
            self.trainer.reset_optimizer();
        }
        Ok(TrainOutput {
            update: into_named(self.trainer.trainable_weights_async().await?)?,
            examples: rows.len() as u64,
            train_loss: loss_sum / task.local_steps.max(1) as f64,
        })
    }
}

impl LocalTrainer for SmolVlaTrainer {
    fn capabilities(&self) -> Capabilities {
        let params: usize = self.trainer.model.cfg.param_specs().iter().map(fedvla_policy::ParamSpec::numel).sum();
        Capabilities { backend: self.backend.clone(), memory_bytes: (params * 4) as u64 }
    }

    fn set_global(&mut self, global: &NamedTensors) -> Result<(), BoxError> {
        // On the CPU, the evaluation model shares the trainer's new tensors; elsewhere it holds a copy on the CPU.
        let on_cpu = *self.trainer.device() == Device::flex();
        let weights = to_weights(global);
        let cpu_copy = (!on_cpu).then(|| ParamStore::upload(weights.iter(), &Device::flex(), false));
        self.trainer.set_trainable_weights(weights)?;
        let trainable = cpu_copy.unwrap_or_else(|| self.trainer.trainable_store());
        self.global_cpu = self.global_cpu.with_trainable(&trainable);
        Ok(())
    }

    fn set_correction(&mut self, correction: &NamedTensors) -> Result<(), BoxError> {
        let weights = (!correction.is_empty()).then(|| to_weights(correction));
        Ok(self.trainer.set_correction(weights.as_ref())?)
    }

    fn set_norm_stats(&mut self, stats: &NormalizationStats) -> Result<(), BoxError> {
        Ok(self.examples.set_norm_stats(stats)?)
    }

    /// `local_steps` AdamW steps on batches drawn (seeded by the task) from the training rows, each row visited
    /// once per pass (the task's opening frames `repeat` times, see [`ShardExamples::training_draws`]).
    async fn train(&mut self, task: &RoundTask) -> Result<TrainOutput, BoxError> {
        self.train_with(task, async |_| {}).await
    }

    async fn evaluate(&mut self) -> Result<EvalOutput, BoxError> {
        let metrics = heldout_metrics(&self.global_cpu, &self.examples, &self.held_out)?;
        Ok(EvalOutput { examples: self.held_out.rows.len() as u64, loss: metrics.loss })
    }

    /// Unfilmed rollouts on the CPU (the browser films its own, see client-wasm).
    async fn rollout(&mut self, request: &RolloutRequest) -> Result<Vec<RolloutOutput>, BoxError> {
        let Some(policy) = self.sim_policy()? else { return Ok(Vec::new()) };
        (0..request.episodes)
            .map(|episode| {
                let (task, seed) = (policy.tasks().task_of(episode as usize), request.first_seed + u64::from(episode));
                let result = run_episode(Episode::new(&policy, task, seed, request.max_frames as usize)?, |_| {})?;
                Ok(RolloutOutput { episode: rollout_episode(episode, &result), video: None })
            })
            .collect()
    }
}

/// The protocol's record of a finished episode (its video is filled in by whoever filmed it).
pub fn rollout_episode(episode: u32, result: &EpisodeResult) -> RolloutEpisode {
    RolloutEpisode {
        episode,
        seed: result.seed,
        success: result.success,
        length: result.length as u32,
        video: None,
        task: Some(result.task.name().to_owned()),
    }
}
