//! SmolVLA configuration: the policy fields LeRobot writes to `config.json`, the SmolVLM2 backbone
//! fields it reads from `vlm/config.json`, the derived action-expert sizes, named presets
//! (`base`, `small`, `tiny`) and the full list of checkpoint tensors (names, shapes, and which of
//! them LeRobot's `freeze_vision_encoder` / `train_expert_only` / `train_state_proj` switches
//! train) that every loader, exporter and optimizer in this crate is driven by.

use serde::{Deserialize, Serialize};

use crate::error::PolicyError;

/// Key prefixes, exactly as LeRobot names the checkpoint tensors.
pub const VISION_PREFIX: &str = "model.vlm_with_expert.vlm.model.vision_model";
pub const CONNECTOR_KEY: &str = "model.vlm_with_expert.vlm.model.connector.modality_projection.proj.weight";
pub const TEXT_PREFIX: &str = "model.vlm_with_expert.vlm.model.text_model";
pub const LM_HEAD_KEY: &str = "model.vlm_with_expert.vlm.lm_head.weight";
pub const EXPERT_PREFIX: &str = "model.vlm_with_expert.lm_expert";
/// The five flow-matching projections (all with bias), trained together with the expert.
pub const PROJECTIONS: [&str; 5] = [
    "model.state_proj",
    "model.action_in_proj",
    "model.action_out_proj",
    "model.action_time_mlp_in",
    "model.action_time_mlp_out",
];

/// SigLIP vision tower (`vision_config` of the SmolVLM config).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct VisionConfig {
    pub hidden_size: usize,
    pub intermediate_size: usize,
    pub num_hidden_layers: usize,
    pub num_attention_heads: usize,
    pub image_size: usize,
    pub patch_size: usize,
    #[serde(default = "default_layer_norm_eps")]
    pub layer_norm_eps: f64,
}

fn default_layer_norm_eps() -> f64 {
    1e-6
}

/// Llama text decoder (`text_config` of the SmolVLM config).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TextConfig {
    pub vocab_size: usize,
    pub hidden_size: usize,
    pub intermediate_size: usize,
    pub num_hidden_layers: usize,
    pub num_attention_heads: usize,
    pub num_key_value_heads: usize,
    pub head_dim: usize,
    #[serde(default = "default_rms_norm_eps")]
    pub rms_norm_eps: f64,
}

fn default_rms_norm_eps() -> f64 {
    1e-5
}

/// The SmolVLM backbone: vision tower, pixel-shuffle connector, text decoder.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct VlmConfig {
    pub vision_config: VisionConfig,
    pub text_config: TextConfig,
    pub scale_factor: usize,
}

/// One policy input or output feature as LeRobot's `config.json` lists it.
#[derive(Debug, Clone, PartialEq)]
pub struct Feature {
    pub name: String,
    /// "STATE", "VISUAL" or "ACTION".
    pub kind: String,
    pub shape: Vec<usize>,
}

/// The SmolVLA policy configuration (LeRobot field names).
#[derive(Debug, Clone, PartialEq)]
pub struct SmolVlaConfig {
    pub vlm: VlmConfig,
    /// Input features in `config.json` order; camera order = order of the VISUAL ones.
    pub input_features: Vec<Feature>,
    pub output_features: Vec<Feature>,
    pub chunk_size: usize,
    pub n_action_steps: usize,
    pub max_state_dim: usize,
    pub max_action_dim: usize,
    /// (width, height) as LeRobot stores it.
    pub resize_imgs_with_padding: (usize, usize),
    pub tokenizer_max_length: usize,
    /// "longest" or "max_length".
    pub pad_language_to: String,
    pub num_steps: usize,
    pub num_vlm_layers: usize,
    pub self_attn_every_n_layers: usize,
    pub expert_width_multiplier: f64,
    pub min_period: f64,
    pub max_period: f64,
    pub optimizer_lr: f64,
    pub optimizer_betas: (f64, f64),
    pub optimizer_eps: f64,
    pub optimizer_weight_decay: f64,
    pub optimizer_grad_clip_norm: f64,
    pub scheduler_warmup_steps: usize,
    pub scheduler_decay_steps: usize,
    pub scheduler_decay_lr: f64,
    /// Where LeRobot finds the backbone config and tokenizer (a Hub id or a local folder).
    pub vlm_model_name: String,
    /// What is trained, LeRobot's switches (its defaults: all three true). `train_expert_only` freezes the whole
    /// backbone; without it the backbone trains too, but for the vision tower when `freeze_vision_encoder`, and
    /// always but for the last text layer, the final norm and `lm_head` (their outputs feed nothing).
    pub freeze_vision_encoder: bool,
    pub train_expert_only: bool,
    pub train_state_proj: bool,
}

