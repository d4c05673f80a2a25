//! `bench_training`: SmolVLA train-step figures in the browser (www/bench.html shows them), on the CPU backend
//! in wasm or on the page's WebGPU adapter. Prints figures, asserts nothing: the browser counterpart of
//! `cargo bench -p fedvla-policy`.

use burn::tensor::Device;
use fedvla_policy::weights::init_random;
use fedvla_policy::{Batch, SmolVlaConfig, Trainer};
use serde_json::json;
use wasm_bindgen::prelude::*;

use crate::browser::{js_error, now_seconds, yield_to_page};
use crate::volunteer::webgpu_device;

/// Times `steps` training steps of the `model_size` preset at `batch_size` on random inputs; `webgpu` picks the
/// page's WebGPU adapter instead of the CPU. Resolves with a JSON object of the figures.
#[wasm_bindgen]
pub async fn bench_training(
    model_size: String,
    batch_size: usize,
    steps: u32,
    webgpu: bool,
) -> Result<String, JsValue> {
    let cfg = SmolVlaConfig::preset(&model_size).map_err(js_error)?;
    let device = if webgpu { webgpu_device().await.map_err(js_error)? } else { Device::flex() };
    let weights = init_random(&cfg.param_specs(), 0);
    let mut trainer = Trainer::new(&cfg, &weights, &device.autodiff(), 0).map_err(js_error)?;
    let batch = Batch::random(&cfg, batch_size, 0);
    let mut seconds = Vec::new();
    for _ in 0..steps.max(2) {
        let started = now_seconds();
        trainer.train_step_async(&batch, 1e-4).await.map_err(js_error)?;
        seconds.push(now_seconds() - started);
        yield_to_page().await;
    }
    let first = seconds[0];
    let mut rest = seconds[1..].to_vec();
    rest.sort_by(f64::total_cmp);
    let median = rest[rest.len() / 2];
    Ok(json!({
        "model": model_size,
        "backend": if webgpu { "webgpu" } else { "wasm-cpu (burn flex)" },
        "batch": batch_size,
        "steps": seconds.len(),
        "first_step_ms": first * 1000.0,
        "median_step_ms": median * 1000.0,
        "samples_per_s": batch_size as f64 / median,
    })
    .to_string())
}
