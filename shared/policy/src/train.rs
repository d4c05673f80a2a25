//! Training SmolVLA's trainable set exactly as LeRobot does: AdamW (torch semantics, decoupled
//! weight decay) over the tensors the configuration's switches train (by default the expert and the
//! five projections), global grad-norm clipping, and seeded Beta(1.5, 1) time / Gaussian noise sampling (each
//! step's learning rate is the caller's: a round's schedule is `RoundTask::lr_at` in the federation crate). The frozen tensors live in a separate store that no
//! optimizer ever sees.

use std::collections::BTreeMap;

use burn::tensor::{Device, Tensor};
use rand::SeedableRng;
use rand::rngs::StdRng;

use crate::batch::{Batch, Prepared, prepare_actions};
use crate::config::SmolVlaConfig;
use crate::error::PolicyError;
use crate::smolvla::{FlowMatchingOutput, SmolVla, gaussian_noise, sample_times};
use crate::vlm_with_expert::ContextKv;
use crate::weights::{HostTensor, ParamStore, WeightMap, check_keys, check_shapes};

/// AdamW hyper-parameters (LeRobot's SmolVLA preset by default).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AdamWConfig {
    pub betas: (f64, f64),
    pub eps: f64,
    pub weight_decay: f64,
    pub grad_clip_norm: f64,
}

impl AdamWConfig {
    pub fn from_policy(cfg: &SmolVlaConfig) -> Self {
        Self {
            betas: cfg.optimizer_betas,
            eps: cfg.optimizer_eps,
            weight_decay: cfg.optimizer_weight_decay,
            grad_clip_norm: cfg.optimizer_grad_clip_norm,
        }
    }
}

/// Figures of one optimizer step.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepReport {
    pub loss: f32,
    pub grad_norm: f32,
    pub lr: f64,
}

/// The trainable tensors as autodiff leaves plus AdamW moments, by LeRobot key.
pub struct Trainer {
    pub model: SmolVla,
    frozen: ParamStore,
    trainable: BTreeMap<String, (Tensor<1>, Vec<usize>)>,
    moments: BTreeMap<String, (Tensor<1>, Tensor<1>)>,
    optimizer: AdamWConfig,
    step: usize,
    rng: StdRng,
    device: Device,
    proximal: Option<Proximal>,
    /// Added to every step's direction (SCAFFOLD's `c - c_i`, per unit of learning rate), by trainable key.
    correction: BTreeMap<String, Tensor<1>>,
}

/// FedProx's proximal term `mu/2 * ||w - anchor||^2` over the trainable tensors (Li et al. 2020), the anchor being
/// the global model a round started from: it keeps a client's local steps near it on non-IID data.
struct Proximal {
    mu: f64,
    anchor: BTreeMap<String, Tensor<1>>,
}

impl Trainer {
    /// Splits a checked checkpoint into the frozen store and the trainable leaves on `device`
    /// (which must have autodiff enabled).
    pub fn new(cfg: &SmolVlaConfig, weights: &WeightMap, device: &Device, seed: u64) -> Result<Self, PolicyError> {
        Self::taking(cfg, weights.clone(), device, seed)
    }

    /// [`Trainer::new`] of a checkpoint it takes: its tensors move to the device (on the CPU, without a copy), so
    /// the checkpoint is never held twice (at the base size it is 1.8 GB of f32).
    pub fn taking(cfg: &SmolVlaConfig, weights: WeightMap, device: &Device, seed: u64) -> Result<Self, PolicyError> {
        let specs = cfg.param_specs();
        check_keys(&specs, &weights, "weights")?;
        let trainable_names: std::collections::BTreeSet<&str> =
            specs.iter().filter(|s| s.trainable).map(|s| s.name.as_str()).collect();
        let (trainable, frozen): (WeightMap, WeightMap) =
            weights.into_iter().partition(|(k, _)| trainable_names.contains(k.as_str()));
        Self::with_frozen(cfg, ParamStore::upload_owned(frozen, device, false), trainable, device, seed)
    }

