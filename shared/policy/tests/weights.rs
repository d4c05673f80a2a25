//! Checkpoint contract: the full configuration's tensor list equals smolvla_base's, and loading
//! reports every missing, unexpected or mis-shaped key.

use std::path::PathBuf;

use fedvla_policy::weights::{HostTensor, check_keys, init_random, read_safetensors};
use fedvla_policy::{PolicyError, SmolVlaConfig};
use safetensors::Dtype;

#[test]
fn full_config_matches_smolvla_base_parameter_counts() {
    let specs = SmolVlaConfig::base().param_specs();
    assert_eq!(specs.len(), 500);
    assert_eq!(specs.iter().map(|s| s.numel()).sum::<usize>(), 450_046_176);
    assert_eq!(specs.iter().filter(|s| s.trainable).map(|s| s.numel()).sum::<usize>(), 99_880_992);
}

#[test]
fn full_config_names_and_shapes_equal_the_reference_list() {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../../shared/reference/smolvla_base_shapes.json");
    let Ok(text) = std::fs::read_to_string(&path) else {
        eprintln!("SKIPPED: {} not found; names/shapes not compared", path.display());
        return;
    };
    let reference: serde_json::Map<String, serde_json::Value> = serde_json::from_str(&text).unwrap();
    let ours: std::collections::BTreeMap<String, Vec<usize>> =
        SmolVlaConfig::base().param_specs().into_iter().map(|s| (s.name, s.shape)).collect();
    assert_eq!(ours.len(), reference.len());
    for (name, shape) in &reference {
        let shape: Vec<usize> = shape.as_array().unwrap().iter().map(|v| v.as_u64().unwrap() as usize).collect();
        assert_eq!(ours.get(name), Some(&shape), "{name}");
    }
}

