//! Parity with LeRobot's own SmolVLA: loads a golden fixture folder (config.json, vlm/config.json,
//! model.safetensors, inputs.safetensors, outputs.safetensors), recomputes every output the
//! fixture holds with this crate, and reports the max abs difference per tensor.
//!
//! Output names are matched by pattern (`vision.<camera>.*`, `grad.<param>`, ...), so fixtures of
//! other sizes, camera counts and image shapes work without changes.

use std::collections::BTreeMap;
use std::path::Path;

use burn::tensor::{Device, Tensor};
use safetensors::{Dtype, SafeTensors};

use crate::batch::{Batch, Prepared, pad_last_dim, prepare_image};
use crate::config::SmolVlaConfig;
use crate::error::PolicyError;
use crate::normalize::FeatureStats;
use crate::smolvla::{SmolVla, time_embedding};
use crate::train::Trainer;
use crate::vlm_with_expert::Trace;
use crate::weights::{HostTensor, ParamStore, WeightMap, read_safetensors};

/// A tensor of any dtype as f64 values (bools as 0/1), for comparison.
#[derive(Debug, Clone)]
pub struct AnyTensor {
    pub shape: Vec<usize>,
    pub values: Vec<f64>,
}

impl AnyTensor {
    fn from_host(t: &HostTensor) -> Self {
        Self { shape: t.shape.clone(), values: t.data.iter().map(|&v| v as f64).collect() }
    }

    fn from_tensor<const D: usize>(t: Tensor<D>) -> Self {
        Self::from_host(&HostTensor::from_tensor(t))
    }

    fn bools(shape: Vec<usize>, v: &[bool]) -> Self {
        Self { shape, values: v.iter().map(|&b| b as u8 as f64).collect() }
    }

    fn ints(shape: Vec<usize>, v: &[i64]) -> Self {
        Self { shape, values: v.iter().map(|&x| x as f64).collect() }
    }

    fn stack(parts: Vec<AnyTensor>) -> Self {
        let mut shape = vec![parts.len()];
        shape.extend(parts.first().map(|p| p.shape.clone()).unwrap_or_default());
        Self { shape, values: parts.into_iter().flat_map(|p| p.values).collect() }
    }
}

/// Reads every tensor of a safetensors file whatever its dtype.
pub fn read_any(path: &Path) -> Result<BTreeMap<String, AnyTensor>, PolicyError> {
    let bytes = std::fs::read(path).map_err(|e| PolicyError::io(path, e))?;
    let st = SafeTensors::deserialize(&bytes)
        .map_err(|e| PolicyError::Safetensors { path: path.into(), message: e.to_string() })?;
    let mut out = BTreeMap::new();
    for (key, view) in st.tensors() {
        let d = view.data();
        let values: Vec<f64> = match view.dtype() {
            Dtype::BOOL | Dtype::U8 => d.iter().map(|&b| b as f64).collect(),
            Dtype::I64 => {
                d.chunks_exact(8).map(|b| i64::from_le_bytes(b.try_into().expect("8 bytes")) as f64).collect()
            }
            Dtype::I32 => {
                d.chunks_exact(4).map(|b| i32::from_le_bytes(b.try_into().expect("4 bytes")) as f64).collect()
            }
            Dtype::F64 => d.chunks_exact(8).map(|b| f64::from_le_bytes(b.try_into().expect("8 bytes"))).collect(),
            other => crate::weights::decode_floats(other, d)
                .ok_or_else(|| PolicyError::Dtype { path: path.into(), key: key.clone(), dtype: format!("{other:?}") })?
                .into_iter()
                .map(f64::from)
                .collect(),
        };
        out.insert(key, AnyTensor { shape: view.shape().to_vec(), values });
    }
    Ok(out)
}

/// One compared tensor.
#[derive(Debug, Clone)]
pub struct ParityRow {
    pub name: String,
    pub shape: Vec<usize>,
    /// `None` when the tensor could not be compared (shape mismatch or unknown name).
    pub max_abs_diff: Option<f64>,
    pub note: String,
}

/// The result of a parity run.
#[derive(Debug, Clone)]
pub struct ParityReport {
    pub rows: Vec<ParityRow>,
    pub tolerance: f64,
}

impl ParityReport {
    pub fn passed(&self) -> bool {
        !self.rows.is_empty() && self.rows.iter().all(|r| r.max_abs_diff.is_some_and(|d| d <= self.tolerance))
    }