    /// [`Trainer::taking`] of a checkpoint in two parts: the frozen tensors already on `device` (kept in the dtype
    /// they are stored in there, e.g. bf16 from [`ParamStore::from_safetensors`]) and the trainable ones, which it
    /// takes. Together they must be the configuration's tensors, each part its own.
    pub fn with_frozen(
        cfg: &SmolVlaConfig,
        frozen: ParamStore,
        trainable: WeightMap,
        device: &Device,
        seed: u64,
    ) -> Result<Self, PolicyError> {
        let specs = cfg.param_specs();
        let shapes = frozen.flat().map(|(k, _, s)| (k.as_str(), s.as_slice()));
        check_shapes(&specs, shapes.chain(trainable.iter().map(|(k, t)| (k.as_str(), t.shape.as_slice()))), "weights")?;
        let misplaced: Vec<&str> =
            specs.iter().filter(|s| s.trainable == frozen.contains(&s.name)).map(|s| s.name.as_str()).collect();
        if !misplaced.is_empty() {
            return Err(PolicyError::Input(format!(
                "these tensors are in the wrong part (frozen or trainable) of the weights: {}",
                misplaced.join(", ")
            )));
        }
        let trainable_store = ParamStore::upload_owned(trainable, device, true);
        let model = SmolVla::new(cfg, &frozen.overlaid(&trainable_store));
        let trainable = trainable_store.flat().map(|(k, t, s)| (k.clone(), (t.clone(), s.clone()))).collect();
        Ok(Self {
            model,
            frozen,
            trainable,
            moments: BTreeMap::new(),
            optimizer: AdamWConfig::from_policy(cfg),
            step: 0,
            rng: StdRng::seed_from_u64(seed),
            device: device.clone(),
            proximal: None,
            correction: BTreeMap::new(),
        })
    }

    pub fn device(&self) -> &Device {
        &self.device
    }

    pub fn steps_taken(&self) -> usize {
        self.step
    }

    /// The trainable tensors on the host: what the federation exchanges.
    pub fn trainable_weights(&self) -> WeightMap {
        ParamStore::from_flat(self.trainable.clone()).to_host()
    }

    /// [`Trainer::trainable_weights`], read asynchronously (browsers).
    pub async fn trainable_weights_async(&self) -> Result<WeightMap, PolicyError> {
        ParamStore::from_flat(self.trainable.clone()).to_host_async().await
    }

    /// [`Trainer::frozen_weights`], read asynchronously (browsers).
    pub async fn frozen_weights_async(&self) -> Result<WeightMap, PolicyError> {
        self.frozen.to_host_async().await
    }

    /// The frozen tensors on the host (they never change; exported with every checkpoint).
    pub fn frozen_weights(&self) -> WeightMap {
        self.frozen.to_host()
    }

    /// The frozen tensors without autodiff, on the training device's own backend and sharing their memory: a model
    /// beside the trainer on the same device evaluates with them at no copy.
    pub fn frozen_store(&self) -> ParamStore {
        ParamStore::from_flat(self.frozen.flat().map(|(k, t, s)| (k.clone(), (t.clone().inner(), s.clone()))).collect())
    }

    /// The trainable tensors as they are now, without autodiff and sharing their memory (see
    /// [`Trainer::frozen_store`]).
    pub fn trainable_store(&self) -> ParamStore {
        ParamStore::from_flat(
            self.trainable.iter().map(|(k, (t, s))| (k.clone(), (t.clone().inner(), s.clone()))).collect(),
        )
    }

    /// Replaces the trainable tensors (e.g. with a new global model); the optimizer's moments stay (see
    /// [`Trainer::reset_optimizer`]).
    pub fn set_trainable_weights(&mut self, weights: WeightMap) -> Result<(), PolicyError> {
        let expected: Vec<_> = self.model.cfg.param_specs().into_iter().filter(|s| s.trainable).collect();
        check_keys(&expected, &weights, "trainable update")?;
        // Taken, not copied: on the CPU the weights' buffers become the tensors.
        let store = ParamStore::upload_owned(weights, &self.device, true);
        self.trainable = store.flat().map(|(k, t, s)| (k.clone(), (t.clone(), s.clone()))).collect();
        self.model = self.model.with_trainable(&store);
        Ok(())
    }

    /// From now on every step moves each trainable tensor by `lr * correction` more than AdamW would (SCAFFOLD's
    /// `c - c_i`: the direction of a step is AdamW's per unit of learning rate, weight decay included); `None`
    /// removes it. A correction names every trainable tensor.
    pub fn set_correction(&mut self, correction: Option<&WeightMap>) -> Result<(), PolicyError> {
        self.correction = match correction {
            None => BTreeMap::new(),
            Some(weights) => {
                let expected: Vec<_> = self.model.cfg.param_specs().into_iter().filter(|s| s.trainable).collect();
                check_keys(&expected, weights, "SCAFFOLD correction")?;
                let store = ParamStore::upload(weights.iter(), &self.device, false);
                store.flat().map(|(k, t, _)| (k.clone(), t.clone())).collect()
            }
        };
        Ok(())
    }

    /// Forgets AdamW's moments and step count: the next step is a first step.
    pub fn reset_optimizer(&mut self) {
        self.moments.clear();
        self.step = 0;
    }

    /// From now on every step's gradient carries FedProx's proximal term `mu/2 * ||w - w0||^2`, `w0` being the
    /// trainable tensors as they are now (the round's global model); `mu` = 0 removes it. The reported loss stays
    /// the flow-matching loss, comparable with and without the term.
    pub fn set_proximal(&mut self, mu: f64) {
        self.proximal = (mu > 0.0).then(|| Proximal {
            mu,
            anchor: self.trainable.iter().map(|(k, (leaf, _))| (k.clone(), leaf.clone().inner())).collect(),
        });
    }