/// Sizes of the action expert, derived from the text config as LeRobot derives them.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ExpertDims {
    pub hidden_size: usize,
    pub intermediate_size: usize,
    pub num_layers: usize,
}

/// One checkpoint tensor: LeRobot key, shape, and whether SmolVLA trains it by default.
#[derive(Debug, Clone, PartialEq)]
pub struct ParamSpec {
    pub name: String,
    pub shape: Vec<usize>,
    pub trainable: bool,
}

impl ParamSpec {
    pub fn numel(&self) -> usize {
        self.shape.iter().product()
    }
}

impl SmolVlaConfig {
    /// `lerobot/smolvla_base`: SmolVLM2-500M truncated to 16 layers, two SO-100 cameras.
    pub fn base() -> Self {
        let vlm = VlmConfig {
            vision_config: VisionConfig {
                hidden_size: 768,
                intermediate_size: 3072,
                num_hidden_layers: 12,
                num_attention_heads: 12,
                image_size: 512,
                patch_size: 16,
                layer_norm_eps: 1e-6,
            },
            text_config: TextConfig {
                vocab_size: 49280,
                hidden_size: 960,
                intermediate_size: 2560,
                num_hidden_layers: 32,
                num_attention_heads: 15,
                num_key_value_heads: 5,
                head_dim: 64,
                rms_norm_eps: 1e-5,
            },
            scale_factor: 4,
        };
        Self::with_backbone(vlm, 16, 50, 32, (512, 512), so100_features(&["camera1", "camera2", "camera3"], 256))
            .with_pad_language_to("max_length")
            .with_vlm_model_name("HuggingFaceTB/SmolVLM2-500M-Video-Instruct")
    }

    /// A model that trains at a useful speed on 2 CPU cores: the embedded default of `fedvla simulate`.
    pub fn small() -> Self {
        let vlm = VlmConfig {
            vision_config: VisionConfig {
                hidden_size: 64,
                intermediate_size: 128,
                num_hidden_layers: 2,
                num_attention_heads: 2,
                image_size: 64,
                patch_size: 16,
                layer_norm_eps: 1e-6,
            },
            text_config: TextConfig {
                vocab_size: 512,
                hidden_size: 128,
                intermediate_size: 256,
                num_hidden_layers: 4,
                num_attention_heads: 4,
                num_key_value_heads: 2,
                head_dim: 32,
                rms_norm_eps: 1e-5,
            },
            scale_factor: 2,
        };
        Self::with_backbone(vlm, 4, 10, 8, (64, 64), so100_features(&["top", "wrist"], 64))
    }

    /// The topology of the golden fixture `smolvla-tiny-a`: for unit tests.
    pub fn tiny() -> Self {
        let vlm = VlmConfig {
            vision_config: VisionConfig {
                hidden_size: 32,
                intermediate_size: 64,
                num_hidden_layers: 2,
                num_attention_heads: 2,
                image_size: 32,
                patch_size: 8,
                layer_norm_eps: 1e-6,
            },
            text_config: TextConfig {
                vocab_size: 340,
                hidden_size: 96,
                intermediate_size: 192,
                num_hidden_layers: 6,
                num_attention_heads: 6,
                num_key_value_heads: 2,
                head_dim: 16,
                rms_norm_eps: 1e-5,
            },
            scale_factor: 2,
        };
        Self::with_backbone(vlm, 4, 5, 8, (32, 32), so100_features(&["top", "wrist"], 32))
    }

    /// Looks a preset up by name (`base`, `small`, `tiny`).
    pub fn preset(name: &str) -> Result<Self, PolicyError> {
        match name {
            "base" => Ok(Self::base()),
            "small" => Ok(Self::small()),
            "tiny" => Ok(Self::tiny()),
            other => {
                Err(PolicyError::Config(format!("unknown model size {other:?}: expected one of base, small, tiny")))
            }
        }
    }