    pub fn worst(&self) -> f64 {
        self.rows.iter().filter_map(|r| r.max_abs_diff).fold(0.0, f64::max)
    }
}

fn input<'a>(inputs: &'a BTreeMap<String, AnyTensor>, key: &str) -> Result<&'a AnyTensor, PolicyError> {
    inputs.get(key).ok_or_else(|| PolicyError::Input(format!("fixture inputs.safetensors has no {key:?}")))
}

fn host(t: &AnyTensor) -> HostTensor {
    HostTensor::new(t.shape.clone(), t.values.iter().map(|&v| v as f32).collect())
}

/// Builds the model batch from a fixture's `inputs.safetensors`.
pub fn fixture_batch(cfg: &SmolVlaConfig, inputs: &BTreeMap<String, AnyTensor>) -> Result<Batch, PolicyError> {
    let tokens = input(inputs, "observation.language.tokens")?;
    let mask = input(inputs, "observation.language.attention_mask")?;
    let images = cfg.camera_keys().iter().map(|k| input(inputs, k).map(host)).collect::<Result<_, _>>()?;
    Ok(Batch {
        images,
        lang_tokens: tokens.values.iter().map(|&v| v as i64).collect(),
        lang_mask: mask.values.iter().map(|&v| v != 0.0).collect(),
        lang_len: tokens.shape[1],
        state: host(input(inputs, "observation.state")?),
        actions: inputs.get("action").map(host),
        action_is_pad: inputs.get("action_is_pad").map(|t| t.values.iter().map(|&v| v != 0.0).collect()),
    })
}

/// Recomputes every tensor of `outputs.safetensors` in fixture `dir` on `device` (which must have
/// autodiff enabled) and compares.
pub fn run(dir: &Path, device: &Device, tolerance: f64) -> Result<ParityReport, PolicyError> {
    let cfg = crate::policy_dir::read_config(dir)?;
    let weights = read_safetensors(&dir.join("model.safetensors"))?;
    crate::weights::check_keys(&cfg.param_specs(), &weights, &dir.join("model.safetensors").display().to_string())?;
    let inputs = read_any(&dir.join("inputs.safetensors"))?;
    let expected = read_any(&dir.join("outputs.safetensors"))?;
    let batch = fixture_batch(&cfg, &inputs)?;
    let actual = recompute(&cfg, &weights, &batch, &inputs, device)?;

    let mut rows = Vec::new();
    for (name, exp) in &expected {
        let row = match actual.get(name) {
            None => ParityRow {
                name: name.clone(),
                shape: exp.shape.clone(),
                max_abs_diff: None,
                note: "not recomputed".into(),
            },
            Some(act) if act.shape != exp.shape => ParityRow {
                name: name.clone(),
                shape: exp.shape.clone(),
                max_abs_diff: None,
                note: format!("shape mismatch: ours {:?}", act.shape),
            },
            Some(act) => {
                // NaN anywhere is a failure, not a difference `f64::max` would skip.
                let diff = exp
                    .values
                    .iter()
                    .zip(&act.values)
                    .map(|(a, b)| (a - b).abs())
                    .fold(0.0, |m, d| if d.is_nan() { f64::INFINITY } else { m.max(d) });
                ParityRow {
                    name: name.clone(),
                    shape: exp.shape.clone(),
                    max_abs_diff: Some(diff),
                    note: String::new(),
                }
            }
        };
        rows.push(row);
    }
    Ok(ParityReport { rows, tolerance })
}

