//! The wasm units in a real headless Chromium (`wasm-pack test --headless --chrome client-wasm`): the protocol
//! codec (and the model a volunteer rebuilds from the server's deltas, to the bits pinned natively), the SO-100 sim
//! and its renderer, and SmolVLA training steps on the CPU backend in wasm, FedProx's and SCAFFOLD's among them
//! (WebGPU: webgpu.rs).
#![cfg(target_arch = "wasm32")]

use burn::tensor::Device;
use fedvla_federation::codec::{UpdateValues, decode_payload, encode_delta_payload, encode_frames, encode_payload};
use fedvla_federation::{NamedTensors, Reassembler, UpdateEncoding, UpdateLimits};
use fedvla_policy::weights::init_random;
use fedvla_policy::{Batch, SmolVlaConfig, Trainer};
use fedvla_sim::{Camera, Expert, Scene, render};
use wasm_bindgen_test::*;

#[path = "../../shared/policy/tests/rules/mod.rs"]
mod rules;

#[path = "../../shared/federation/tests/deltas/mod.rs"]
mod deltas;

wasm_bindgen_test_configure!(run_in_browser);

#[wasm_bindgen_test]
fn an_update_survives_chunking_and_reassembly_in_wasm() {
    let mut update = NamedTensors::new();
    update.insert("model.action_out_proj.weight", vec![3, 4], (0..12).map(|i| i as f32 * 0.5 - 2.0).collect()).unwrap();
    update.insert("model.state_proj.bias", vec![4], vec![1.0, -1.0, f32::MIN_POSITIVE, 3.5]).unwrap();
    let spec = update.spec();
    let payload = encode_payload(&update);
    let frames: Vec<_> = encode_frames(&payload, 7, 64).collect();
    assert!(frames.len() > 1, "a 64-byte frame limit splits the update");
    let limits = UpdateLimits::for_spec(&spec, UpdateEncoding::F32, 64, 0);
    let mut reassembler = Reassembler::start(&frames[0], limits).unwrap();
    for frame in &frames[1..] {
        reassembler.push(frame).unwrap();
    }
    assert!(reassembler.is_complete());
    assert_eq!(reassembler.header().round, 7);
    let decoded = decode_payload(&reassembler.finish().unwrap(), &spec, UpdateEncoding::F32).unwrap();
    assert_eq!(decoded, UpdateValues::Model(update.clone()));

    // A compressed delta (half floats and int8 blocks decode the same in wasm).
    for encoding in [UpdateEncoding::Bf16, UpdateEncoding::Int8, UpdateEncoding::Topk { fraction: 0.5 }] {
        let payload = encode_delta_payload(&mut update.clone(), encoding);
        assert!(matches!(decode_payload(&payload, &spec, encoding), Ok(UpdateValues::Delta(_))), "{encoding:?}");
    }
}

#[wasm_bindgen_test]
fn model_deltas_rebuild_the_servers_model_in_wasm_to_the_native_bits() {
    assert_eq!(deltas::rebuilt_checksums(), deltas::PINNED);
}

#[wasm_bindgen_test]
fn the_sim_steps_the_expert_and_renders_both_cameras_in_wasm() {
    let mut scene = Scene::new(3);
    let start = scene.state();
    let mut expert = Expert::new(&scene);
    for _ in 0..60 {
        scene.step(expert.act(&scene));
    }
    assert_ne!(scene.state(), start, "the arm moved");
    for camera in Camera::ALL {
        let rgb = render(&scene, camera, 64, 64);
        assert_eq!(rgb.len(), 64 * 64 * 3);
        let mean = rgb.iter().map(|&v| f64::from(v)).sum::<f64>() / rgb.len() as f64;
        let variance = rgb.iter().map(|&v| (f64::from(v) - mean).powi(2)).sum::<f64>() / rgb.len() as f64;
        assert!(variance > 100.0, "{} camera frame is not blank (variance {variance})", camera.name());
    }
}

#[wasm_bindgen_test]
fn tiny_smolvla_trains_on_the_cpu_backend_in_wasm() {
    let cfg = SmolVlaConfig::tiny();
    let weights = init_random(&cfg.param_specs(), 1);
    let mut trainer = Trainer::new(&cfg, &weights, &Device::flex().autodiff(), 5).unwrap();
    let batch = Batch::random(&cfg, 2, 11);
    let (noise, time) = trainer.sample_noise_and_time(2);
    let mut losses = Vec::new();
    for _ in 0..5 {
        let (report, _) = trainer.train_step_with(&batch, noise.clone(), &time, 1e-3).unwrap();
        assert!(report.loss.is_finite() && report.grad_norm.is_finite(), "{report:?}");
        losses.push(report.loss);
    }
    assert!(losses[4] < losses[0], "the loss falls on a fixed batch: {losses:?}");
    let frozen_after = trainer.frozen_weights();
    for (name, tensor) in &frozen_after {
        assert_eq!(tensor, &weights[name], "frozen tensor {name} is untouched");
    }
}

/// The browser's trainer applies FedProx's proximal term and SCAFFOLD's correction by the very checks the native
/// tests run (shared/policy/tests/rules).
#[wasm_bindgen_test]
fn fedprox_and_scaffold_shape_the_steps_in_wasm_as_natively() {
    let device = Device::flex().autodiff();
    rules::proximal_term_adds_mu_times_the_distance_from_the_anchor(&device);
    rules::a_correction_shifts_the_step_by_lr_times_itself(&device);
}