    /// Forward pass with given noise and time (no update).
    pub fn forward(&self, batch: &Batch, noise: Tensor<3>, time: &[f32]) -> Result<FlowMatchingOutput, PolicyError> {
        self.forward_from(batch, None, noise, time)
    }

    /// [`Trainer::forward`], with the context's keys and values of `batch` given when a frozen-feature cache
    /// holds them (only the state row and the expert run then).
    fn forward_from(
        &self,
        batch: &Batch,
        context: Option<&ContextKv>,
        noise: Tensor<3>,
        time: &[f32],
    ) -> Result<FlowMatchingOutput, PolicyError> {
        let obs = Prepared::new(&self.model.cfg, batch, &self.device)?;
        let actions =
            batch.actions.as_ref().ok_or_else(|| PolicyError::Input("batch has no actions to train on".into()))?;
        let actions = prepare_actions(&self.model.cfg, actions, &self.device);
        let pad = batch.action_is_pad.as_deref();
        Ok(match context {
            Some(context) => self.model.forward_loss_from(&obs, context, actions, noise, time, pad),
            None => self.model.forward_loss(&obs, actions, noise, time, pad, None),
        })
    }

    /// The context's keys and values of `batch` (see [`SmolVla::context_kv`]), without a graph: what a
    /// frozen-feature cache keeps. Only meaningful while the backbone is frozen
    /// ([`SmolVlaConfig::backbone_frozen`]).
    pub fn context_kv(&self, batch: &Batch) -> Result<ContextKv, PolicyError> {
        let obs = Prepared::new(&self.model.cfg, batch, &self.device)?;
        Ok(self.model.context_kv(&obs).detach())
    }

    /// Seeded flow-matching noise `[B, T, max_action_dim]` and times `t = 0.999·Beta(1.5, 1) + 0.001`.
    pub fn sample_noise_and_time(&mut self, batch: usize) -> (Tensor<3>, Vec<f32>) {
        let cfg = &self.model.cfg;
        let noise = gaussian_noise(&mut self.rng, [batch, cfg.chunk_size, cfg.max_action_dim], &self.device);
        let time = sample_times(&mut self.rng, batch);
        (noise, time)
    }

    /// One training step on `batch` with seeded noise and time, at learning rate `lr`.
    pub fn train_step(&mut self, batch: &Batch, lr: f64) -> Result<StepReport, PolicyError> {
        self.train_step_from(batch, None, lr)
    }

    /// [`Trainer::train_step`] with the context's keys and values of `batch` given when a frozen-feature cache
    /// holds them.
    pub fn train_step_from(
        &mut self,
        batch: &Batch,
        context: Option<&ContextKv>,
        lr: f64,
    ) -> Result<StepReport, PolicyError> {
        let (noise, time) = self.sample_noise_and_time(batch.batch_size());
        let (loss, grads) = self.backward(batch, context, noise, &time)?;
        let norm_sq = squared_norm(&grads).map_or(0.0, |n| n.into_scalar::<f64>());
        self.finish_step(loss.into_scalar::<f32>(), norm_sq, grads, lr)
    }

    /// [`Trainer::train_step`] with its two reads (loss and gradient norm) awaited: a browser's WebGPU device
    /// cannot read synchronously.
    pub async fn train_step_async(&mut self, batch: &Batch, lr: f64) -> Result<StepReport, PolicyError> {
        self.train_step_async_from(batch, None, lr).await
    }

    /// [`Trainer::train_step_async`] with the context's keys and values of `batch` given when a frozen-feature
    /// cache holds them.
    pub async fn train_step_async_from(
        &mut self,
        batch: &Batch,
        context: Option<&ContextKv>,
        lr: f64,
    ) -> Result<StepReport, PolicyError> {
        let (noise, time) = self.sample_noise_and_time(batch.batch_size());
        let (loss, grads) = self.backward(batch, context, noise, &time)?;
        let norm_sq = match squared_norm(&grads) {
            Some(n) => n.into_scalar_async::<f64>().await.map_err(read_error)?,
            None => 0.0,
        };
        let loss = loss.into_scalar_async::<f32>().await.map_err(read_error)?;
        self.finish_step(loss, norm_sq, grads, lr)
    }

    /// One training step with given noise and time; also returns the gradients before clipping.
    pub fn train_step_with(
        &mut self,
        batch: &Batch,
        noise: Tensor<3>,
        time: &[f32],
        lr: f64,
    ) -> Result<(StepReport, WeightMap), PolicyError> {
        self.train_step_from_with(batch, None, noise, time, lr)
    }

