//! How FedProx's proximal term and SCAFFOLD's correction shape a training step of the tiny SmolVLA, as checks on
//! a device: `training.rs` runs them natively and `client-wasm/tests/web.rs` (which includes this file) in
//! Chromium, so the browser's trainer is held to the very rules the native one is.

use burn::tensor::Device;
use fedvla_policy::weights::init_random;
use fedvla_policy::{Batch, SmolVlaConfig, Trainer, WeightMap};

/// Seeded random values for the trainable tensors only.
fn trainable_values(cfg: &SmolVlaConfig, seed: u64) -> WeightMap {
    let names: std::collections::BTreeSet<String> =
        cfg.param_specs().into_iter().filter(|s| s.trainable).map(|s| s.name).collect();
    init_random(&cfg.param_specs(), seed).into_iter().filter(|(k, _)| names.contains(k)).collect()
}

/// FedProx: with the proximal term the gradient of every trainable tensor gains exactly `mu * (w - w0)`, `w0`
/// the weights when it was set; without it (mu = 0) nothing changes.
pub fn proximal_term_adds_mu_times_the_distance_from_the_anchor(device: &Device) {
    let cfg = SmolVlaConfig::tiny();
    let anchor = init_random(&cfg.param_specs(), 1);
    let trainable = trainable_values(&cfg, 2);
    let batch = Batch::random(&cfg, 2, 3);
    let gradients = |mu: f64| {
        let mut trainer = Trainer::new(&cfg, &anchor, device, 5).unwrap();
        trainer.set_proximal(mu);
        trainer.set_trainable_weights(trainable.clone()).unwrap();
        let (noise, time) = trainer.sample_noise_and_time(2);
        trainer.train_step_with(&batch, noise, &time, 1e-3).unwrap().1
    };
    let (plain, off, mu) = (gradients(0.0), gradients(0.0), 0.25);
    let proximal = gradients(mu);
    assert_eq!(plain, off);
    for (name, g) in &plain {
        let (w, w0) = (&trainable[name].data, &anchor[name].data);
        for (i, (with, without)) in proximal[name].data.iter().zip(&g.data).enumerate() {
            let expected = without + (mu as f32) * (w[i] - w0[i]);
            assert!((with - expected).abs() <= 1e-5 * (1.0 + expected.abs()), "{name}[{i}]: {with} != {expected}");
        }
    }
}

/// SCAFFOLD's correction: with it, a step moves every trainable tensor by exactly `lr * correction` more than
/// AdamW's step from the same state on the same batch; a correction that misses a trainable tensor is refused.
pub fn a_correction_shifts_the_step_by_lr_times_itself(device: &Device) {
    let cfg = SmolVlaConfig::tiny();
    let weights = init_random(&cfg.param_specs(), 1);
    let batch = Batch::random(&cfg, 2, 3);
    let step = |correction: Option<&WeightMap>| {
        let mut trainer = Trainer::new(&cfg, &weights, device, 5).unwrap();
        trainer.set_correction(correction).unwrap();
        let (noise, time) = trainer.sample_noise_and_time(2);
        trainer.train_step_with(&batch, noise, &time, 1e-3).unwrap();
        trainer.trainable_weights()
    };
    let plain = step(None);
    let correction = trainable_values(&cfg, 9);
    let corrected = step(Some(&correction));
    for (name, p) in &plain {
        let (with, c) = (&corrected[name].data, &correction[name].data);
        for (i, &without) in p.data.iter().enumerate() {
            let expected = without - 1e-3 * c[i];
            assert!(
                (with[i] - expected).abs() <= 1e-6 * (1.0 + expected.abs()),
                "{name}[{i}]: {} != {expected}",
                with[i]
            );
        }
    }
    let mut partial = correction.clone();
    partial.pop_first();
    let mut trainer = Trainer::new(&cfg, &weights, device, 5).unwrap();
    assert!(trainer.set_correction(Some(&partial)).is_err());
}
