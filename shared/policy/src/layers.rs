//! Building blocks shared by the vision tower, the text decoder and the action expert: linear
//! layers in PyTorch's [out, in] layout, LayerNorm, RMSNorm, SmolVLA's own RoPE, the eager GQA
//! attention kernel LeRobot uses (masked logits replaced by f32::MIN, softmax in f32), and the
//! Llama decoder layer whose key names the text model and the expert share.

use burn::tensor::activation::{silu, softmax};
use burn::tensor::{Bool, Device, Tensor, TensorData};

use crate::weights::{ParamStore, as_f32};

/// `y = x Wᵀ + b`, weights stored as the checkpoint stores them ([out, in]).
#[derive(Debug, Clone)]
pub struct Linear {
    /// [in, out]: transposed once at build time so every forward is a plain matmul.
    weight_t: Tensor<2>,
    bias: Option<Tensor<1>>,
}

impl Linear {
    pub fn load(store: &ParamStore, prefix: &str, bias: bool) -> Self {
        Self::from_weight(
            store.get::<2>(&format!("{prefix}.weight")),
            bias.then(|| store.get::<1>(&format!("{prefix}.bias"))),
        )
    }

    pub fn from_weight(weight: Tensor<2>, bias: Option<Tensor<1>>) -> Self {
        Self { weight_t: weight.transpose(), bias }
    }

    /// # Shapes
    /// - x: `[..., in]` → `[..., out]`
    pub fn forward<const D: usize>(&self, x: Tensor<D>) -> Tensor<D> {
        burn::tensor::module::linear(x, as_f32(self.weight_t.clone()), self.bias.clone().map(as_f32))
    }
}

/// LayerNorm with affine weight and bias (SigLIP).
#[derive(Debug, Clone)]
pub struct LayerNorm {
    weight: Tensor<1>,
    bias: Tensor<1>,
    eps: f64,
}

impl LayerNorm {
    pub fn load(store: &ParamStore, prefix: &str, eps: f64) -> Self {
        Self { weight: store.get(&format!("{prefix}.weight")), bias: store.get(&format!("{prefix}.bias")), eps }
    }

    pub fn forward<const D: usize>(&self, x: Tensor<D>) -> Tensor<D> {
        let mean = x.clone().mean_dim(D - 1);
        let centered = x - mean;
        let var = centered.clone().square().mean_dim(D - 1);
        let normed = centered / (var + self.eps).sqrt();
        normed * as_f32(self.weight.clone()).unsqueeze() + as_f32(self.bias.clone()).unsqueeze()
    }
}

/// Llama RMSNorm: `w ⊙ x / sqrt(mean(x²) + eps)`.
#[derive(Debug, Clone)]
pub struct RmsNorm {
    weight: Tensor<1>,
    eps: f64,
}

impl RmsNorm {
    pub fn load(store: &ParamStore, prefix: &str, eps: f64) -> Self {
        Self { weight: store.get(&format!("{prefix}.weight")), eps }
    }

    pub fn forward<const D: usize>(&self, x: Tensor<D>) -> Tensor<D> {
        let variance = x.clone().square().mean_dim(D - 1);
        x * (variance + self.eps).sqrt().recip() * as_f32(self.weight.clone()).unsqueeze()
    }
}

/// Cos/sin tables of SmolVLA's RoPE (θ = 10 000, split-half), for integer positions.
/// Computed on the host in f32 the way LeRobot's `apply_rope` computes them.
#[derive(Debug, Clone)]
pub struct Rope {
    /// `[B, L, 1, head_dim/2]`
    cos: Tensor<4>,
    sin: Tensor<4>,
}

impl Rope {
    /// `positions` is row-major `[batch, len]`.
    pub fn new(positions: &[i64], batch: usize, len: usize, head_dim: usize, device: &Device) -> Self {
        let half = head_dim / 2;
        let timescale: Vec<f32> = (0..half)
            .map(|k| {
                let exponent = (2.0f32 / head_dim as f32) * k as f32;
                10000f32.powf(exponent)
            })
            .collect();
        let mut cos = Vec::with_capacity(positions.len() * half);
        let mut sin = Vec::with_capacity(positions.len() * half);
        for &p in positions {
            for ts in &timescale {
                let radians = p as f32 / ts;
                cos.push(radians.cos());
                sin.push(radians.sin());
            }
        }
        let shape = [batch, len, 1, half];
        Self {
            cos: Tensor::from_data(TensorData::new(cos, shape), device),
            sin: Tensor::from_data(TensorData::new(sin, shape), device),
        }
    }

    /// # Shapes
    /// - x: `[B, L, heads, head_dim]`
    pub fn apply(&self, x: Tensor<4>) -> Tensor<4> {
        let [_, _, _, d] = x.dims();
        let half = d / 2;
        let x1 = x.clone().narrow(3, 0, half);
        let x2 = x.narrow(3, half, half);
        let out1 = x1.clone() * self.cos.clone() - x2.clone() * self.sin.clone();
        let out2 = x2 * self.cos.clone() + x1 * self.sin.clone();
        Tensor::cat(vec![out1, out2], 3)
    }
}

