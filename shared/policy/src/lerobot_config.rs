//! SmolVLA's configuration as LeRobot writes and reads it: the policy `config.json` and the backbone's
//! `vlm/config.json` (transformers' SmolVLMConfig).

use serde_json::{Map, Value, json};

use crate::config::{Feature, SmolVlaConfig, VlmConfig};
use crate::error::PolicyError;

impl SmolVlaConfig {
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
