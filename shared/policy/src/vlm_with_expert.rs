//! LeRobot's `SmolVLMWithExpertModel`: the truncated SmolVLM (vision tower, connector, token
//! embeddings, first N text layers; frozen by default) and the action expert whose layers run
//! beside the text layers — joint self-attention on even layers, cross-attention into the VLM's
//! (RoPE'd) keys and values on odd ones.
//!
//! The prefix is computed in two parts. Image and language tokens never attend to the state token
//! (mask rule), so their hidden states depend on the backbone and the frame only: with a frozen
//! backbone they run without any trainable tensor, hence without an autodiff graph (a trained
//! backbone gives them one). The single state token row runs through the same layers with a
//! graph, so `state_proj` receives its exact gradient. With the whole backbone frozen, the context's keys and
//! values ([`ContextKv`]) are a function of the frame and the task alone: [`encode_context`] computes them once,
//! a frozen-feature cache keeps them, and [`encode_state`] runs only the state row against them.

use burn::tensor::{Int, Tensor, TensorData};

use crate::config::{EXPERT_PREFIX, SmolVlaConfig, TEXT_PREFIX, TextConfig};
use crate::layers::{DecoderLayer, Linear, RmsNorm, Rope, attention, bool_tensor};
use crate::vision::{Connector, VisionTower};
use crate::weights::{ParamStore, as_f32};

/// The frozen backbone.
#[derive(Debug, Clone)]
pub struct Vlm {
    pub vision: VisionTower,
    pub connector: Connector,
    embed_tokens: Tensor<2>,
    layers: Vec<DecoderLayer>,
    norm: RmsNorm,
    hidden: usize,
}

/// The `count` decoder layers `{prefix}.layers.{n}`, with the text config's heads and norm epsilon (the expert
/// shares them with the VLM; widths come from the weights).
fn load_layers(store: &ParamStore, prefix: &str, count: usize, t: &TextConfig) -> Vec<DecoderLayer> {
    (0..count)
        .map(|n| {
            let p = format!("{prefix}.layers.{n}");
            DecoderLayer::load(store, &p, t.rms_norm_eps, t.num_attention_heads, t.num_key_value_heads, t.head_dim)
        })
        .collect()
}

impl Vlm {
    pub fn load(store: &ParamStore, cfg: &SmolVlaConfig) -> Self {
        let t = &cfg.vlm.text_config;
        Self {
            vision: VisionTower::load(store, &cfg.vlm.vision_config),
            connector: Connector::load(store, cfg),
            embed_tokens: store.get(&format!("{TEXT_PREFIX}.embed_tokens.weight")),
            layers: load_layers(store, TEXT_PREFIX, cfg.num_vlm_layers, t),
            norm: RmsNorm::load(store, &format!("{TEXT_PREFIX}.norm"), t.rms_norm_eps),
            hidden: t.hidden_size,
        }
    }

    /// The device the backbone lives on.
    pub fn device(&self) -> burn::tensor::Device {
        self.embed_tokens.device()
    }

    pub fn head_dim(&self) -> usize {
        self.layers[0].head_dim
    }

    /// Connector output for one camera, before the √hidden scaling.
    ///
    /// # Shapes
    /// - images: `[B, 3, H, W]` in [-1, 1] → `[B, tokens_per_image, hidden]`
    pub fn embed_image(&self, images: Tensor<4>) -> Tensor<3> {
        self.connector.forward(self.vision.forward(images))
    }

    /// Token embeddings, before the √hidden scaling.
    pub fn embed_language(&self, tokens: &[i64], batch: usize, len: usize) -> Tensor<3> {
        let device = self.embed_tokens.device();
        let ids = Tensor::<1, Int>::from_data(TensorData::new(tokens.to_vec(), [batch * len]), &device);
        as_f32(self.embed_tokens.clone().select(0, ids)).reshape([batch, len, self.hidden])
    }

    pub fn final_norm(&self, x: Tensor<3>) -> Tensor<3> {
        self.norm.forward(x)
    }
}