    /// [`Trainer::train_step_with`] with the context's keys and values of `batch` given when a frozen-feature
    /// cache holds them.
    pub fn train_step_from_with(
        &mut self,
        batch: &Batch,
        context: Option<&ContextKv>,
        noise: Tensor<3>,
        time: &[f32],
        lr: f64,
    ) -> Result<(StepReport, WeightMap), PolicyError> {
        let (loss, grads) = self.backward(batch, context, noise, time)?;
        let raw_grads = grads
            .iter()
            .map(|(k, g)| {
                (
                    k.clone(),
                    HostTensor::new(
                        self.trainable[k].1.clone(),
                        g.to_data().convert::<f32>().try_into_vec::<f32>().expect("f32"),
                    ),
                )
            })
            .collect();
        let norm_sq = squared_norm(&grads).map_or(0.0, |n| n.into_scalar::<f64>());
        let report = self.finish_step(loss.into_scalar::<f32>(), norm_sq, grads, lr)?;
        Ok((report, raw_grads))
    }

    /// The loss and the gradient of every trainable tensor that received one.
    fn backward(
        &mut self,
        batch: &Batch,
        context: Option<&ContextKv>,
        noise: Tensor<3>,
        time: &[f32],
    ) -> Result<(Tensor<1>, BTreeMap<String, Tensor<1>>), PolicyError> {
        let loss = self.forward_from(batch, context, noise, time)?.loss;
        let grads = loss.backward();
        let mut grads: BTreeMap<String, Tensor<1>> =
            self.trainable.iter().filter_map(|(k, (leaf, _))| leaf.grad(&grads).map(|g| (k.clone(), g))).collect();
        if let Some(Proximal { mu, anchor }) = &self.proximal {
            // d/dw of mu/2 * ||w - w0||^2.
            for (name, grad) in &mut grads {
                let w = self.trainable[name].0.clone().inner();
                *grad = grad.clone() + (w - anchor[name].clone()) * *mu;
            }
        }
        Ok((loss.inner(), grads))
    }

    /// Clips to the global norm and applies AdamW, unless the loss is not finite.
    fn finish_step(
        &mut self,
        loss: f32,
        norm_sq: f64,
        grads: BTreeMap<String, Tensor<1>>,
        lr: f64,
    ) -> Result<StepReport, PolicyError> {
        if !loss.is_finite() {
            return Err(PolicyError::Input(format!("training loss is {loss}; refusing to apply the update")));
        }
        let grad_norm = norm_sq.sqrt();
        let clip = (self.optimizer.grad_clip_norm / (grad_norm + 1e-6)).min(1.0);
        self.apply_adamw(grads, clip, lr);
        Ok(StepReport { loss, grad_norm: grad_norm as f32, lr })
    }

    /// torch.optim.AdamW on every trainable tensor that received a gradient.
    fn apply_adamw(&mut self, grads: BTreeMap<String, Tensor<1>>, clip: f64, lr: f64) {
        self.step += 1;
        let AdamWConfig { betas: (b1, b2), eps, weight_decay, .. } = self.optimizer;
        let bias1 = 1.0 - b1.powi(self.step as i32);
        let bias2_sqrt = (1.0 - b2.powi(self.step as i32)).sqrt();
        for (name, grad) in grads {
            let grad = if clip < 1.0 { grad * clip } else { grad };
            let (leaf, shape) = self.trainable.remove(&name).expect("gradient of a trainable tensor");
            let param = leaf.inner();
            let (m, v) = self.moments.remove(&name).unwrap_or_else(|| (param.zeros_like(), param.zeros_like()));
            let m = m * b1 + grad.clone() * (1.0 - b1);
            let v = v * b2 + grad.square() * (1.0 - b2);
            let param = param * (1.0 - lr * weight_decay);
            let denom = v.clone().sqrt() / bias2_sqrt + eps;
            let param = param - (m.clone() / denom) * (lr / bias1);
            let param = match self.correction.get(&name) {
                Some(correction) => param - correction.clone() * lr,
                None => param,
            };
            self.moments.insert(name.clone(), (m, v));
            self.trainable.insert(name, (Tensor::from_inner(param).require_grad(), shape));
        }
        self.model = self.model.with_trainable(&ParamStore::from_flat(self.trainable.clone()));
    }
}

/// Sum of the squares of every gradient, as one scalar tensor (one read for the global norm).
fn squared_norm(grads: &BTreeMap<String, Tensor<1>>) -> Option<Tensor<1>> {
    let squares: Vec<Tensor<1>> = grads.values().map(|g| g.clone().square().sum()).collect();
    (!squares.is_empty()).then(|| Tensor::cat(squares, 0).sum())
}

fn read_error(e: impl std::fmt::Display) -> PolicyError {
    PolicyError::Input(format!("reading a tensor from the device failed: {e}"))
}
