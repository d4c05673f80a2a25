//! SmolVLA training on the browser's WebGPU adapter, checked against the CPU backend, in a real headless Chromium
//! started with `--enable-unsafe-webgpu` (webdriver.json). On a machine without a GPU the adapter is SwiftShader:
//! slow (seconds per step), so the test trains two steps of the tiny model at batch 1, in a dedicated worker so
//! the page stays responsive to the test runner meanwhile.
#![cfg(target_arch = "wasm32")]

use burn::tensor::Device;
use fedvla_policy::weights::init_random;
use fedvla_policy::{Batch, SmolVlaConfig, Trainer};
use wasm_bindgen_test::*;

wasm_bindgen_test_configure!(run_in_dedicated_worker);

#[wasm_bindgen_test]
async fn tiny_smolvla_trains_on_webgpu_as_it_does_on_the_cpu() {
    let cfg = SmolVlaConfig::tiny();
    let weights = init_random(&cfg.param_specs(), 1);
    let batch = Batch::random(&cfg, 1, 11);
    let gpu = Device::wgpu_options()
        .init_async()
        .await
        .expect("a WebGPU adapter (Chromium runs with --enable-unsafe-webgpu)");
    let mut runs = Vec::new();
    for (name, device) in [("cpu (flex)", Device::flex()), ("webgpu", gpu)] {
        let mut trainer = Trainer::new(&cfg, &weights, &device.autodiff(), 5).unwrap();
        let mut losses = Vec::new();
        for step in 0..2 {
            let started = js_sys::Date::now();
            let report = trainer.train_step_async(&batch, 1e-3).await.unwrap();
            console_log!("{name}: step {step}: loss {:.6}, {:.0} ms", report.loss, js_sys::Date::now() - started);
            losses.push(report.loss);
        }
        runs.push((losses, trainer.trainable_weights_async().await.unwrap()));
    }
    let ((cpu_losses, cpu_weights), (gpu_losses, gpu_weights)) = (&runs[0], &runs[1]);
    for (c, g) in cpu_losses.iter().zip(gpu_losses) {
        assert!((c - g).abs() <= 1e-3 * c.abs().max(1.0), "losses differ: cpu {cpu_losses:?}, webgpu {gpu_losses:?}");
    }
    let worst = cpu_weights
        .iter()
        .flat_map(|(k, c)| c.data.iter().zip(&gpu_weights[k].data).map(|(a, b)| (a - b).abs()))
        .fold(0.0f32, f32::max);
    console_log!("webgpu vs cpu after 2 steps: worst trainable-weight difference {worst:e}");
    assert!(worst < 1e-3, "trainable weights after two steps differ by {worst}");
}
