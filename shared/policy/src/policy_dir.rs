//! LeRobot policy directories in and out: `config.json` + `model.safetensors` + the processor
//! pipeline files with their statistics, and (for sizes other than smolvla_base) a `vlm/` folder
//! with the backbone config and tokenizer, so LeRobot can load the policy with no Hub access.

use std::path::{Path, PathBuf};

use serde_json::{Value, json};

use crate::config::{SmolVlaConfig, VlmConfig};
use crate::error::PolicyError;
use crate::normalize::NormStats;
use crate::tokenizer::{Tokenizer, WordTokenizer};
use crate::weights::{
    StoredDtype, TensorRef, WeightMap, check_keys, check_shapes, read_checkpoint, write_safetensors_as,
};

/// A policy read from disk.
#[derive(Debug, Clone)]
pub struct PolicyDir {
    pub cfg: SmolVlaConfig,
    pub weights: WeightMap,
    pub stats: Option<NormStats>,
    /// The backbone folder (config + tokenizer) when one is available locally.
    pub vlm_dir: Option<PathBuf>,
    /// What `model.safetensors` stores (the weights above are f32 whatever it is).
    pub dtype: StoredDtype,
}

fn read_json(path: &Path) -> Result<Value, PolicyError> {
    let text = std::fs::read_to_string(path).map_err(|e| PolicyError::io(path, e))?;
    serde_json::from_str(&text).map_err(|e| PolicyError::Json { path: path.into(), source: e })
}

/// The local backbone folder of a policy: `vlm_model_name` relative to the policy directory (as
/// LeRobot resolves it from its working directory), or a `vlm/` folder beside the weights.
pub fn find_vlm_dir(dir: &Path, vlm_model_name: &str) -> Option<PathBuf> {
    [dir.join(vlm_model_name), dir.join("vlm")].into_iter().find(|p| p.join("config.json").exists())
}

/// Reads a LeRobot SmolVLA `config.json` and the backbone config its `vlm_model_name` names.
/// The full `smolvla_base` backbone is known without its folder.
pub fn read_config(dir: &Path) -> Result<SmolVlaConfig, PolicyError> {
    let policy = read_json(&dir.join("config.json"))?;
    let vlm_name = policy.get("vlm_model_name").and_then(Value::as_str).unwrap_or("vlm");
    let vlm = match find_vlm_dir(dir, vlm_name) {
        Some(vlm_dir) => {
            let path = vlm_dir.join("config.json");
            serde_json::from_value::<VlmConfig>(read_json(&path)?).map_err(|e| PolicyError::Json { path, source: e })?
        }
        None if vlm_name == SmolVlaConfig::base().vlm_model_name => SmolVlaConfig::base().vlm,
        None => {
            return Err(PolicyError::Config(format!(
                "{}: the backbone {vlm_name:?} named by config.json is not available locally (expected {}/config.json)",
                dir.display(),
                dir.join(vlm_name).display()
            )));
        }
    };
    SmolVlaConfig::from_lerobot_json(&policy, vlm)
}

impl PolicyDir {
    /// Loads config, weights (checked key by key against the config) and statistics.
    pub fn load(dir: &Path) -> Result<Self, PolicyError> {
        let cfg = read_config(dir)?;
        let model_path = dir.join("model.safetensors");
        let (weights, dtype) = read_checkpoint(&model_path)?;
        check_keys(&cfg.param_specs(), &weights, &model_path.display().to_string())?;
        let stats = NormStats::read_policy_dir(dir)?;
        let vlm_dir = find_vlm_dir(dir, &cfg.vlm_model_name);
        Ok(Self { cfg, weights, stats, vlm_dir, dtype })
    }

    /// The tokenizer of this policy's backbone folder, when one is available locally.
    pub fn tokenizer(&self) -> Result<Option<Tokenizer>, PolicyError> {
        match &self.vlm_dir {
            Some(d) if d.join("tokenizer.json").exists() => Tokenizer::read(&d.join("tokenizer.json")).map(Some),
            _ => Ok(None),
        }
    }
}