/// Writes `tensors` as safetensors, the trainable ones in F32 and the rest in BF16, as a
/// LeRobot checkpoint mixes them.
fn write_mixed(path: &std::path::Path, tensors: &[(String, HostTensor, bool)]) {
    let raw: Vec<(String, Dtype, Vec<u8>, Vec<usize>)> = tensors
        .iter()
        .map(|(k, t, f32_dtype)| {
            let (dtype, bytes) = if *f32_dtype {
                (Dtype::F32, t.data.iter().flat_map(|x| x.to_le_bytes()).collect())
            } else {
                (Dtype::BF16, t.data.iter().flat_map(|x| half::bf16::from_f32(*x).to_le_bytes()).collect())
            };
            (k.clone(), dtype, bytes, t.shape.clone())
        })
        .collect();
    let views: Vec<(String, safetensors::tensor::TensorView<'_>)> = raw
        .iter()
        .map(|(k, d, b, s)| (k.clone(), safetensors::tensor::TensorView::new(*d, s.clone(), b).unwrap()))
        .collect();
    std::fs::write(path, safetensors::serialize(views, None).unwrap()).unwrap();
}

fn tiny_checkpoint() -> (SmolVlaConfig, Vec<(String, HostTensor, bool)>) {
    let cfg = SmolVlaConfig::tiny();
    let specs = cfg.param_specs();
    let weights = init_random(&specs, 3);
    let tensors = specs.iter().map(|s| (s.name.clone(), weights[&s.name].clone(), s.trainable)).collect();
    (cfg, tensors)
}

fn load_error(tensors: &[(String, HostTensor, bool)], cfg: &SmolVlaConfig, tag: &str) -> String {
    let path = std::env::temp_dir().join(format!("fedvla-{tag}-{}.safetensors", std::process::id()));
    write_mixed(&path, tensors);
    let loaded = read_safetensors(&path).unwrap();
    std::fs::remove_file(&path).unwrap();
    match check_keys(&cfg.param_specs(), &loaded, "ckpt") {
        Err(e @ PolicyError::KeyMismatch { .. }) => e.to_string(),
        other => panic!("expected a key mismatch, got {other:?}"),
    }
}

#[test]
fn mixed_bf16_f32_checkpoint_loads_with_values_converted() {
    let (cfg, tensors) = tiny_checkpoint();
    let path = std::env::temp_dir().join(format!("fedvla-mixed-{}.safetensors", std::process::id()));
    write_mixed(&path, &tensors);
    let loaded = read_safetensors(&path).unwrap();
    std::fs::remove_file(&path).unwrap();
    check_keys(&cfg.param_specs(), &loaded, "mixed").unwrap();
    for (k, t, is_f32) in &tensors {
        let expected: Vec<f32> =
            if *is_f32 { t.data.clone() } else { t.data.iter().map(|x| half::bf16::from_f32(*x).to_f32()).collect() };
        assert_eq!(loaded[k].data, expected, "{k}");
    }
}

#[test]
fn missing_extra_and_misshaped_keys_are_each_named() {
    let (cfg, tensors) = tiny_checkpoint();
    let missing = "model.action_out_proj.bias";
    let without: Vec<_> = tensors.iter().filter(|(k, _, _)| k != missing).cloned().collect();
    let msg = load_error(&without, &cfg, "missing");
    assert!(msg.contains(&format!("missing key {missing}")), "{msg}");

    let mut extra = tensors.clone();
    extra.push(("model.unknown_head.weight".into(), HostTensor::new(vec![2], vec![0.0, 1.0]), true));
    let msg = load_error(&extra, &cfg, "extra");
    assert!(msg.contains("unexpected key model.unknown_head.weight"), "{msg}");

    let mut wrong = tensors.clone();
    wrong[0].1 = HostTensor::new(vec![1], vec![0.0]);
    let msg = load_error(&wrong, &cfg, "shape");
    assert!(msg.contains(&format!("wrong shape for {}", wrong[0].0)), "{msg}");
}

#[test]
fn torch_compile_prefix_is_stripped_and_normalizer_buffers_ignored() {
    let (cfg, tensors) = tiny_checkpoint();
    let mut renamed: Vec<_> =
        tensors.into_iter().map(|(k, t, f)| (k.replacen("model.", "model._orig_mod.", 1), t, f)).collect();
    renamed.push((
        "normalize_inputs.buffer_observation_state.mean".into(),
        HostTensor::new(vec![6], vec![0.0; 6]),
        true,
    ));
    let path = std::env::temp_dir().join(format!("fedvla-compiled-{}.safetensors", std::process::id()));
    write_mixed(&path, &renamed);
    let loaded = read_safetensors(&path).unwrap();
    std::fs::remove_file(&path).unwrap();
    check_keys(&cfg.param_specs(), &loaded, "compiled").unwrap();
}

#[test]
fn full_size_500_key_checkpoint_in_mixed_bf16_f32_loads() {
    // The real checkpoint's contract at full size (~0.9 GB on disk): frozen tensors in BF16, the
    // trainable ones in F32, every value converted on load.
    let specs = SmolVlaConfig::base().param_specs();
    let raw: Vec<(String, Dtype, Vec<u8>, Vec<usize>)> = specs
        .iter()
        .map(|s| {
            let (dtype, bytes) = if s.trainable {
                (Dtype::F32, 0.5f32.to_le_bytes().repeat(s.numel()))
            } else {
                (Dtype::BF16, half::bf16::from_f32(-0.25).to_le_bytes().repeat(s.numel()))
            };
            (s.name.clone(), dtype, bytes, s.shape.clone())
        })
        .collect();
    let views: Vec<(String, safetensors::tensor::TensorView<'_>)> = raw
        .iter()
        .map(|(k, d, b, s)| (k.clone(), safetensors::tensor::TensorView::new(*d, s.clone(), b).unwrap()))
        .collect();
    let path = std::env::temp_dir().join(format!("fedvla-full-{}.safetensors", std::process::id()));
    safetensors::serialize_to_file(views, None, &path).unwrap();
    drop(raw);
    let loaded = read_safetensors(&path);
    std::fs::remove_file(&path).unwrap();
    let loaded = loaded.unwrap();
    check_keys(&specs, &loaded, "full").unwrap();
    assert_eq!(loaded.len(), 500);
    for s in &specs {
        let t = &loaded[&s.name];
        let expected = if s.trainable { 0.5 } else { -0.25 };
        assert!(t.data.first() == Some(&expected) && t.data.last() == Some(&expected), "{}", s.name);
    }
}