    fn with_backbone(
        vlm: VlmConfig,
        num_vlm_layers: usize,
        chunk_size: usize,
        max_dim: usize,
        resize: (usize, usize),
        (input_features, output_features): (Vec<Feature>, Vec<Feature>),
    ) -> Self {
        Self {
            vlm,
            input_features,
            output_features,
            chunk_size,
            n_action_steps: chunk_size,
            max_state_dim: max_dim,
            max_action_dim: max_dim,
            resize_imgs_with_padding: resize,
            tokenizer_max_length: 48,
            pad_language_to: "longest".into(),
            num_steps: 10,
            num_vlm_layers,
            self_attn_every_n_layers: 2,
            expert_width_multiplier: 0.75,
            min_period: 4e-3,
            max_period: 4.0,
            optimizer_lr: 1e-4,
            optimizer_betas: (0.9, 0.95),
            optimizer_eps: 1e-8,
            optimizer_weight_decay: 1e-10,
            optimizer_grad_clip_norm: 10.0,
            scheduler_warmup_steps: 1000,
            scheduler_decay_steps: 30000,
            scheduler_decay_lr: 2.5e-6,
            vlm_model_name: "vlm".into(),
            freeze_vision_encoder: true,
            train_expert_only: true,
            train_state_proj: true,
        }
    }

    /// The same policy on square `size` x `size` camera inputs cut into `patch` x `patch` patches (the vision
    /// tower's position embedding follows the patch grid).
    pub fn with_image_size(mut self, size: usize, patch: usize) -> Self {
        self.vlm.vision_config.image_size = size;
        self.vlm.vision_config.patch_size = patch;
        self.resize_imgs_with_padding = (size, size);
        for f in self.input_features.iter_mut().filter(|f| f.kind == "VISUAL") {
            f.shape = vec![3, size, size];
        }
        self
    }

    /// The same policy predicting chunks of `chunk` actions and executing `n_action_steps` of each.
    pub fn with_action_chunk(mut self, chunk: usize, n_action_steps: usize) -> Self {
        self.chunk_size = chunk;
        self.n_action_steps = n_action_steps;
        self
    }

    /// The same policy training what LeRobot's switches say (see [`SmolVlaConfig::train_expert_only`]).
    pub fn with_trained_parts(mut self, freeze_vision_encoder: bool, train_expert_only: bool) -> Self {
        self.freeze_vision_encoder = freeze_vision_encoder;
        self.train_expert_only = train_expert_only;
        self
    }

    fn with_pad_language_to(mut self, pad: &str) -> Self {
        self.pad_language_to = pad.into();
        self
    }

    fn with_vlm_model_name(mut self, name: &str) -> Self {
        self.vlm_model_name = name.into();
        self
    }

    /// Replaces the cameras (in slot order) keeping their declared input size.
    pub fn with_cameras(mut self, names: &[&str]) -> Self {
        let (w, h) = self.resize_imgs_with_padding;
        let state = self.state_dim();
        let action = self.action_dim();
        self.input_features =
            std::iter::once(Feature { name: "observation.state".into(), kind: "STATE".into(), shape: vec![state] })
                .chain(names.iter().map(|n| Feature {
                    name: format!("observation.images.{n}"),
                    kind: "VISUAL".into(),
                    shape: vec![3, h, w],
                }))
                .collect();
        self.output_features[0].shape = vec![action];
        self
    }

    pub fn expert(&self) -> ExpertDims {
        let hidden = (self.vlm.text_config.hidden_size as f64 * self.expert_width_multiplier) as usize;
        let h = (2 * hidden) / 3;
        let multiple_of = 256;
        let intermediate = (4 * h).div_ceil(multiple_of) * multiple_of;
        ExpertDims { hidden_size: hidden, intermediate_size: intermediate, num_layers: self.num_vlm_layers }
    }

    /// Expert layer `l` is joint self-attention (true) or cross-attention into the VLM keys (false).
    pub fn is_self_attn_layer(&self, layer: usize) -> bool {
        layer.is_multiple_of(self.self_attn_every_n_layers)
    }

    pub fn camera_keys(&self) -> Vec<String> {
        self.input_features.iter().filter(|f| f.kind == "VISUAL").map(|f| f.name.clone()).collect()
    }

    pub fn state_dim(&self) -> usize {
        self.input_features.iter().find(|f| f.kind == "STATE").map_or(0, |f| f.shape[0])
    }

