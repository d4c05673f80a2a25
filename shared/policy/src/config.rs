//! SmolVLA configuration: the policy fields LeRobot writes to `config.json`, the SmolVLM2 backbone
//! fields it reads from `vlm/config.json`, the derived action-expert sizes, named presets
//! (`base`, `small`, `tiny`) and the full list of checkpoint tensors (names, shapes, and which of
//! them LeRobot's `freeze_vision_encoder` / `train_expert_only` / `train_state_proj` switches
//! train) that every loader, exporter and optimizer in this crate is driven by.

use serde::{Deserialize, Serialize};
use serde_json::{Map, Value, json};

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
        layer % self.self_attn_every_n_layers == 0
    }

    pub fn camera_keys(&self) -> Vec<String> {
        self.input_features.iter().filter(|f| f.kind == "VISUAL").map(|f| f.name.clone()).collect()
    }

    pub fn state_dim(&self) -> usize {
        self.input_features.iter().find(|f| f.kind == "STATE").map(|f| f.shape[0]).unwrap_or(0)
    }

    pub fn action_dim(&self) -> usize {
        self.output_features.iter().find(|f| f.kind == "ACTION").map(|f| f.shape[0]).unwrap_or(0)
    }

    /// Image tokens per camera after the pixel-shuffle connector.
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
        if t.num_attention_heads % t.num_key_value_heads != 0 {
            return bad(format!(
                "num_attention_heads {} is not a multiple of num_key_value_heads {}",
                t.num_attention_heads, t.num_key_value_heads
            ));
        }
        if v.hidden_size % v.num_attention_heads != 0 || v.image_size % v.patch_size != 0 {
            return bad("vision hidden_size/heads or image_size/patch_size do not divide".into());
        }
        if (v.image_size / v.patch_size) % self.vlm.scale_factor != 0 {
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

    /// Every tensor of the checkpoint, in LeRobot's module order, marked trainable as LeRobot's
    /// `set_requires_grad` marks it under this configuration's switches.
    pub fn param_specs(&self) -> Vec<ParamSpec> {
        let mut specs = Vec::new();
        let mut add =
            |name: String, shape: Vec<usize>, trainable: bool| specs.push(ParamSpec { name, shape, trainable });
        let backbone = !self.train_expert_only;
        let vision = backbone && !self.freeze_vision_encoder;
        let v = &self.vlm.vision_config;
        let t = &self.vlm.text_config;
        let e = self.expert();
        let (dv, dt, de) = (v.hidden_size, t.hidden_size, e.hidden_size);
        let kv = t.num_key_value_heads * t.head_dim;
        let q = t.num_attention_heads * t.head_dim;

        let vp = VISION_PREFIX;
        add(format!("{vp}.embeddings.patch_embedding.weight"), vec![dv, 3, v.patch_size, v.patch_size], vision);
        add(format!("{vp}.embeddings.patch_embedding.bias"), vec![dv], vision);
        let patches = (v.image_size / v.patch_size).pow(2);
        add(format!("{vp}.embeddings.position_embedding.weight"), vec![patches, dv], vision);
        for n in 0..v.num_hidden_layers {
            let p = format!("{vp}.encoder.layers.{n}");
            for norm in ["layer_norm1", "layer_norm2"] {
                add(format!("{p}.{norm}.weight"), vec![dv], vision);
                add(format!("{p}.{norm}.bias"), vec![dv], vision);
            }
            for proj in ["q_proj", "k_proj", "v_proj", "out_proj"] {
                add(format!("{p}.self_attn.{proj}.weight"), vec![dv, dv], vision);
                add(format!("{p}.self_attn.{proj}.bias"), vec![dv], vision);
            }
            add(format!("{p}.mlp.fc1.weight"), vec![v.intermediate_size, dv], vision);
            add(format!("{p}.mlp.fc1.bias"), vec![v.intermediate_size], vision);
            add(format!("{p}.mlp.fc2.weight"), vec![dv, v.intermediate_size], vision);
            add(format!("{p}.mlp.fc2.bias"), vec![dv], vision);
        }
        add(format!("{vp}.post_layernorm.weight"), vec![dv], vision);
        add(format!("{vp}.post_layernorm.bias"), vec![dv], vision);
        add(CONNECTOR_KEY.into(), vec![dt, dv * self.vlm.scale_factor.pow(2)], backbone);

        let tp = TEXT_PREFIX;
        add(format!("{tp}.embed_tokens.weight"), vec![t.vocab_size, dt], backbone);
        for n in 0..self.num_vlm_layers {
            let p = format!("{tp}.layers.{n}");
            let trained = backbone && n + 1 < self.num_vlm_layers;
            add(format!("{p}.input_layernorm.weight"), vec![dt], trained);
            add(format!("{p}.self_attn.q_proj.weight"), vec![q, dt], trained);
            add(format!("{p}.self_attn.k_proj.weight"), vec![kv, dt], trained);
            add(format!("{p}.self_attn.v_proj.weight"), vec![kv, dt], trained);
            add(format!("{p}.self_attn.o_proj.weight"), vec![dt, q], trained);
            add(format!("{p}.post_attention_layernorm.weight"), vec![dt], trained);
            add(format!("{p}.mlp.gate_proj.weight"), vec![t.intermediate_size, dt], trained);
            add(format!("{p}.mlp.up_proj.weight"), vec![t.intermediate_size, dt], trained);
            add(format!("{p}.mlp.down_proj.weight"), vec![dt, t.intermediate_size], trained);
        }
        add(format!("{tp}.norm.weight"), vec![dt], false);
        add(LM_HEAD_KEY.into(), vec![t.vocab_size, dt], false);

        let ep = EXPERT_PREFIX;
        for n in 0..e.num_layers {
            let p = format!("{ep}.layers.{n}");
            let kv_in = if self.is_self_attn_layer(n) { de } else { kv };
            add(format!("{p}.input_layernorm.weight"), vec![de], true);
            add(format!("{p}.self_attn.q_proj.weight"), vec![q, de], true);
            add(format!("{p}.self_attn.k_proj.weight"), vec![kv, kv_in], true);
            add(format!("{p}.self_attn.v_proj.weight"), vec![kv, kv_in], true);
            add(format!("{p}.self_attn.o_proj.weight"), vec![de, q], true);
            add(format!("{p}.post_attention_layernorm.weight"), vec![de], true);
            add(format!("{p}.mlp.gate_proj.weight"), vec![e.intermediate_size, de], true);
            add(format!("{p}.mlp.up_proj.weight"), vec![e.intermediate_size, de], true);
            add(format!("{p}.mlp.down_proj.weight"), vec![de, e.intermediate_size], true);
        }
        add(format!("{ep}.norm.weight"), vec![de], true);

        let shapes = [
            ([dt, self.max_state_dim], dt),
            ([de, self.max_action_dim], de),
            ([self.max_action_dim, de], self.max_action_dim),
            ([de, 2 * de], de),
            ([de, de], de),
        ];
        for (name, (w, b)) in PROJECTIONS.iter().zip(shapes) {
            let trained = self.train_state_proj || *name != "model.state_proj";
            add(format!("{name}.weight"), w.to_vec(), trained);
            add(format!("{name}.bias"), vec![b], trained);
        }
        specs
    }

    /// Reads a LeRobot policy `config.json` plus the backbone config it points to.
    pub fn from_lerobot_json(policy: &Value, vlm: VlmConfig) -> Result<Self, PolicyError> {
        let obj = policy.as_object().ok_or_else(|| PolicyError::Config("config.json is not a JSON object".into()))?;
        if let Some(t) = obj.get("type").and_then(Value::as_str)
            && t != "smolvla"
        {
            return Err(PolicyError::Config(format!("config.json has type {t:?}, expected \"smolvla\"")));
        }
        let num = |k: &str| -> Result<f64, PolicyError> {
            obj.get(k)
                .and_then(Value::as_f64)
                .ok_or_else(|| PolicyError::Config(format!("config.json: missing or non-numeric field {k:?}")))
        };
        let uint = |k: &str| num(k).map(|x| x as usize);
        let string = |k: &str| -> Result<String, PolicyError> {
            obj.get(k)
                .and_then(Value::as_str)
                .map(str::to_owned)
                .ok_or_else(|| PolicyError::Config(format!("config.json: missing or non-string field {k:?}")))
        };
        let pair = |k: &str| -> Result<(f64, f64), PolicyError> {
            let a = obj.get(k).and_then(Value::as_array).filter(|a| a.len() == 2);
            let a = a.ok_or_else(|| PolicyError::Config(format!("config.json: {k:?} must be a 2-element list")))?;
            Ok((a[0].as_f64().unwrap_or(f64::NAN), a[1].as_f64().unwrap_or(f64::NAN)))
        };
        // LeRobot's defaults when absent.
        let flag = |k: &str| -> Result<bool, PolicyError> {
            match obj.get(k) {
                None => Ok(true),
                Some(v) => {
                    v.as_bool().ok_or_else(|| PolicyError::Config(format!("config.json: {k:?} must be a boolean")))
                }
            }
        };
        let features = |k: &str| -> Result<Vec<Feature>, PolicyError> {
            let map = obj
                .get(k)
                .and_then(Value::as_object)
                .ok_or_else(|| PolicyError::Config(format!("config.json: missing {k:?}")))?;
            map.iter()
                .map(|(name, f)| {
                    let kind = f.get("type").and_then(Value::as_str).unwrap_or_default().to_owned();
                    let shape = f
                        .get("shape")
                        .and_then(Value::as_array)
                        .map(|s| s.iter().filter_map(Value::as_u64).map(|x| x as usize).collect())
                        .unwrap_or_default();
                    Ok(Feature { name: name.clone(), kind, shape })
                })
                .collect()
        };
        for (k, expected) in [("attention_mode", "cross_attn")] {
            if let Some(v) = obj.get(k).and_then(Value::as_str)
                && v != expected
            {
                return Err(PolicyError::Config(format!(
                    "config.json: {k} {v:?} is not supported (only {expected:?})"
                )));
            }
        }
        let num_vlm_layers = uint("num_vlm_layers")?;
        if let Some(n) = obj.get("num_expert_layers").and_then(Value::as_i64)
            && n > 0
            && n as usize != num_vlm_layers
        {
            return Err(PolicyError::Config(format!(
                "config.json: num_expert_layers {n} differs from num_vlm_layers {num_vlm_layers}; only equal depths are supported"
            )));
        }
        if obj.get("empty_cameras").and_then(Value::as_u64).unwrap_or(0) != 0 {
            return Err(PolicyError::Config("config.json: empty_cameras > 0 is not supported".into()));
        }
        let (rw, rh) = pair("resize_imgs_with_padding")?;
        let cfg = Self {
            vlm,
            input_features: features("input_features")?,
            output_features: features("output_features")?,
            chunk_size: uint("chunk_size")?,
            n_action_steps: uint("n_action_steps")?,
            max_state_dim: uint("max_state_dim")?,
            max_action_dim: uint("max_action_dim")?,
            resize_imgs_with_padding: (rw as usize, rh as usize),
            tokenizer_max_length: uint("tokenizer_max_length")?,
            pad_language_to: string("pad_language_to")?,
            num_steps: uint("num_steps")?,
            num_vlm_layers,
            self_attn_every_n_layers: uint("self_attn_every_n_layers")?,
            expert_width_multiplier: num("expert_width_multiplier")?,
            min_period: num("min_period")?,
            max_period: num("max_period")?,
            optimizer_lr: num("optimizer_lr")?,
            optimizer_betas: pair("optimizer_betas")?,
            optimizer_eps: num("optimizer_eps")?,
            optimizer_weight_decay: num("optimizer_weight_decay")?,
            optimizer_grad_clip_norm: num("optimizer_grad_clip_norm")?,
            scheduler_warmup_steps: uint("scheduler_warmup_steps")?,
            scheduler_decay_steps: uint("scheduler_decay_steps")?,
            scheduler_decay_lr: num("scheduler_decay_lr")?,
            vlm_model_name: string("vlm_model_name")?,
            freeze_vision_encoder: flag("freeze_vision_encoder")?,
            train_expert_only: flag("train_expert_only")?,
            train_state_proj: flag("train_state_proj")?,
        };
        cfg.validate()?;
        Ok(cfg)
    }

    /// The policy `config.json` LeRobot 0.6 writes (and reads back with `draccus`).
    pub fn to_lerobot_json(&self) -> Value {
        let features = |fs: &[Feature]| {
            let mut m = Map::new();
            for f in fs {
                m.insert(f.name.clone(), json!({"type": f.kind, "shape": f.shape}));
            }
            Value::Object(m)
        };
        json!({
            "type": "smolvla",
            "n_obs_steps": 1,
            "input_features": features(&self.input_features),
            "output_features": features(&self.output_features),
            "device": "cpu",
            "use_amp": false,
            "use_peft": false,
            "push_to_hub": false,
            "repo_id": null,
            "private": null,
            "tags": null,
            "license": null,
            "pretrained_path": null,
            "pretrained_revision": null,
            "chunk_size": self.chunk_size,
            "n_action_steps": self.n_action_steps,
            "normalization_mapping": {"VISUAL": "IDENTITY", "STATE": "MEAN_STD", "ACTION": "MEAN_STD"},
            "max_state_dim": self.max_state_dim,
            "max_action_dim": self.max_action_dim,
            "resize_imgs_with_padding": [self.resize_imgs_with_padding.0, self.resize_imgs_with_padding.1],
            "empty_cameras": 0,
            "adapt_to_pi_aloha": false,
            "use_delta_joint_actions_aloha": false,
            "tokenizer_max_length": self.tokenizer_max_length,
            "num_steps": self.num_steps,
            "use_cache": true,
            "freeze_vision_encoder": self.freeze_vision_encoder,
            "train_expert_only": self.train_expert_only,
            "train_state_proj": self.train_state_proj,
            "optimizer_lr": self.optimizer_lr,
            "optimizer_betas": [self.optimizer_betas.0, self.optimizer_betas.1],
            "optimizer_eps": self.optimizer_eps,
            "optimizer_weight_decay": self.optimizer_weight_decay,
            "optimizer_grad_clip_norm": self.optimizer_grad_clip_norm,
            "scheduler_warmup_steps": self.scheduler_warmup_steps,
            "scheduler_decay_steps": self.scheduler_decay_steps,
            "scheduler_decay_lr": self.scheduler_decay_lr,
            "vlm_model_name": self.vlm_model_name,
            "load_vlm_weights": false,
            "add_image_special_tokens": false,
            "attention_mode": "cross_attn",
            "prefix_length": -1,
            "pad_language_to": self.pad_language_to,
            "num_expert_layers": -1,
            "num_vlm_layers": self.num_vlm_layers,
            "self_attn_every_n_layers": self.self_attn_every_n_layers,
            "expert_width_multiplier": self.expert_width_multiplier,
            "min_period": self.min_period,
            "max_period": self.max_period,
            "rtc_config": null,
            "compile_model": false,
            "compile_mode": "max-autotune"
        })
    }

    /// The backbone `config.json` transformers' SmolVLMConfig reads (for a `vlm/` folder).
    pub fn vlm_config_json(&self) -> Value {
        let v = &self.vlm.vision_config;
        let t = &self.vlm.text_config;
        json!({
            "model_type": "smolvlm",
            "scale_factor": self.vlm.scale_factor,
            "pad_token_id": crate::tokenizer::PAD_ID,
            "image_token_id": crate::tokenizer::IMAGE_ID,
            "tie_word_embeddings": false,
            "use_cache": true,
            "text_config": {
                "model_type": "llama",
                "vocab_size": t.vocab_size,
                "hidden_size": t.hidden_size,
                "intermediate_size": t.intermediate_size,
                "num_hidden_layers": t.num_hidden_layers,
                "num_attention_heads": t.num_attention_heads,
                "num_key_value_heads": t.num_key_value_heads,
                "head_dim": t.head_dim,
                "rms_norm_eps": t.rms_norm_eps,
                "hidden_act": "silu",
                "attention_bias": false,
                "mlp_bias": false,
                "max_position_embeddings": 2048,
                "bos_token_id": crate::tokenizer::BOS_ID,
                "eos_token_id": crate::tokenizer::PAD_ID,
                "pad_token_id": crate::tokenizer::PAD_ID,
                "tie_word_embeddings": false,
                "rope_parameters": {"rope_theta": 100000.0, "rope_type": "default"}
            },
            "vision_config": {
                "model_type": "smolvlm_vision",
                "hidden_size": v.hidden_size,
                "intermediate_size": v.intermediate_size,
                "num_hidden_layers": v.num_hidden_layers,
                "num_attention_heads": v.num_attention_heads,
                "image_size": v.image_size,
                "patch_size": v.patch_size,
                "num_channels": 3,
                "layer_norm_eps": v.layer_norm_eps,
                "hidden_act": "gelu_pytorch_tanh"
            }
        })
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
