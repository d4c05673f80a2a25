//! Saves one PNG per camera of a seeded scene after the expert has run FRAMES frames, to look
//! at by eye: `cargo run -p fedvla-sim --example snapshot -- SEED FRAMES OUT_DIR [SIZE]`.
use fedvla_sim::{Camera, Expert, Scene, render};

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let seed: u64 = args.get(1).and_then(|s| s.parse().ok()).unwrap_or(0);
    let frames: u32 = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(0);
    let out_dir = args.get(3).map(String::as_str).unwrap_or(".");
    let size: usize = args.get(4).and_then(|s| s.parse().ok()).unwrap_or(256);
    let mut scene = Scene::new(seed);
    let mut expert = Expert::new(&scene);
    for _ in 0..frames {
        let action = expert.act(&scene);
        scene.step(action);
    }
    println!("state {:?} cube {:?} success {}", scene.state(), scene.cube_pose().translation, scene.success());
    for camera in Camera::ALL {
        let rgb = render(&scene, camera, size, size);
        let path = format!("{out_dir}/seed{seed}_f{frames}_{}.png", camera.name());
        image::save_buffer(&path, &rgb, size as u32, size as u32, image::ColorType::Rgb8).expect("write png");
        println!("{path}");
    }
}
