//! Saves one PNG per camera of a seeded scene after the expert has run FRAMES frames, to look
//! at by eye: `cargo run -p fedvla-sim --example snapshot -- SEED FRAMES OUT_DIR [SIZE [TASK]]`
//! (TASK by name, cube-in-bowl if left out).
use fedvla_sim::{Camera, Expert, Scene, TaskKind, render};

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let seed: u64 = args.get(1).and_then(|s| s.parse().ok()).unwrap_or(0);
    let frames: u32 = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(0);
    let out_dir = args.get(3).map_or(".", String::as_str);
    let size: usize = args.get(4).and_then(|s| s.parse().ok()).unwrap_or(256);
    let task = args.get(5).map_or(Ok(TaskKind::CubeInBowl), |name| name.parse()).expect("task");
    let mut scene = Scene::with_task(task, seed);
    let mut expert = Expert::new(&scene);
    for _ in 0..frames {
        let action = expert.act(&scene);
        scene.step(action);
    }
    println!("{}", scene.instruction());
    println!("state {:?} cube {:?} success {}", scene.state(), scene.cube_pose().translation, scene.success());
    for camera in Camera::ALL {
        let rgb = render(&scene, camera, size, size);
        let path = format!("{out_dir}/{task}_seed{seed}_f{frames}_{}.png", camera.name());
        image::save_buffer(&path, &rgb, size as u32, size as u32, image::ColorType::Rgb8).expect("write png");
        println!("{path}");
    }
}
