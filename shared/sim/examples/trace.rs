//! Prints the cube's position and grip every few frames of one expert episode, to see where an
//! episode goes wrong: `cargo run -p fedvla-sim --example trace -- SEED`.
use fedvla_sim::{Expert, Scene};

fn main() {
    let seed: u64 = std::env::args().nth(1).and_then(|s| s.parse().ok()).unwrap_or(0);
    let mut scene = Scene::new(seed);
    let mut expert = Expert::new(&scene);
    println!("{:?}", scene.layout());
    while !expert.done() {
        let action = expert.act(&scene);
        scene.step(action);
        if scene.frame().is_multiple_of(5) {
            let cube = scene.cube_pose().translation;
            println!(
                "frame {:3} cube ({:.3}, {:.3}, {:.3}) gripped {} state {:.0?}",
                scene.frame(),
                cube.x,
                cube.y,
                cube.z,
                scene.cube_gripped(),
                scene.state()
            );
        }
    }
    println!("success {}", scene.success());
}
