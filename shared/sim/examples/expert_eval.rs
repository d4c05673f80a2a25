//! Success rate of the scripted expert over seeds 0..N, optionally executing its goals perturbed by
//! D degrees (the recovery demonstrations of `gen-data --action-noise`), on the task named TASK
//! (cube-in-bowl if left out): `cargo run --release -p fedvla-sim --example expert_eval -- N [D [TASK]]`.
use fedvla_sim::{ActionNoise, TaskKind, run_expert_episode_on};

fn main() {
    let episodes: u64 = std::env::args().nth(1).and_then(|s| s.parse().ok()).unwrap_or(100);
    let noise = ActionNoise::degrees(std::env::args().nth(2).and_then(|s| s.parse().ok()).unwrap_or(0.0));
    let task = std::env::args().nth(3).map_or(Ok(TaskKind::CubeInBowl), |name| name.parse()).expect("task");
    let mut successes = 0;
    let mut frames = 0;
    for seed in 0..episodes {
        let outcome = run_expert_episode_on(task, seed, 400, noise);
        successes += u32::from(outcome.success);
        frames += outcome.frames;
        if !outcome.success {
            println!("seed {seed}: failed, cube ended at {:?}", outcome.final_cube_position);
        }
    }
    println!(
        "{task} expert success {successes}/{episodes} ({:.1}%), mean episode {:.0} frames",
        100.0 * successes as f64 / episodes as f64,
        frames as f64 / episodes as f64
    );
}
