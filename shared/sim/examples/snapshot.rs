//! Saves one PNG per camera of a seeded scene, to look at it by eye:
//! `cargo run -p fedvla-sim --example snapshot -- SEED OUT_DIR [SIZE]`.
use fedvla_sim::{Camera, Scene, render};

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let seed: u64 = args.get(1).and_then(|s| s.parse().ok()).unwrap_or(0);
    let out_dir = args.get(2).map(String::as_str).unwrap_or(".");
    let size: usize = args.get(3).and_then(|s| s.parse().ok()).unwrap_or(256);
    let scene = Scene::new(seed);
    for camera in Camera::ALL {
        let rgb = render(&scene, camera, size, size);
        let path = format!("{out_dir}/seed{seed}_{}.png", camera.name());
        image::save_buffer(&path, &rgb, size as u32, size as u32, image::ColorType::Rgb8).expect("write png");
        println!("{path}");
    }
}
