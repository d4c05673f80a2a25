//! LeRobot's `SmolVLMWithExpertModel`: the truncated SmolVLM (vision tower, connector, token
//! embeddings, first N text layers; frozen by default) and the action expert whose layers run
//! beside the text layers — joint self-attention on even layers, cross-attention into the VLM's
//! (RoPE'd) keys and values on odd ones.
//!
//! The prefix is computed in two parts. Image and language tokens never attend to the state token
//! (mask rule), so their hidden states depend on the backbone and the frame only: with a frozen
//! backbone they run without any trainable tensor, hence without an autodiff graph (a trained
//! backbone gives them one). The single state token row runs through the same layers with a
//! graph, so `state_proj` receives its exact gradient.

use burn::tensor::{Int, Tensor, TensorData};

use crate::config::{EXPERT_PREFIX, SmolVlaConfig, TEXT_PREFIX, TextConfig};
use crate::layers::{DecoderLayer, Linear, RmsNorm, Rope, attention, bool_tensor};
use crate::vision::{Connector, VisionTower};
use crate::weights::ParamStore;

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
        self.embed_tokens.clone().select(0, ids).reshape([batch, len, self.hidden])
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

/// Runs the frozen text layers over the prefix: context tokens without a graph, the state token
/// row with one. Returns the per-layer keys/values.
pub fn encode_prefix(
    vlm: &Vlm,
    context: Tensor<3>,
    state_token: Tensor<3>,
    layout: &PrefixLayout,
    mut trace: Option<&mut Trace>,
) -> PrefixKv {
    let device = context.device();
    let (b, lc) = (layout.batch, layout.context_len);
    let hd = vlm.head_dim();
    let context_rope = Rope::new(&layout.context_positions, b, lc, hd, &device);
    let state_rope = Rope::new(&layout.state_positions, b, 1, hd, &device);
    let context_mask = bool_tensor(layout.context_mask.clone(), [b, lc, lc], &device);
    let state_mask = bool_tensor(layout.state_mask.clone(), [b, 1, lc + 1], &device);
    let (mut xc, mut xs) = (context, state_token);
    let mut kv = PrefixKv { keys: Vec::new(), values: Vec::new() };
    for layer in &vlm.layers {
        if let Some(t) = trace.as_deref_mut() {
            t.vlm_layer_inputs.push(Tensor::cat(vec![xc.clone(), xs.clone()], 1));
        }
        let (qc, kc, vc) = layer.qkv(layer.input_layernorm.forward(xc.clone()));
        let (qs, ks, vs) = layer.qkv(layer.input_layernorm.forward(xs.clone()));
        let (qc, kc) = (context_rope.apply(qc), context_rope.apply(kc));
        let (qs, ks) = (state_rope.apply(qs), state_rope.apply(ks));
        let keys = Tensor::cat(vec![kc.clone(), ks], 1);
        let values = Tensor::cat(vec![vc.clone(), vs], 1);
        let attn_c = attention(qc, kc, vc, Some(context_mask.clone()));
        let attn_s = attention(qs, keys.clone(), values.clone(), Some(state_mask.clone()));
        xc = layer.finish(xc, attn_c);
        xs = layer.finish(xs, attn_s);
        kv.keys.push(keys);
        kv.values.push(values);
    }
    if let Some(t) = trace {
        t.prefix_out = Some(vlm.final_norm(Tensor::cat(vec![xc, xs], 1)));
    }
    kv
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
