//! SmolVLM's SigLIP vision tower (patch embedding, NaViT-style position ids, pre-LN encoder,
//! post-layernorm) and the pixel-shuffle connector that turns its patches into text-width tokens.

use burn::tensor::activation::gelu_approximate;
use burn::tensor::{Int, Tensor, TensorData};

use crate::config::{CONNECTOR_KEY, SmolVlaConfig, VISION_PREFIX, VisionConfig};
use crate::layers::{LayerNorm, Linear, attention};
use crate::weights::{ParamStore, as_f32};

#[derive(Debug, Clone)]
struct EncoderLayer {
    layer_norm1: LayerNorm,
    q_proj: Linear,
    k_proj: Linear,
    v_proj: Linear,
    out_proj: Linear,
    layer_norm2: LayerNorm,
    fc1: Linear,
    fc2: Linear,
    num_heads: usize,
}

impl EncoderLayer {
    fn load(store: &ParamStore, prefix: &str, cfg: &VisionConfig) -> Self {
        let lin = |n: &str| Linear::load(store, &format!("{prefix}.{n}"), true);
        let norm = |n: &str| LayerNorm::load(store, &format!("{prefix}.{n}"), cfg.layer_norm_eps);
        Self {
            layer_norm1: norm("layer_norm1"),
            q_proj: lin("self_attn.q_proj"),
            k_proj: lin("self_attn.k_proj"),
            v_proj: lin("self_attn.v_proj"),
            out_proj: lin("self_attn.out_proj"),
            layer_norm2: norm("layer_norm2"),
            fc1: lin("mlp.fc1"),
            fc2: lin("mlp.fc2"),
            num_heads: cfg.num_attention_heads,
        }
    }

    fn forward(&self, x: Tensor<3>) -> Tensor<3> {
        let [b, n, d] = x.dims();
        let heads = |t: Tensor<3>| t.reshape([b, n, self.num_heads, d / self.num_heads]);
        let h = self.layer_norm1.forward(x.clone());
        let q = heads(self.q_proj.forward(h.clone()));
        let k = heads(self.k_proj.forward(h.clone()));
        let v = heads(self.v_proj.forward(h));
        let x = x + self.out_proj.forward(attention(q, k, v, None));
        let h = self.layer_norm2.forward(x.clone());
        x.clone() + self.fc2.forward(gelu_approximate(self.fc1.forward(h)))
    }
}

/// SigLIP encoder as SmolVLM configures it.
#[derive(Debug, Clone)]
pub struct VisionTower {
    patch_embedding: Linear,
    position_embedding: Tensor<2>,
    layers: Vec<EncoderLayer>,
    post_layernorm: LayerNorm,
    cfg: VisionConfig,
}

impl VisionTower {
    pub fn load(store: &ParamStore, cfg: &VisionConfig) -> Self {
        let p = VISION_PREFIX;
        let conv: Tensor<4> = store.get(&format!("{p}.embeddings.patch_embedding.weight"));
        let [d, c, ph, pw] = conv.dims();
        // A stride = kernel convolution is a matmul over flattened (channel, row, col) patches.
        let patch_embedding = Linear::from_weight(
            conv.reshape([d, c * ph * pw]),
            Some(store.get(&format!("{p}.embeddings.patch_embedding.bias"))),
        );
        Self {
            patch_embedding,
            position_embedding: store.get(&format!("{p}.embeddings.position_embedding.weight")),
            layers: (0..cfg.num_hidden_layers)
                .map(|n| EncoderLayer::load(store, &format!("{p}.encoder.layers.{n}"), cfg))
                .collect(),
            post_layernorm: LayerNorm::load(store, &format!("{p}.post_layernorm"), cfg.layer_norm_eps),
            cfg: cfg.clone(),
        }
    }

    /// Position ids SmolVLM's vision embeddings assign to a patch grid of `rows × cols`: fractional
    /// patch coordinates bucketed onto the `image_size / patch_size` grid of the position table
    /// (the identity for a full-size image).
    pub fn position_ids(&self, rows: usize, cols: usize) -> Vec<i64> {
        let per_side = self.cfg.image_size / self.cfg.patch_size;
        let step = 1.0f32 / per_side as f32;
        let boundaries: Vec<f32> = (1..per_side).map(|k| k as f32 * step).collect();
        let bucket = |n: usize| -> Vec<i64> {
            (0..n)
                .map(|i| {
                    let frac = i as f32 / n as f32;
                    boundaries.iter().filter(|&&b| b <= frac).count() as i64
                })
                .collect()
        };
        let (rb, cb) = (bucket(rows), bucket(cols));
        rb.iter().flat_map(|r| cb.iter().map(move |c| r * per_side as i64 + c)).collect()
    }

    /// # Shapes
    /// - images: `[B, 3, H, W]` in [-1, 1] → `[B, (H/p)·(W/p), D]` after post_layernorm
    pub fn forward(&self, images: Tensor<4>) -> Tensor<3> {
        let [b, c, h, w] = images.dims();
        let p = self.cfg.patch_size;
        let (rows, cols) = (h / p, w / p);
        let patches =
            images.reshape([b, c, rows, p, cols, p]).permute([0, 2, 4, 1, 3, 5]).reshape([b, rows * cols, c * p * p]);
        let x = self.patch_embedding.forward(patches);
        let device = x.device();
        let ids = self.position_ids(rows, cols);
        let ids = Tensor::<1, Int>::from_data(TensorData::new(ids, [rows * cols]), &device);
        let pos = as_f32(self.position_embedding.clone().select(0, ids)).unsqueeze::<3>();
        let mut x = x + pos;
        for layer in &self.layers {
            x = layer.forward(x);
        }
        self.post_layernorm.forward(x)
    }
}

/// Pixel shuffle by `scale_factor` followed by `modality_projection.proj` (no bias).
#[derive(Debug, Clone)]
pub struct Connector {
    proj: Linear,
    scale_factor: usize,
}

impl Connector {
    pub fn load(store: &ParamStore, cfg: &SmolVlaConfig) -> Self {
        Self { proj: Linear::from_weight(store.get(CONNECTOR_KEY), None), scale_factor: cfg.vlm.scale_factor }
    }

    /// # Shapes
    /// - x: `[B, N, D]` with N a square → `[B, N/r², Dtext]`
    pub fn forward(&self, x: Tensor<3>) -> Tensor<3> {
        let [b, n, d] = x.dims();
        let r = self.scale_factor;
        let s = (n as f64).sqrt().round() as usize;
        // Output token (h', w') gathers the r×r block of patches; features are row offset (outer),
        // column offset, channel (inner), exactly as SmolVLM's pixel_shuffle lays them out.
        let x = x.reshape([b, s, s / r, d * r]).swap_dims(1, 2).reshape([b, s / r, s / r, d * r * r]);
        let x = x.swap_dims(1, 2).reshape([b, n / (r * r), d * r * r]);
        self.proj.forward(x)
    }
}
