//! MEAN_STD normalisation of state and actions (LeRobot's normalizer/unnormalizer processor steps)
//! and the processor files that carry the statistics in a LeRobot policy directory.

use std::collections::BTreeMap;
use std::path::Path;

use serde_json::{Value, json};

use crate::config::SmolVlaConfig;
use crate::error::PolicyError;
use crate::weights::{HostTensor, WeightMap, read_safetensors, write_safetensors};

/// LeRobot's epsilon in `(x - mean) / (std + eps)`.
pub const NORM_EPS: f32 = 1e-8;

/// Mean and standard deviation of one feature.
#[derive(Debug, Clone, PartialEq)]
pub struct FeatureStats {
    pub mean: Vec<f32>,
    pub std: Vec<f32>,
}

impl FeatureStats {
    pub fn normalize(&self, x: &[f32]) -> Vec<f32> {
        x.iter()
            .enumerate()
            .map(|(i, v)| (v - self.mean[i % self.mean.len()]) / (self.std[i % self.std.len()] + NORM_EPS))
            .collect()
    }

    pub fn unnormalize(&self, y: &[f32]) -> Vec<f32> {
        y.iter().enumerate().map(|(i, v)| v * self.std[i % self.std.len()] + self.mean[i % self.mean.len()]).collect()
    }
}

/// Statistics of the normalised features (`observation.state`, `action`).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct NormStats {
    pub features: BTreeMap<String, FeatureStats>,
}

impl NormStats {
    pub fn get(&self, feature: &str) -> Result<&FeatureStats, PolicyError> {
        self.features
            .get(feature)
            .ok_or_else(|| PolicyError::Input(format!("no normalisation statistics for {feature:?}")))
    }

    /// Flat `"<feature>.mean"` / `"<feature>.std"` tensors, the processor state-file layout.
    pub fn to_tensors(&self) -> WeightMap {
        let mut out = WeightMap::new();
        for (name, s) in &self.features {
            out.insert(format!("{name}.mean"), HostTensor::new(vec![s.mean.len()], s.mean.clone()));
            out.insert(format!("{name}.std"), HostTensor::new(vec![s.std.len()], s.std.clone()));
        }
        out
    }

    pub fn from_tensors(tensors: &WeightMap) -> Self {
        let mut features = BTreeMap::new();
        for (key, mean) in tensors.iter().filter_map(|(k, t)| k.strip_suffix(".mean").map(|f| (f, t))) {
            if let Some(std) = tensors.get(&format!("{key}.std")) {
                features.insert(key.to_string(), FeatureStats { mean: mean.data.clone(), std: std.data.clone() });
            }
        }
        Self { features }
    }

    /// Reads the statistics from a LeRobot policy directory's pre-processor pipeline (the
    /// normalizer step's `state_file`, whatever its index). `None` when the directory has none.
    pub fn read_policy_dir(dir: &Path) -> Result<Option<Self>, PolicyError> {
        let path = dir.join(PREPROCESSOR_JSON);
        if !path.exists() {
            return Ok(None);
        }
        let text = std::fs::read_to_string(&path).map_err(|e| PolicyError::io(&path, e))?;
        let json: Value =
            serde_json::from_str(&text).map_err(|e| PolicyError::Json { path: path.clone(), source: e })?;
        let steps = json.get("steps").and_then(Value::as_array).cloned().unwrap_or_default();
        let state_file = steps
            .iter()
            .find(|s| s.get("registry_name").and_then(Value::as_str) == Some("normalizer_processor"))
            .and_then(|s| s.get("state_file").and_then(Value::as_str));
        match state_file {
            Some(f) => Ok(Some(Self::from_tensors(&read_safetensors(&dir.join(f))?))),
            None => Ok(None),
        }
    }

    /// Writes LeRobot's processor pipeline files (pre: rename, batch, newline, tokenizer, device,
    /// normalizer; post: unnormalizer, device) with their statistics.
    pub fn write_policy_dir(&self, dir: &Path, cfg: &SmolVlaConfig) -> Result<(), PolicyError> {
        let features: serde_json::Map<String, Value> = cfg
            .input_features
            .iter()
            .chain(&cfg.output_features)
            .map(|f| (f.name.clone(), json!({"type": f.kind, "shape": f.shape})))
            .collect();
        let norm_map = json!({"VISUAL": "IDENTITY", "STATE": "MEAN_STD", "ACTION": "MEAN_STD"});
        let pre = json!({
            "name": "policy_preprocessor",
            "steps": [
                {"registry_name": "rename_observations_processor", "config": {"rename_map": {}}},
                {"registry_name": "to_batch_processor", "config": {}},
                {"registry_name": "smolvla_new_line_processor", "config": {}},
                {"registry_name": "tokenizer_processor", "config": {
                    "max_length": cfg.tokenizer_max_length, "task_key": "task", "padding_side": "right",
                    "padding": cfg.pad_language_to, "truncation": true, "tokenizer_name": cfg.vlm_model_name}},
                {"registry_name": "device_processor", "config": {"device": "cpu", "float_dtype": null}},
                {"registry_name": "normalizer_processor", "config": {"eps": NORM_EPS, "features": features, "norm_map": norm_map},
                 "state_file": PREPROCESSOR_STATE}
            ]
        });
        let action: serde_json::Map<String, Value> =
            cfg.output_features.iter().map(|f| (f.name.clone(), json!({"type": f.kind, "shape": f.shape}))).collect();
        let post = json!({
            "name": "policy_postprocessor",
            "steps": [
                {"registry_name": "unnormalizer_processor", "config": {"eps": NORM_EPS, "features": action, "norm_map": norm_map},
                 "state_file": POSTPROCESSOR_STATE},
                {"registry_name": "device_processor", "config": {"device": "cpu", "float_dtype": null}}
            ]
        });
        let write_json = |name: &str, v: &Value| {
            let path = dir.join(name);
            let text = serde_json::to_string_pretty(v).expect("json");
            fedvla_fs::write_atomic(&path, text.as_bytes()).map_err(|e| PolicyError::io(&path, e))
        };
        write_json(PREPROCESSOR_JSON, &pre)?;
        write_json(POSTPROCESSOR_JSON, &post)?;
        let tensors = self.to_tensors();
        write_safetensors(&dir.join(PREPROCESSOR_STATE), &tensors)?;
        write_safetensors(&dir.join(POSTPROCESSOR_STATE), &tensors)
    }
}

pub const PREPROCESSOR_JSON: &str = "policy_preprocessor.json";
pub const POSTPROCESSOR_JSON: &str = "policy_postprocessor.json";
pub const PREPROCESSOR_STATE: &str = "policy_preprocessor_step_5_normalizer_processor.safetensors";
pub const POSTPROCESSOR_STATE: &str = "policy_postprocessor_step_0_unnormalizer_processor.safetensors";