/// Per-layer prefix keys (after RoPE) and values, `[B, Lp, KVH, hd]` each: what the expert reads.
#[derive(Debug, Clone)]
pub struct PrefixKv {
    pub keys: Vec<Tensor<4>>,
    pub values: Vec<Tensor<4>>,
}

/// Masks and positions of one prefix pass, all host-side and row-major.
#[derive(Debug, Clone)]
pub struct PrefixLayout {
    pub batch: usize,
    /// Context tokens (cameras + language); the state token follows at index `context_len`.
    pub context_len: usize,
    /// `[B, Lc, Lc]` context self-attention mask.
    pub context_mask: Vec<bool>,
    /// `[B, 1, Lc + 1]` state-token row of the mask.
    pub state_mask: Vec<bool>,
    /// `[B, Lc]` and `[B]` position ids.
    pub context_positions: Vec<i64>,
    pub state_positions: Vec<i64>,
}

/// Intermediate values LeRobot's golden fixtures record; collected only when asked for.
#[derive(Debug, Default)]
pub struct Trace {
    pub vlm_layer_inputs: Vec<Tensor<3>>,
    pub prefix_out: Option<Tensor<3>>,
    pub expert_layer_inputs: Vec<Tensor<3>>,
    pub suffix_out: Option<Tensor<3>>,
}

/// The context's per-layer keys (after RoPE) and values, `[B, Lc, KVH, hd]` each: all that the state token and
/// the expert read of the image and language tokens.
#[derive(Debug, Clone)]
pub struct ContextKv {
    pub keys: Vec<Tensor<4>>,
    pub values: Vec<Tensor<4>>,
}

