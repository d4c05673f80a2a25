//! The `gpu` feature's device trains as the CPU does: three AdamW steps of the tiny SmolVLA on burn's wgpu
//! backend (on a machine without a GPU, Mesa's software Vulkan, lavapipe) against the same steps on flex, from
//! the same weights, batch, noise and times. Built only with the feature:
//! `cargo test --release -p fedvla-workloads --features gpu --test gpu` (README, "Training on a GPU").
#![cfg(feature = "gpu")]

use fedvla_aggregator::config::ComputeDevice;
use fedvla_policy::weights::init_random;
use fedvla_policy::{Batch, SmolVlaConfig, Trainer};
use fedvla_workloads::device::training_device;

#[test]
fn steps_on_the_gpu_match_steps_on_the_cpu() {
    let cfg = SmolVlaConfig::preset("tiny").unwrap();
    let weights = init_random(&cfg.param_specs(), 1);
    let batch = Batch::random(&cfg, 4, 7);
    let steps = |kind: ComputeDevice| {
        let (device, backend) = training_device(kind).unwrap();
        let mut trainer = Trainer::new(&cfg, &weights, &device, 3).unwrap();
        let losses: Vec<f32> = (0..3).map(|_| trainer.train_step(&batch, 1e-3).unwrap().loss).collect();
        (backend, losses, trainer.trainable_weights())
    };
    let (cpu, cpu_losses, cpu_weights) = steps(ComputeDevice::Cpu);
    let (gpu, gpu_losses, gpu_weights) = steps(ComputeDevice::Wgpu);
    assert_eq!((cpu, gpu), ("cpu-flex", "wgpu"));
    println!("losses: cpu {cpu_losses:?}, wgpu {gpu_losses:?}");
    for (step, (c, g)) in cpu_losses.iter().zip(&gpu_losses).enumerate() {
        assert!((c - g).abs() <= 1e-3 * c.abs().max(1.0), "step {step}: loss {g} on wgpu, {c} on the CPU");
    }
    // After three steps every trained value agrees to float rounding (kernels sum in other orders).
    for (name, c) in cpu_weights.iter() {
        let g = &gpu_weights[name];
        let worst = c.data.iter().zip(&g.data).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
        assert!(worst <= 1e-3, "{name}: wgpu differs from the CPU by {worst}");
    }
}
