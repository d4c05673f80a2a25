//! LeRobot's `VLAFlowMatching`: prefix embedding (cameras, language, state), suffix embedding
//! (noisy actions + sinusoidal time), the flow-matching loss with `action_is_pad` masking, and
//! Euler sampling from noise with the prefix keys/values computed once.

use burn::tensor::activation::silu;
use burn::tensor::{Device, Tensor, TensorData};

use crate::batch::{Prepared, att_2d_mask, mask_block, position_ids};
use crate::config::SmolVlaConfig;
use crate::vlm_with_expert::{
    ActionExpert, ContextKv, PrefixKv, PrefixLayout, SuffixLayout, Trace, Vlm, encode_context, encode_prefix,
    encode_state,
};
use crate::weights::ParamStore;

/// SmolVLA: the VLM and the action expert side by side.
#[derive(Debug, Clone)]
pub struct SmolVla {
    pub cfg: SmolVlaConfig,
    pub vlm: Vlm,
    pub expert: ActionExpert,
    /// Every tensor the model was built from, so that the trained ones can be swapped in.
    store: ParamStore,
}

/// The prefix of one observation batch: keys/values per layer plus its masks.
#[derive(Debug, Clone)]
pub struct Prefix {
    pub kv: PrefixKv,
    /// `[B, Lp]` pad mask (true = real token).
    pub pad: Vec<bool>,
    pub len: usize,
    pub batch: usize,
    /// The full `[B, Lp, Lp]` prefix attention mask and `[B, Lp]` positions (for inspection).
    pub att_2d: Vec<bool>,
    pub positions: Vec<i64>,
}

/// Outputs of one training forward pass.
#[derive(Debug, Clone)]
pub struct FlowMatchingOutput {
    /// Scalar loss as `SmolVLAPolicy.forward` returns it.
    pub loss: Tensor<1>,
    /// `[B, T, max_action_dim]` element-wise squared error, unmasked.
    pub losses: Tensor<3>,
    pub v_t: Tensor<3>,
    pub u_t: Tensor<3>,
    pub x_t: Tensor<3>,
}

/// One Euler step of sampling: the time, the state before the step, the predicted velocity.
#[derive(Debug, Clone)]
pub struct EulerStep {
    pub time: f32,
    pub x: Tensor<3>,
    pub v: Tensor<3>,
}

/// Sinusoidal time embedding, computed in f64 and cast to f32 as LeRobot does: `[B, dim]`.
pub fn time_embedding(time: &[f32], dim: usize, min_period: f64, max_period: f64) -> Vec<f32> {
    let half = dim / 2;
    let mut out = Vec::with_capacity(time.len() * dim);
    for &t in time {
        let angles: Vec<f64> = (0..half)
            .map(|k| {
                let fraction = if half > 1 { k as f64 / (half - 1) as f64 } else { 0.0 };
                let period = min_period * (max_period / min_period).powf(fraction);
                (1.0 / period) * 2.0 * std::f64::consts::PI * t as f64
            })
            .collect();
        out.extend(angles.iter().map(|a| a.sin() as f32));
        out.extend(angles.iter().map(|a| a.cos() as f32));
    }
    out
}

impl SmolVla {
    /// Builds the model from a store holding every tensor of `cfg` (the trainable ones may be autodiff leaves).
    pub fn new(cfg: &SmolVlaConfig, store: &ParamStore) -> Self {
        Self {
            cfg: cfg.clone(),
            vlm: Vlm::load(store, cfg),
            expert: ActionExpert::load(store, cfg),
            store: store.clone(),
        }
    }

    pub fn device(&self) -> Device {
        self.vlm.device()
    }

    /// The model with `trainable`'s tensors in place of its own (after an optimizer step or a new global model).
    pub fn with_trainable(&self, trainable: &ParamStore) -> Self {
        Self::new(&self.cfg, &self.store.overlaid(trainable))
    }

    /// Connector outputs per camera (unscaled), for inspection and for the prefix.
    pub fn embed_images(&self, obs: &Prepared) -> Vec<Tensor<3>> {
        obs.images.iter().map(|img| self.vlm.embed_image(img.clone())).collect()
    }

    /// Runs the prefix: `[cameras | language | state]` through the frozen text layers.
    pub fn encode_prefix(&self, obs: &Prepared, trace: Option<&mut Trace>) -> Prefix {
        let context = self.context(obs);
        let (layout, prefix) = self.prefix_layout(obs, context.dims()[1]);
        let kv = encode_prefix(&self.vlm, context, self.state_token(obs), &layout, trace);
        Prefix { kv, ..prefix }
    }

    /// The context's keys and values (cameras and language through the text layers) for `obs`: with the backbone
    /// frozen, a function of its frames and task alone, which a frozen-feature cache keeps.
    pub fn context_kv(&self, obs: &Prepared) -> ContextKv {
        let context = self.context(obs);
        let (layout, _) = self.prefix_layout(obs, context.dims()[1]);
        encode_context(&self.vlm, context, &layout)
    }