/// Every quantity a fixture may hold, by its output name.
fn recompute(
    cfg: &SmolVlaConfig,
    weights: &WeightMap,
    batch: &Batch,
    inputs: &BTreeMap<String, AnyTensor>,
    device: &Device,
) -> Result<BTreeMap<String, AnyTensor>, PolicyError> {
    let mut out = BTreeMap::new();
    let b = batch.batch_size();
    let (t, amax) = (cfg.chunk_size, cfg.max_action_dim);
    let cams = cfg.camera_keys();
    let (tw, th) = cfg.resize_imgs_with_padding;

    // Inference model without autodiff: traces, vision, sampling.
    let plain = device.clone().without_autodiff();
    let store = ParamStore::upload(weights.iter(), &plain, false);
    let model = SmolVla::new(cfg, &store);
    let obs = Prepared::new(cfg, batch, &plain)?;
    for (key, img) in cams.iter().zip(&batch.images) {
        out.insert(format!("prepared.images.{key}"), AnyTensor::from_host(&prepare_image(img, tw, th)));
    }
    out.insert("prepared.img_masks".into(), AnyTensor::bools(vec![cams.len(), b], &vec![true; cams.len() * b]));
    out.insert("prepared.state".into(), AnyTensor::from_host(&pad_last_dim(&batch.state, cfg.max_state_dim)));
    if let Some(actions) = &batch.actions {
        out.insert("prepared.actions".into(), AnyTensor::from_host(&pad_last_dim(actions, amax)));
    }
    let p = cfg.vlm.vision_config.patch_size;
    for (key, img) in cams.iter().zip(&obs.images) {
        let hidden = model.vlm.vision.forward(img.clone());
        out.insert(
            format!("vision.{key}.connector_out"),
            AnyTensor::from_tensor(model.vlm.connector.forward(hidden.clone())),
        );
        out.insert(format!("vision.{key}.last_hidden_state"), AnyTensor::from_tensor(hidden));
        let ids = model.vlm.vision.position_ids(th / p, tw / p);
        let n = ids.len();
        out.insert(format!("vision.{key}.position_ids"), AnyTensor::ints(vec![b, n], &ids.repeat(b)));
    }

    // Training forward with fixed noise/time and its trace.
    if let (Some(actions), Some(noise), Some(time)) = (&batch.actions, inputs.get("noise"), inputs.get("time")) {
        let time: Vec<f32> = time.values.iter().map(|&v| v as f32).collect();
        let mut trace = Trace::default();
        let fm = model.forward_loss(
            &obs,
            pad_last_dim(actions, amax).to_tensor(&plain),
            host(noise).to_tensor(&plain),
            &time,
            batch.action_is_pad.as_deref(),
            Some(&mut trace),
        );
        let prefix = model.encode_prefix(&obs, None);
        let lp = prefix.len;
        let l = lp + t;
        out.insert("fm.prefix_pad_masks".into(), AnyTensor::bools(vec![b, lp], &prefix.pad));
        let ar: Vec<bool> = (0..b).flat_map(|_| (0..lp).map(|i| i == lp - 1)).collect();
        out.insert("fm.prefix_att_masks".into(), AnyTensor::bools(vec![b, lp], &ar));
        out.insert("fm.suffix_pad_masks".into(), AnyTensor::bools(vec![b, t], &vec![true; b * t]));
        out.insert("fm.suffix_att_masks".into(), AnyTensor { shape: vec![b, t], values: vec![1.0; b * t] });
        let mut pad = Vec::new();
        let mut ar_full = Vec::new();
        for n in 0..b {
            pad.extend_from_slice(&prefix.pad[n * lp..(n + 1) * lp]);
            pad.extend(std::iter::repeat_n(true, t));
            ar_full.extend_from_slice(&ar[n * lp..(n + 1) * lp]);
            ar_full.extend(std::iter::repeat_n(true, t));
        }
        out.insert(
            "fm.att_2d_masks".into(),
            AnyTensor::bools(vec![b, l, l], &crate::batch::att_2d_mask(&pad, &ar_full, b, l)),
        );
        out.insert("fm.position_ids".into(), AnyTensor::ints(vec![b, l], &crate::batch::position_ids(&pad, b, l)));
        let de = cfg.expert().hidden_size;
        out.insert(
            "fm.time_emb".into(),
            AnyTensor {
                shape: vec![b, de],
                values: time_embedding(&time, de, cfg.min_period, cfg.max_period).into_iter().map(f64::from).collect(),
            },
        );
        if let Some(first) = trace.vlm_layer_inputs.first() {
            out.insert("fm.prefix_embs".into(), AnyTensor::from_tensor(first.clone()));
        }
        if let Some(first) = trace.expert_layer_inputs.first() {
            out.insert("fm.suffix_embs".into(), AnyTensor::from_tensor(first.clone()));
        }
        out.insert(
            "fm.vlm_layer_inputs".into(),
            AnyTensor::stack(trace.vlm_layer_inputs.into_iter().map(AnyTensor::from_tensor).collect()),
        );
        out.insert(
            "fm.expert_layer_inputs".into(),
            AnyTensor::stack(trace.expert_layer_inputs.into_iter().map(AnyTensor::from_tensor).collect()),
        );
        if let Some(p) = trace.prefix_out {
            out.insert("fm.prefix_out".into(), AnyTensor::from_tensor(p));
        }
        if let Some(s) = trace.suffix_out {
            out.insert("fm.suffix_out".into(), AnyTensor::from_tensor(s));
        }
        out.insert("fm.x_t".into(), AnyTensor::from_tensor(fm.x_t));
        out.insert("fm.u_t".into(), AnyTensor::from_tensor(fm.u_t));
        out.insert("fm.v_t".into(), AnyTensor::from_tensor(fm.v_t));
        out.insert("fm.losses".into(), AnyTensor::from_tensor(fm.losses));
        out.insert("policy.loss".into(), AnyTensor { shape: vec![], values: vec![fm.loss.into_scalar::<f64>()] });

        // Gradients, clipping and one AdamW step on the autodiff device.
        let mut trainer = Trainer::new(cfg, weights, device, 0)?;
        let before = trainer.trainable_weights();
        let (report, grads) = trainer.train_step_with(batch, host(noise).to_tensor(device), &time, cfg.optimizer_lr)?;
        let clip = (cfg.optimizer_grad_clip_norm / (report.grad_norm as f64 + 1e-6)).min(1.0);
        out.insert(
            "grad_norm_total_preclip".into(),
            AnyTensor { shape: vec![], values: vec![report.grad_norm as f64] },
        );
        let after = trainer.trainable_weights();
        for (name, g) in &grads {
            out.insert(format!("grad.{name}"), AnyTensor::from_host(g));
            let clipped: Vec<f64> =
                g.data.iter().map(|&v| if clip < 1.0 { (v as f64) * clip } else { v as f64 }).collect();
            out.insert(format!("grad_clipped.{name}"), AnyTensor { shape: g.shape.clone(), values: clipped });
        }
        for (name, w) in after.iter().chain(before.iter().filter(|(k, _)| !after.contains_key(*k))) {
            out.insert(format!("adamw_step1.{name}"), AnyTensor::from_host(w));
        }
    }

    // Sampling with fixed initial noise.
    if let Some(sample_noise) = inputs.get("sample_noise") {
        let mut steps = Vec::new();
        let actions = model.sample_actions(&obs, host(sample_noise).to_tensor(&plain), Some(&mut steps));
        let prefix = model.encode_prefix(&obs, None);
        let layout = model.suffix_layout(&prefix);
        let lp = prefix.len;
        out.insert("sample.prefix_att_2d_masks".into(), AnyTensor::bools(vec![b, lp, lp], &prefix.att_2d));
        out.insert("sample.prefix_position_ids".into(), AnyTensor::ints(vec![b, lp], &prefix.positions));
        out.insert("sample.denoise_att_2d_masks".into(), AnyTensor::bools(vec![b, t, lp + t], &layout.joint_mask));
        out.insert("sample.denoise_position_ids".into(), AnyTensor::ints(vec![b, t], &layout.positions));
        let kv_layout = |ts: &[Tensor<4>]| {
            AnyTensor::stack(ts.iter().map(|k| AnyTensor::from_tensor(k.clone().swap_dims(1, 2))).collect())
        };
        out.insert("sample.prefix_kv.keys".into(), kv_layout(&prefix.kv.keys));
        out.insert("sample.prefix_kv.values".into(), kv_layout(&prefix.kv.values));
        out.insert(
            "sample.time".into(),
            AnyTensor { shape: vec![steps.len()], values: steps.iter().map(|s| s.time as f64).collect() },
        );
        let mut xs: Vec<AnyTensor> = steps.iter().map(|s| AnyTensor::from_tensor(s.x.clone())).collect();
        xs.push(AnyTensor::from_tensor(actions.clone()));
        out.insert("sample.x_t".into(), AnyTensor::stack(xs));
        out.insert(
            "sample.v_t".into(),
            AnyTensor::stack(steps.into_iter().map(|s| AnyTensor::from_tensor(s.v)).collect()),
        );
        let a = cfg.action_dim();
        let chunk = HostTensor::from_tensor(actions.clone().narrow(2, 0, a));
        out.insert("sample.actions".into(), AnyTensor::from_tensor(actions));
        out.insert("policy.predict_action_chunk".into(), AnyTensor::from_host(&chunk));
        if let (Some(mean), Some(std)) = (inputs.get("stats.action.mean"), inputs.get("stats.action.std")) {
            let stats = FeatureStats { mean: host(mean).data, std: host(std).data };
            out.insert(
                "policy.predict_action_chunk.unnormalized".into(),
                AnyTensor::from_host(&HostTensor::new(chunk.shape.clone(), stats.unnormalize(&chunk.data))),
            );
        }
    }
    Ok(out)
}