    pub fn action_dim(&self) -> usize {
        self.output_features.iter().find(|f| f.kind == "ACTION").map_or(0, |f| f.shape[0])
    }

    /// Image tokens per camera after the pixel-shuffle connector.
    /// Whether nothing of the backbone trains (vision tower, connector, token embeddings and text layers:
    /// `train_expert_only`): then the context's keys and values depend on the frame and the task alone, and a
    /// frozen-feature cache may keep them.
    pub fn backbone_frozen(&self) -> bool {
        self.train_expert_only
    }

    pub fn tokens_per_image(&self) -> usize {
        let v = &self.vlm.vision_config;
        let side = v.image_size / v.patch_size;
        (side / self.vlm.scale_factor).pow(2)
    }

    /// Checks the relations LeRobot's code assumes; every other module relies on them.
    pub fn validate(&self) -> Result<(), PolicyError> {
        let t = &self.vlm.text_config;
        let v = &self.vlm.vision_config;
        let bad = |m: String| Err(PolicyError::Config(m));
        if self.num_vlm_layers == 0 || self.num_vlm_layers > t.num_hidden_layers {
            return bad(format!(
                "num_vlm_layers {} must be in 1..={} (text layers of the backbone)",
                self.num_vlm_layers, t.num_hidden_layers
            ));
        }
        if !t.num_attention_heads.is_multiple_of(t.num_key_value_heads) {
            return bad(format!(
                "num_attention_heads {} is not a multiple of num_key_value_heads {}",
                t.num_attention_heads, t.num_key_value_heads
            ));
        }
        if !v.hidden_size.is_multiple_of(v.num_attention_heads) || !v.image_size.is_multiple_of(v.patch_size) {
            return bad("vision hidden_size/heads or image_size/patch_size do not divide".into());
        }
        if !(v.image_size / v.patch_size).is_multiple_of(self.vlm.scale_factor) {
            return bad(format!(
                "patch grid {} is not divisible by the connector scale_factor {}",
                v.image_size / v.patch_size,
                self.vlm.scale_factor
            ));
        }
        if self.camera_keys().is_empty() {
            return bad("input_features has no VISUAL feature: SmolVLA needs at least one camera".into());
        }
        if self.state_dim() > self.max_state_dim || self.action_dim() > self.max_action_dim {
            return bad(format!(
                "state dim {} / action dim {} exceed max_state_dim {} / max_action_dim {}",
                self.state_dim(),
                self.action_dim(),
                self.max_state_dim,
                self.max_action_dim
            ));
        }
        if self.action_dim() == 0 {
            return bad("output_features has no ACTION feature".into());
        }
        if self.self_attn_every_n_layers == 0 {
            return bad("self_attn_every_n_layers must be >= 1".into());
        }
        if self.chunk_size == 0 || self.n_action_steps == 0 || self.n_action_steps > self.chunk_size {
            return bad(format!(
                "n_action_steps {} must be in 1..=chunk_size {}",
                self.n_action_steps, self.chunk_size
            ));
        }
        Ok(())
    }
}

/// SO-100 features: 6 joints of state and action, cameras `observation.images.<name>`.
fn so100_features(cameras: &[&str], size: usize) -> (Vec<Feature>, Vec<Feature>) {
    let mut inputs = vec![Feature { name: "observation.state".into(), kind: "STATE".into(), shape: vec![6] }];
    inputs.extend(cameras.iter().map(|c| Feature {
        name: format!("observation.images.{c}"),
        kind: "VISUAL".into(),
        shape: vec![3, size, size],
    }));
    let outputs = vec![Feature { name: "action".into(), kind: "ACTION".into(), shape: vec![6] }];
    (inputs, outputs)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn expert_sizes_follow_lerobot_rounding() {
        assert_eq!(
            SmolVlaConfig::base().expert(),
            ExpertDims { hidden_size: 720, intermediate_size: 2048, num_layers: 16 }
        );
        assert_eq!(
            SmolVlaConfig::tiny().expert(),
            ExpertDims { hidden_size: 72, intermediate_size: 256, num_layers: 4 }
        );
    }

    #[test]
    fn presets_validate() {
        for name in ["base", "small", "tiny"] {
            SmolVlaConfig::preset(name).unwrap().validate().unwrap();
        }
        assert!(SmolVlaConfig::preset("huge").is_err());
    }
}
