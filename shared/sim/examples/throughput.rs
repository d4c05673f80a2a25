//! Render frames/s per camera and simulation control steps/s, to compare with the data
//! generation budget: `cargo run --release -p fedvla-sim --example throughput -- [SIZE]`.
use fedvla_sim::{Camera, Expert, Scene, render};
use std::time::Instant;

fn main() {
    let size: usize = std::env::args().nth(1).and_then(|s| s.parse().ok()).unwrap_or(256);
    let mut scene = Scene::new(0);
    let mut expert = Expert::new(&scene);
    let started = Instant::now();
    let mut steps = 0;
    while !expert.done() {
        let action = expert.act(&scene);
        scene.step(action);
        steps += 1;
    }
    let seconds = started.elapsed().as_secs_f64();
    println!("sim + expert: {:.0} control steps/s ({steps} steps, 8 physics substeps each)", steps as f64 / seconds);

    // Render the settled scene and a mid-grasp one, so the wrist camera sees the bowl close up.
    let mut mid = Scene::new(0);
    let mut mid_expert = Expert::new(&mid);
    for _ in 0..110 {
        let action = mid_expert.act(&mid);
        mid.step(action);
    }
    for camera in Camera::ALL {
        let frames = 300;
        let started = Instant::now();
        let mut checksum = 0u64;
        for i in 0..frames {
            let scene = if i % 2 == 0 { &scene } else { &mid };
            checksum += render(scene, camera, size, size)[0] as u64;
        }
        let seconds = started.elapsed().as_secs_f64();
        println!(
            "render {}: {:.0} frames/s at {size}x{size} (checksum {checksum})",
            camera.name(),
            frames as f64 / seconds
        );
    }
}
