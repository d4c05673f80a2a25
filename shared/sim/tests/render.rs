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

/// Pixels within `tolerance` of `color` on every channel.
fn pixels_near(rgb: &[u8], color: [u8; 3], tolerance: u8) -> usize {
    rgb.chunks_exact(3).filter(|p| p.iter().zip(color).all(|(a, b)| a.abs_diff(b) <= tolerance)).count()
}

/// Every task's objects stand in the top camera's view as the episode starts, each cube in its
/// own colour and the target marker on the table.
#[test]
fn the_top_camera_sees_every_task_s_objects() {
    use fedvla_sim::{CubeColour, Goal, TaskKind};
    for task in TaskKind::ALL {
        for seed in 0..5 {
            let scene = Scene::with_task(task, seed);
            let rgb = render(&scene, Camera::Top, SIZE, SIZE);
            // Lit from above: the top faces show each colour at about 90% brightness.
            let lit = |color: [f32; 3]| color.map(|channel| (channel * 0.915 * 255.0) as u8);
            for cube in &scene.arrangement().cubes {
                let seen = pixels_near(&rgb, lit(cube.colour.rgb()), 30);
                assert!(seen > 15, "{task} seed {seed}: {seen} pixels of the {} cube", cube.colour.name());
            }
            if let Goal::OnTarget { .. } = scene.arrangement().goal {
                let seen = pixels_near(&rgb, [230, 230, 230], 20);
                assert!(seen > 100, "{task} seed {seed}: {seen} pixels of the target");
            }
        }
        let colours: Vec<CubeColour> = Scene::with_task(task, 0).arrangement().cubes.iter().map(|c| c.colour).collect();
        assert!(colours.iter().enumerate().all(|(i, c)| !colours[..i].contains(c)), "{task}: {colours:?}");
    }
}