/// Where an exported policy's backbone (config + tokenizer) comes from.
#[derive(Debug, Clone, Copy)]
pub enum Backbone<'a> {
    /// `vlm_model_name` names a backbone LeRobot can already resolve (e.g. the Hub id).
    Named,
    /// Write a `vlm/` folder for this configuration with the given word-level tokenizer.
    Generated(&'a WordTokenizer),
    /// Copy an existing local backbone folder to `vlm/`.
    CopyFrom(&'a Path),
    /// Write a `vlm/` folder for this configuration with the tokenizer (`tokenizer.json`, `tokenizer_config.json`)
    /// of an existing backbone folder: a backbone of one size speaking another's vocabulary (a full-size rehearsal
    /// checkpoint with a small fixture's tokenizer).
    GeneratedWithTokenizerOf(&'a Path),
}

/// Writes a LeRobot-loadable policy directory, `model.safetensors` in `dtype`, of `weights`, every tensor of the
/// checkpoint wherever it is held (the frozen ones and a round's trainable ones need not be merged first: each is
/// read and encoded as it is written). Every file goes through a temporary name and a rename, so an interrupted
/// export never leaves a half-written checkpoint behind.
pub fn export<'a>(
    dir: &Path,
    cfg: &SmolVlaConfig,
    weights: impl IntoIterator<Item = (&'a String, TensorRef<'a>)>,
    stats: &NormStats,
    backbone: Backbone<'_>,
    dtype: StoredDtype,
) -> Result<(), PolicyError> {
    let weights: Vec<(&String, TensorRef<'_>)> = weights.into_iter().collect();
    check_shapes(&cfg.param_specs(), weights.iter().map(|(k, t)| (k.as_str(), t.shape())), "export")?;
    std::fs::create_dir_all(dir).map_err(|e| PolicyError::io(dir, e))?;
    let mut cfg = cfg.clone();
    let vlm = dir.join("vlm");
    match backbone {
        Backbone::Named => {}
        Backbone::Generated(tok) => {
            // A backbone that is not on the Hub travels with the policy as `vlm/`.
            cfg.vlm_model_name = "vlm".into();
            write_backbone_config(&vlm, &cfg)?;
            write_json(&vlm.join("tokenizer.json"), &tok.to_json())?;
            write_json(&vlm.join("tokenizer_config.json"), &WordTokenizer::tokenizer_config())?;
        }
        Backbone::GeneratedWithTokenizerOf(src) => {
            cfg.vlm_model_name = "vlm".into();
            write_backbone_config(&vlm, &cfg)?;
            for name in ["tokenizer.json", "tokenizer_config.json"] {
                copy_file(&src.join(name), &vlm.join(name))?;
            }
        }
        Backbone::CopyFrom(src) => {
            cfg.vlm_model_name = "vlm".into();
            std::fs::create_dir_all(&vlm).map_err(|e| PolicyError::io(&vlm, e))?;
            let entries = std::fs::read_dir(src).map_err(|e| PolicyError::io(src, e))?;
            for entry in entries {
                let path = entry.map_err(|e| PolicyError::io(src, e))?.path();
                if path.is_file() && path.parent() != Some(vlm.as_path()) {
                    copy_file(&path, &vlm.join(path.file_name().expect("file name")))?;
                }
            }
        }
    }
    write_json(&dir.join("config.json"), &cfg.to_lerobot_json())?;
    write_safetensors_as(&dir.join("model.safetensors"), weights, dtype)?;
    stats.write_policy_dir(dir, &cfg)
}

/// The backbone folder's `config.json` and `processor_config.json` for `cfg`, as transformers reads them.
fn write_backbone_config(vlm: &Path, cfg: &SmolVlaConfig) -> Result<(), PolicyError> {
    std::fs::create_dir_all(vlm).map_err(|e| PolicyError::io(vlm, e))?;
    write_json(&vlm.join("config.json"), &cfg.vlm_config_json())?;
    write_json(&vlm.join("processor_config.json"), &processor_config(cfg))
}

fn copy_file(from: &Path, to: &Path) -> Result<(), PolicyError> {
    let bytes = std::fs::read(from).map_err(|e| PolicyError::io(from, e))?;
    fedvla_fs::write_atomic(to, &bytes).map_err(|e| PolicyError::io(to, e))
}

fn write_json(path: &Path, value: &Value) -> Result<(), PolicyError> {
    let text = serde_json::to_string_pretty(value).expect("serialisable JSON");
    fedvla_fs::write_atomic(path, text.as_bytes()).map_err(|e| PolicyError::io(path, e))
}

/// SmolVLMProcessor settings transformers needs to build the processor of a local backbone.
fn processor_config(cfg: &SmolVlaConfig) -> Value {
    let size = cfg.vlm.vision_config.image_size;
    let image = json!({
        "do_convert_rgb": true, "do_image_splitting": false, "do_normalize": true, "do_pad": true,
        "do_rescale": true, "do_resize": true, "image_mean": [0.5, 0.5, 0.5], "image_std": [0.5, 0.5, 0.5],
        "image_processor_type": "SmolVLMImageProcessor", "max_image_size": {"longest_edge": size},
        "resample": 1, "rescale_factor": 1.0 / 255.0, "size": {"longest_edge": size}
    });
    let video = json!({
        "do_convert_rgb": true, "do_normalize": true, "do_pad": true, "do_rescale": true, "do_resize": true,
        "do_sample_frames": false, "image_mean": [0.5, 0.5, 0.5], "image_std": [0.5, 0.5, 0.5],
        "max_image_size": {"longest_edge": size}, "resample": 1, "rescale_factor": 1.0 / 255.0,
        "return_metadata": false, "size": {"longest_edge": size}, "video_processor_type": "SmolVLMVideoProcessor"
    });
    json!({
        "image_processor": image, "video_processor": video, "image_seq_len": cfg.tokens_per_image(),
        "processor_class": "SmolVLMProcessor"
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::normalize::FeatureStats;
    use crate::weights::{host_refs, init_random};

    fn stats() -> NormStats {
        let mut s = NormStats::default();
        for f in ["observation.state", "action"] {
            s.features.insert(f.into(), FeatureStats { mean: vec![0.5; 6], std: vec![2.0; 6] });
        }
        s
    }

    #[test]
    fn export_then_load_round_trips_every_tensor_bit_exactly() {
        let dir = std::env::temp_dir().join(format!("fedvla-export-{}", std::process::id()));
        let cfg = SmolVlaConfig::tiny();
        let weights = init_random(&cfg.param_specs(), 7);
        let tok = WordTokenizer::from_texts(["put the cube in the bowl"]);
        export(&dir, &cfg, host_refs(&weights), &stats(), Backbone::Generated(&tok), StoredDtype::F32).unwrap();
        let loaded = PolicyDir::load(&dir).unwrap();
        assert_eq!(loaded.dtype, StoredDtype::F32);
        assert_eq!(loaded.weights.len(), weights.len());
        for (k, t) in &weights {
            let l = &loaded.weights[k];
            assert_eq!(l.shape, t.shape, "{k}");
            assert!(l.data.iter().zip(&t.data).all(|(a, b)| a.to_bits() == b.to_bits()), "{k} changed");
        }
        assert_eq!(loaded.stats, Some(stats()));
        assert_eq!(loaded.cfg.param_specs(), cfg.param_specs());
        let Some(Tokenizer::Word(read_back)) = loaded.tokenizer().unwrap() else { panic!("word tokenizer expected") };
        assert_eq!(read_back, tok);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn a_bf16_export_reloads_within_bf16_rounding_at_half_the_bytes() {
        let dir = std::env::temp_dir().join(format!("fedvla-export-bf16-{}", std::process::id()));
        let (f32_dir, bf16_dir) = (dir.join("f32"), dir.join("bf16"));
        let cfg = SmolVlaConfig::tiny();
        let weights = init_random(&cfg.param_specs(), 7);
        let tok = WordTokenizer::from_texts(["put the cube in the bowl"]);
        export(&f32_dir, &cfg, host_refs(&weights), &stats(), Backbone::Generated(&tok), StoredDtype::F32).unwrap();
        export(&bf16_dir, &cfg, host_refs(&weights), &stats(), Backbone::Generated(&tok), StoredDtype::Bf16).unwrap();
        let loaded = PolicyDir::load(&bf16_dir).unwrap();
        assert_eq!(loaded.dtype, StoredDtype::Bf16);
        for (k, t) in &weights {
            for (a, b) in loaded.weights[k].data.iter().zip(&t.data) {
                // bf16 keeps 8 significant bits: round to nearest is within half a unit in the last place.
                assert!((a - b).abs() <= b.abs() * 2f32.powi(-8), "{k}: {b} stored as {a}");
            }
        }
        let size = |d: &Path| std::fs::metadata(d.join("model.safetensors")).unwrap().len() as f64;
        let ratio = size(&bf16_dir) / size(&f32_dir);
        assert!((0.49..0.52).contains(&ratio), "bf16 file is {ratio} of the f32 one");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