impl ContextKv {
    /// Context length.
    pub fn len(&self) -> usize {
        self.keys.first().map_or(0, |k| k.dims()[1])
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Its values' bytes.
    pub fn bytes(&self) -> usize {
        self.keys.iter().chain(&self.values).map(|t| t.dims().iter().product::<usize>() * 4).sum()
    }

    /// One batch of `rows` (each of batch 1, its own context length: its cameras and its own task's tokens),
    /// each right-padded with zeros to the longest (the batch's context: the model reads the language columns of
    /// its longest task, masking the others' padding out) and stacked.
    pub fn stack(rows: &[&ContextKv]) -> ContextKv {
        let len = rows.iter().map(|r| r.len()).max().unwrap_or(0);
        let pad = |t: &Tensor<4>| {
            let [b, l, h, d] = t.dims();
            match len - l {
                0 => t.clone(),
                missing => Tensor::cat(vec![t.clone(), Tensor::zeros([b, missing, h, d], &t.device())], 1),
            }
        };
        let layers = rows.first().map_or(0, |r| r.keys.len());
        let stacked = |pick: fn(&ContextKv) -> &Vec<Tensor<4>>| {
            (0..layers).map(|n| Tensor::cat(rows.iter().map(|r| pad(&pick(r)[n])).collect(), 0)).collect()
        };
        ContextKv { keys: stacked(|r| &r.keys), values: stacked(|r| &r.values) }
    }

    /// The same values without any autodiff graph (a cache keeps them across steps).
    pub fn detach(self) -> ContextKv {
        ContextKv {
            keys: self.keys.into_iter().map(Tensor::detach).collect(),
            values: self.values.into_iter().map(Tensor::detach).collect(),
        }
    }
}

/// Runs the frozen text layers over the prefix: context tokens without a graph, the state token
/// row with one. Returns the per-layer keys/values.
pub fn encode_prefix(
    vlm: &Vlm,
    context: Tensor<3>,
    state_token: Tensor<3>,
    layout: &PrefixLayout,
    trace: Option<&mut Trace>,
) -> PrefixKv {
    let traced = trace.is_some();
    let (context, context_inputs, context_out) = run_context(vlm, context, layout, traced);
    let (kv, state_inputs, state_out) = run_state(vlm, &context, state_token, layout, traced);
    if let Some(t) = trace {
        let inputs = context_inputs.into_iter().zip(state_inputs).map(|(c, s)| Tensor::cat(vec![c, s], 1));
        t.vlm_layer_inputs.extend(inputs);
        t.prefix_out = Some(vlm.final_norm(Tensor::cat(vec![context_out, state_out], 1)));
    }
    kv
}

/// The context's keys and values through every text layer: the part of the prefix a frozen backbone computes
/// from the frame and the task alone.
pub fn encode_context(vlm: &Vlm, context: Tensor<3>, layout: &PrefixLayout) -> ContextKv {
    run_context(vlm, context, layout, false).0
}

/// The prefix keys and values from the context's (computed now or kept by a cache) and the state token row.
pub fn encode_state(vlm: &Vlm, context: &ContextKv, state_token: Tensor<3>, layout: &PrefixLayout) -> PrefixKv {
    run_state(vlm, context, state_token, layout, false).0
}

/// The context tokens through the text layers: their keys and values, and when asked each layer's input and the
/// last layer's output.
fn run_context(
    vlm: &Vlm,
    context: Tensor<3>,
    layout: &PrefixLayout,
    keep_inputs: bool,
) -> (ContextKv, Vec<Tensor<3>>, Tensor<3>) {
    let device = context.device();
    let (b, lc) = (layout.batch, layout.context_len);
    let rope = Rope::new(&layout.context_positions, b, lc, vlm.head_dim(), &device);
    let mask = bool_tensor(layout.context_mask.clone(), [b, lc, lc], &device);
    let mut x = context;
    let (mut kv, mut inputs) = (ContextKv { keys: Vec::new(), values: Vec::new() }, Vec::new());
    for layer in &vlm.layers {
        if keep_inputs {
            inputs.push(x.clone());
        }
        let (q, k, v) = layer.qkv(layer.input_layernorm.forward(x.clone()));
        let (q, k) = (rope.apply(q), rope.apply(k));
        let attn = attention(q, k.clone(), v.clone(), Some(mask.clone()));
        x = layer.finish(x, attn);
        kv.keys.push(k);
        kv.values.push(v);
    }
    (kv, inputs, x)
}

/// The state token row through the text layers, attending to the context's keys and values and its own: the
/// prefix's keys and values, and when asked each layer's input and the last layer's output.
fn run_state(
    vlm: &Vlm,
    context: &ContextKv,
    state_token: Tensor<3>,
    layout: &PrefixLayout,
    keep_inputs: bool,
) -> (PrefixKv, Vec<Tensor<3>>, Tensor<3>) {
    let device = state_token.device();
    let (b, lc) = (layout.batch, layout.context_len);
    let rope = Rope::new(&layout.state_positions, b, 1, vlm.head_dim(), &device);
    let mask = bool_tensor(layout.state_mask.clone(), [b, 1, lc + 1], &device);
    let mut x = state_token;
    let (mut kv, mut inputs) = (PrefixKv { keys: Vec::new(), values: Vec::new() }, Vec::new());
    for (n, layer) in vlm.layers.iter().enumerate() {
        if keep_inputs {
            inputs.push(x.clone());
        }
        let (q, k, v) = layer.qkv(layer.input_layernorm.forward(x.clone()));
        let (q, k) = (rope.apply(q), rope.apply(k));
        let keys = Tensor::cat(vec![context.keys[n].clone(), k], 1);
        let values = Tensor::cat(vec![context.values[n].clone(), v], 1);
        let attn = attention(q, keys.clone(), values.clone(), Some(mask.clone()));
        x = layer.finish(x, attn);
        kv.keys.push(keys);
        kv.values.push(values);
    }
    (kv, inputs, x)
}

/// The trainable part: expert layers, expert norm and the five flow-matching projections.
#[derive(Debug, Clone)]
pub struct ActionExpert {
    layers: Vec<DecoderLayer>,
    self_attn: Vec<bool>,
    norm: RmsNorm,
    pub state_proj: Linear,
    pub action_in_proj: Linear,
    pub action_out_proj: Linear,
    pub action_time_mlp_in: Linear,
    pub action_time_mlp_out: Linear,
}

/// Masks and positions of the suffix (action tokens) against a prefix, host-side.
#[derive(Debug, Clone)]
pub struct SuffixLayout {
    pub batch: usize,
    pub prefix_len: usize,
    pub chunk: usize,
    /// `[B, T, Lp + T]`: valid prefix keys, causal among actions (self-attention layers).
    pub joint_mask: Vec<bool>,
    /// `[B, T, Lp]`: valid prefix keys (cross-attention layers).
    pub cross_mask: Vec<bool>,
    /// `[B, T]` global positions (after the valid prefix) and local ones (0..T).
    pub positions: Vec<i64>,
    pub local_positions: Vec<i64>,
}

impl ActionExpert {
    pub fn load(store: &ParamStore, cfg: &SmolVlaConfig) -> Self {
        let t = &cfg.vlm.text_config;
        let lin = |n: &str| Linear::load(store, &format!("model.{n}"), true);
        Self {
            layers: load_layers(store, EXPERT_PREFIX, cfg.expert().num_layers, t),
            self_attn: (0..cfg.expert().num_layers).map(|n| cfg.is_self_attn_layer(n)).collect(),
            norm: RmsNorm::load(store, &format!("{EXPERT_PREFIX}.norm"), t.rms_norm_eps),
            state_proj: lin("state_proj"),
            action_in_proj: lin("action_in_proj"),
            action_out_proj: lin("action_out_proj"),
            action_time_mlp_in: lin("action_time_mlp_in"),
            action_time_mlp_out: lin("action_time_mlp_out"),
        }
    }