    /// [`SmolVla::encode_prefix`] with the context's keys and values given (`context_kv` of the same frames and
    /// tasks, stacked): only the state token row runs.
    pub fn encode_prefix_from(&self, obs: &Prepared, context: &ContextKv) -> Prefix {
        let (layout, prefix) = self.prefix_layout(obs, context.len());
        let kv = encode_state(&self.vlm, context, self.state_token(obs), &layout);
        Prefix { kv, ..prefix }
    }

    /// Camera and language embeddings, scaled: `[B, Lc, hidden]`.
    fn context(&self, obs: &Prepared) -> Tensor<3> {
        let scale = (self.cfg.vlm.text_config.hidden_size as f64).sqrt();
        let mut parts: Vec<Tensor<3>> = self.embed_images(obs).into_iter().map(|t| t * scale).collect();
        parts.push(self.vlm.embed_language(&obs.lang_tokens, obs.batch, obs.lang_len) * scale);
        Tensor::cat(parts, 1)
    }

    fn state_token(&self, obs: &Prepared) -> Tensor<3> {
        self.expert.state_proj.forward(obs.state.clone()).unsqueeze_dim::<3>(1)
    }

    /// The prefix's masks and positions for a context of `lc` tokens (a [`Prefix`] still without keys and values).
    fn prefix_layout(&self, obs: &Prepared, lc: usize) -> (PrefixLayout, Prefix) {
        let b = obs.batch;
        let cams = obs.images.len();
        let per_image = (lc - obs.lang_len) / cams.max(1);
        let lp = lc + 1;
        let mut pad = Vec::with_capacity(b * lp);
        let mut ar = Vec::with_capacity(b * lp);
        for n in 0..b {
            pad.extend(std::iter::repeat_n(true, cams * per_image));
            pad.extend_from_slice(&obs.lang_mask[n * obs.lang_len..(n + 1) * obs.lang_len]);
            pad.push(true);
            ar.extend(std::iter::repeat_n(false, lc));
            ar.push(true);
        }
        let att_2d = att_2d_mask(&pad, &ar, b, lp);
        let positions = position_ids(&pad, b, lp);
        let layout = PrefixLayout {
            batch: b,
            context_len: lc,
            context_mask: mask_block(&att_2d, b, lp, 0..lc, 0..lc),
            state_mask: mask_block(&att_2d, b, lp, lc..lp, 0..lp),
            context_positions: (0..b).flat_map(|n| positions[n * lp..n * lp + lc].to_vec()).collect(),
            state_positions: (0..b).map(|n| positions[n * lp + lc]).collect(),
        };
        let kv = PrefixKv { keys: Vec::new(), values: Vec::new() };
        (layout, Prefix { kv, pad, len: lp, batch: b, att_2d, positions })
    }

    /// Masks and positions of the action tokens after `prefix` (the mask_ar rule with every action
    /// token opening a new block).
    pub fn suffix_layout(&self, prefix: &Prefix) -> SuffixLayout {
        let (b, lp, t) = (prefix.batch, prefix.len, self.cfg.chunk_size);
        let l = lp + t;
        let mut pad = Vec::with_capacity(b * l);
        let mut ar = Vec::with_capacity(b * l);
        for n in 0..b {
            pad.extend_from_slice(&prefix.pad[n * lp..(n + 1) * lp]);
            pad.extend(std::iter::repeat_n(true, t));
            // Within the prefix only the state token opens a block; its position is lp - 1.
            ar.extend((0..lp).map(|i| i == lp - 1));
            ar.extend(std::iter::repeat_n(true, t));
        }
        let mask = att_2d_mask(&pad, &ar, b, l);
        let positions = position_ids(&pad, b, l);
        SuffixLayout {
            batch: b,
            prefix_len: lp,
            chunk: t,
            joint_mask: mask_block(&mask, b, l, lp..l, 0..l),
            cross_mask: mask_block(&mask, b, l, lp..l, 0..lp),
            positions: (0..b).flat_map(|n| positions[n * l + lp..(n + 1) * l].to_vec()).collect(),
            local_positions: (0..b).flat_map(|_| 0..t as i64).collect(),
        }
    }

    /// Suffix tokens from noisy actions and their times: `[B, T, De]`.
    pub fn embed_suffix(&self, x_t: Tensor<3>, time: &[f32]) -> Tensor<3> {
        let device = x_t.device();
        let [b, t, _] = x_t.dims();
        let de = self.cfg.expert().hidden_size;
        let temb = time_embedding(time, de, self.cfg.min_period, self.cfg.max_period);
        let temb =
            Tensor::<2>::from_data(TensorData::new(temb, [b, de]), &device).unsqueeze_dim::<3>(1).expand([b, t, de]);
        let action = self.expert.action_in_proj.forward(x_t);
        let h = self.expert.action_time_mlp_in.forward(Tensor::cat(vec![action, temb], 2));
        self.expert.action_time_mlp_out.forward(silu(h))
    }

