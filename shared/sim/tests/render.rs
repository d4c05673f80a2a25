//! Both cameras render a recognisable, lit 3D scene: saved as PNG under the cargo target tmp
//! dir for inspection, and checked for content (not blank, arm and cube visible).

use fedvla_sim::{Camera, Expert, Scene, render};

const SIZE: usize = 256;

/// Pixels that look like the arm's orange printed parts.
fn orange_pixels(rgb: &[u8]) -> usize {
    rgb.chunks_exact(3).filter(|p| p[0] > 120 && p[1] > 30 && p[1] < (p[0] as u16 * 3 / 4) as u8 && p[2] < 60).count()
}

/// Pixels that look like the red cube.
fn red_pixels(rgb: &[u8]) -> usize {
    rgb.chunks_exact(3).filter(|p| p[0] > 90 && p[1] < 40 && p[2] < 40).count()
}

fn variance(rgb: &[u8]) -> f64 {
    let n = rgb.len() as f64;
    let mean = rgb.iter().map(|&v| v as f64).sum::<f64>() / n;
    rgb.iter().map(|&v| (v as f64 - mean).powi(2)).sum::<f64>() / n
}

#[test]
fn cameras_render_arm_and_cube() {
    // Run the expert to the moment it holds the cube above the table: both cameras then see
    // the arm and the cube.
    let mut scene = Scene::new(3);
    let mut expert = Expert::new(&scene);
    for _ in 0..110 {
        let action = expert.act(&scene);
        scene.step(action);
    }
    assert!(scene.cube_gripped());
    for camera in Camera::ALL {
        let rgb = render(&scene, camera, SIZE, SIZE);
        assert_eq!(rgb.len(), SIZE * SIZE * 3);
        let path = std::path::Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!("{}.png", camera.name()));
        image::save_buffer(&path, &rgb, SIZE as u32, SIZE as u32, image::ColorType::Rgb8).expect("write png");
        let (variance, orange, red) = (variance(&rgb), orange_pixels(&rgb), red_pixels(&rgb));
        println!("{}: variance {variance:.0}, orange {orange}, red {red}, saved {}", camera.name(), path.display());
        assert!(variance > 100.0, "{} looks blank: variance {variance}", camera.name());
        assert!(orange > 200, "{}: only {orange} arm-coloured pixels", camera.name());
        assert!(red > 30, "{}: only {red} cube-coloured pixels", camera.name());
    }
}

#[test]
fn image_size_is_configurable() {
    let scene = Scene::new(0);
    let rgb = render(&scene, Camera::Top, 320, 240);
    assert_eq!(rgb.len(), 320 * 240 * 3);
    assert!(variance(&rgb) > 100.0);
}