    /// Runs the action tokens through the expert layers against the prefix keys/values and
    /// returns the expert stream after its final norm.
    ///
    /// # Shapes
    /// - suffix: `[B, T, De]` → `[B, T, De]`
    pub fn forward(
        &self,
        suffix: Tensor<3>,
        prefix: &PrefixKv,
        layout: &SuffixLayout,
        mut trace: Option<&mut Trace>,
    ) -> Tensor<3> {
        let device = suffix.device();
        let (b, lp, t) = (layout.batch, layout.prefix_len, layout.chunk);
        let hd = self.layers[0].head_dim;
        let rope = Rope::new(&layout.positions, b, t, hd, &device);
        let local_rope = Rope::new(&layout.local_positions, b, t, hd, &device);
        let joint_mask = bool_tensor(layout.joint_mask.clone(), [b, t, lp + t], &device);
        let cross_mask = bool_tensor(layout.cross_mask.clone(), [b, t, lp], &device);
        let mut x = suffix;
        for (l, layer) in self.layers.iter().enumerate() {
            if let Some(tr) = trace.as_deref_mut() {
                tr.expert_layer_inputs.push(x.clone());
            }
            let h = layer.input_layernorm.forward(x.clone());
            let q = layer.heads(layer.q_proj.forward(h.clone()), layer.num_heads);
            let attn = if self.self_attn[l] {
                let k = layer.heads(layer.k_proj.forward(h.clone()), layer.num_kv_heads);
                let v = layer.heads(layer.v_proj.forward(h), layer.num_kv_heads);
                let keys = Tensor::cat(vec![prefix.keys[l].clone(), rope.apply(k)], 1);
                let values = Tensor::cat(vec![prefix.values[l].clone(), v], 1);
                attention(rope.apply(q), keys, values, Some(joint_mask.clone()))
            } else {
                // The expert re-projects the VLM's rotated keys and plain values; no second RoPE.
                let [_, _, kvh, _] = prefix.keys[l].dims();
                let flat = |t: &Tensor<4>| t.clone().reshape([b, lp, kvh * hd]);
                let keys = layer.heads(layer.k_proj.forward(flat(&prefix.keys[l])), layer.num_kv_heads);
                let values = layer.heads(layer.v_proj.forward(flat(&prefix.values[l])), layer.num_kv_heads);
                attention(local_rope.apply(q), keys, values, Some(cross_mask.clone()))
            };
            x = layer.finish(x, attn);
        }
        let out = self.norm.forward(x);
        if let Some(tr) = trace {
            tr.suffix_out = Some(out.clone());
        }
        out
    }
}
