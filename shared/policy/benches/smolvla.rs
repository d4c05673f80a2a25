//! `cargo bench -p fedvla-policy`: SmolVLA train-step throughput (samples/s) and sampling latency
//! for the tiny and small presets on burn's flex CPU backend. Prints figures; asserts nothing.

use std::time::Instant;

use burn::tensor::Device;
use fedvla_policy::batch::Prepared;
use fedvla_policy::smolvla::gaussian_noise;
use fedvla_policy::weights::{ParamStore, init_random};
use fedvla_policy::{Batch, SmolVla, SmolVlaConfig, Trainer};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

fn median(mut xs: Vec<f64>) -> f64 {
    xs.sort_by(f64::total_cmp);
    xs[xs.len() / 2]
}

fn main() {
    let mut rng = StdRng::seed_from_u64(0);
    println!("backend: flex (CPU), threads: {}", std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1));
    for name in ["tiny", "small"] {
        let cfg = SmolVlaConfig::preset(name).unwrap();
        let weights = init_random(&cfg.param_specs(), 0);
        let params: usize = cfg.param_specs().iter().map(|s| s.numel()).sum();
        for b in [8, 32] {
            let mut trainer = Trainer::new(&cfg, &weights, &Device::flex().autodiff(), 0).unwrap();
            let data = Batch::random(&cfg, b, rng.random());
            trainer.train_step(&data, 1e-4).unwrap();
            let times: Vec<f64> = (0..5)
                .map(|_| {
                    let start = Instant::now();
                    trainer.train_step(&data, 1e-4).unwrap();
                    start.elapsed().as_secs_f64()
                })
                .collect();
            let step = median(times);
            println!(
                "{name:<6} ({params} params) train step  batch {b:>3}: {:>8.1} ms  {:>8.1} samples/s",
                step * 1e3,
                b as f64 / step
            );
        }
        let device = Device::flex();
        let store = ParamStore::upload(weights.iter(), &device, false);
        let model = SmolVla::new(&cfg, &store);
        let data = Batch::random(&cfg, 1, rng.random());
        let obs = Prepared::new(&cfg, &data, &device).unwrap();
        let times: Vec<f64> = (0..5)
            .map(|_| {
                let noise = gaussian_noise(&mut rng, [1, cfg.chunk_size, cfg.max_action_dim], &device);
                let start = Instant::now();
                let _ = model.sample_actions(&obs, noise, None).into_data();
                start.elapsed().as_secs_f64()
            })
            .collect();
        println!("{name:<6} sample_actions batch 1, {} Euler steps: {:>8.1} ms", cfg.num_steps, median(times) * 1e3);
    }
}