    /// Predicted velocity `v_t` for noisy actions `x_t` at times `time`: `[B, T, max_action_dim]`.
    pub fn velocity(
        &self,
        prefix: &Prefix,
        layout: &SuffixLayout,
        x_t: Tensor<3>,
        time: &[f32],
        trace: Option<&mut Trace>,
    ) -> Tensor<3> {
        let suffix = self.embed_suffix(x_t, time);
        let out = self.expert.forward(suffix, &prefix.kv, layout, trace);
        self.expert.action_out_proj.forward(out)
    }

    /// The flow-matching training loss with fixed noise and time (`VLAFlowMatching.forward` +
    /// `SmolVLAPolicy.forward`'s masking). `actions` and `noise` are `[B, T, max_action_dim]`;
    /// `action_is_pad` is `[B, T]` or absent.
    pub fn forward_loss(
        &self,
        obs: &Prepared,
        actions: Tensor<3>,
        noise: Tensor<3>,
        time: &[f32],
        action_is_pad: Option<&[bool]>,
        mut trace: Option<&mut Trace>,
    ) -> FlowMatchingOutput {
        let prefix = self.encode_prefix(obs, trace.as_deref_mut());
        self.loss_after(&prefix, actions, noise, time, action_is_pad, trace)
    }

    /// [`SmolVla::forward_loss`] with the context's keys and values given (see [`SmolVla::encode_prefix_from`]).
    pub fn forward_loss_from(
        &self,
        obs: &Prepared,
        context: &ContextKv,
        actions: Tensor<3>,
        noise: Tensor<3>,
        time: &[f32],
        action_is_pad: Option<&[bool]>,
    ) -> FlowMatchingOutput {
        let prefix = self.encode_prefix_from(obs, context);
        self.loss_after(&prefix, actions, noise, time, action_is_pad, None)
    }

    /// The flow-matching loss of the expert's velocity after `prefix`.
    fn loss_after(
        &self,
        prefix: &Prefix,
        actions: Tensor<3>,
        noise: Tensor<3>,
        time: &[f32],
        action_is_pad: Option<&[bool]>,
        trace: Option<&mut Trace>,
    ) -> FlowMatchingOutput {
        let device = actions.device();
        let [b, t, amax] = actions.dims();
        let tt = Tensor::<1>::from_data(TensorData::new(time.to_vec(), [b]), &device).reshape([b, 1, 1]);
        let x_t = noise.clone() * tt.clone() + actions.clone() * (tt.neg() + 1.0);
        let u_t = noise - actions;
        let layout = self.suffix_layout(prefix);
        let v_t = self.velocity(prefix, &layout, x_t.clone(), time, trace);
        let losses = (u_t.clone() - v_t.clone()).square();
        let a = self.cfg.action_dim();
        let valid: Vec<f32> = match action_is_pad {
            Some(pad) => pad.iter().map(|&p| if p { 0.0 } else { 1.0 }).collect(),
            None => vec![1.0; b * t],
        };
        let count = valid.iter().sum::<f32>().max(1.0) * a as f32;
        let valid = Tensor::<3>::from_data(TensorData::new(valid, [b, t, 1]), &device);
        let cropped = losses.clone().narrow(2, 0, a.min(amax)) * valid;
        let loss = cropped.sum() / count as f64;
        FlowMatchingOutput { loss, losses, v_t, u_t, x_t }
    }

    /// Euler integration from `noise` (t = 1) to t = 0 in `num_steps` steps; returns `[B, T,
    /// max_action_dim]` normalised actions and records every step when `steps` is given.
    pub fn sample_actions(
        &self,
        obs: &Prepared,
        noise: Tensor<3>,
        mut steps: Option<&mut Vec<EulerStep>>,
    ) -> Tensor<3> {
        let prefix = self.encode_prefix(obs, None);
        let layout = self.suffix_layout(&prefix);
        let n = self.cfg.num_steps;
        let dt = -1.0 / n as f64;
        let mut x = noise;
        for k in 0..n {
            let t = (1.0 + k as f64 * dt) as f32;
            let v = self.velocity(&prefix, &layout, x.clone(), &vec![t; obs.batch], None);
            if let Some(s) = steps.as_deref_mut() {
                s.push(EulerStep { time: t, x: x.clone(), v: v.clone() });
            }
            x = x + v * (dt as f32) as f64;
        }
        x
    }
}

/// Flow-matching times `t = 0.999·s + 0.001` with `s ~ Beta(1.5, 1)`, drawn as `U^(1/1.5)`.
pub fn sample_times(rng: &mut impl rand::Rng, batch: usize) -> Vec<f32> {
    (0..batch).map(|_| rng.random::<f64>().powf(1.0 / 1.5) as f32 * 0.999 + 0.001).collect()
}

/// Standard-normal noise `[B, T, D]` from a seeded generator (host-side, so every backend draws
/// the same numbers).
pub fn gaussian_noise(rng: &mut impl rand::Rng, shape: [usize; 3], device: &Device) -> Tensor<3> {
    use rand_distr::{Distribution, StandardNormal};
    let data: Vec<f32> = (0..shape.iter().product::<usize>()).map(|_| StandardNormal.sample(rng)).collect();
    Tensor::from_data(TensorData::new(data, shape), device)
}