/// Eager grouped-query attention. Query head `h` reads KV head `h / (heads / kv_heads)`.
///
/// # Shapes
/// - q: `[B, Lq, H, hd]`, k and v: `[B, Lk, KVH, hd]`
/// - mask: `[B, Lq, Lk]`, true where query i may attend key j; `None` = no mask
/// - output: `[B, Lq, H·hd]`
pub fn attention(q: Tensor<4>, k: Tensor<4>, v: Tensor<4>, mask: Option<Tensor<3, Bool>>) -> Tensor<3> {
    let [b, lq, h, hd] = q.dims();
    let [_, lk, kvh, _] = k.dims();
    let groups = h / kvh;
    // [B, H, Lq, hd] → [B, KVH, G·Lq, hd]: heads g·G..g·G+G-1 share KV head g.
    let q = q.swap_dims(1, 2).reshape([b, kvh, groups * lq, hd]);
    let k = k.swap_dims(1, 2);
    let v = v.swap_dims(1, 2);
    let scores = q.matmul(k.swap_dims(2, 3)) * (hd as f64).powf(-0.5);
    let scores = match mask {
        Some(mask) => {
            let blocked = mask.bool_not().unsqueeze_dim::<4>(1).repeat_dim(1, groups).reshape([b, 1, groups * lq, lk]);
            scores.mask_fill(blocked.expand([b, kvh, groups * lq, lk]), f32::MIN)
        }
        None => scores,
    };
    let probs = softmax(scores, 3);
    probs.matmul(v).reshape([b, h, lq, hd]).swap_dims(1, 2).reshape([b, lq, h * hd])
}

/// Llama decoder layer weights (`input_layernorm`, `self_attn.{q,k,v,o}_proj`,
/// `post_attention_layernorm`, `mlp.{gate,up,down}_proj`), used by the text model and the expert.
#[derive(Debug, Clone)]
pub struct DecoderLayer {
    pub input_layernorm: RmsNorm,
    pub q_proj: Linear,
    pub k_proj: Linear,
    pub v_proj: Linear,
    pub o_proj: Linear,
    pub post_attention_layernorm: RmsNorm,
    gate_proj: Linear,
    up_proj: Linear,
    down_proj: Linear,
    pub num_heads: usize,
    pub num_kv_heads: usize,
    pub head_dim: usize,
}

impl DecoderLayer {
    pub fn load(
        store: &ParamStore,
        prefix: &str,
        eps: f64,
        num_heads: usize,
        num_kv_heads: usize,
        head_dim: usize,
    ) -> Self {
        let lin = |name: &str| Linear::load(store, &format!("{prefix}.{name}"), false);
        Self {
            input_layernorm: RmsNorm::load(store, &format!("{prefix}.input_layernorm"), eps),
            q_proj: lin("self_attn.q_proj"),
            k_proj: lin("self_attn.k_proj"),
            v_proj: lin("self_attn.v_proj"),
            o_proj: lin("self_attn.o_proj"),
            post_attention_layernorm: RmsNorm::load(store, &format!("{prefix}.post_attention_layernorm"), eps),
            gate_proj: lin("mlp.gate_proj"),
            up_proj: lin("mlp.up_proj"),
            down_proj: lin("mlp.down_proj"),
            num_heads,
            num_kv_heads,
            head_dim,
        }
    }

    /// Splits the last dimension into heads: `[B, L, n·hd]` → `[B, L, n, hd]`.
    pub fn heads(&self, x: Tensor<3>, n: usize) -> Tensor<4> {
        let [b, l, _] = x.dims();
        x.reshape([b, l, n, self.head_dim])
    }

    /// Query, key and value of the normed stream `h`, split into heads.
    pub fn qkv(&self, h: Tensor<3>) -> (Tensor<4>, Tensor<4>, Tensor<4>) {
        let q = self.heads(self.q_proj.forward(h.clone()), self.num_heads);
        let k = self.heads(self.k_proj.forward(h.clone()), self.num_kv_heads);
        let v = self.heads(self.v_proj.forward(h), self.num_kv_heads);
        (q, k, v)
    }

    /// Everything after attention: o_proj, residual, post-attention norm, SwiGLU MLP, residual.
    pub fn finish(&self, residual: Tensor<3>, attn: Tensor<3>) -> Tensor<3> {
        let x = residual + self.o_proj.forward(attn);
        let h = self.post_attention_layernorm.forward(x.clone());
        let mlp = self.down_proj.forward(silu(self.gate_proj.forward(h.clone())) * self.up_proj.forward(h));
        x + mlp
    }
}

/// Boolean mask tensor from row-major host values.
pub fn bool_tensor<const D: usize>(values: Vec<bool>, shape: [usize; D], device: &Device) -> Tensor<D, Bool> {
    Tensor::from_data(TensorData::new(values, shape), device)
}
