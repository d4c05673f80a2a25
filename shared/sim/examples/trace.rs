//! Prints the task's cube's position and grip every few frames of one expert episode, to see
//! where an episode goes wrong: `cargo run -p fedvla-sim --example trace -- SEED [TASK]` (TASK
//! by name, cube-in-bowl if left out).
use fedvla_sim::{Expert, Scene, TaskKind};

fn main() {
    let seed: u64 = std::env::args().nth(1).and_then(|s| s.parse().ok()).unwrap_or(0);
    let task = std::env::args().nth(2).map_or(Ok(TaskKind::CubeInBowl), |name| name.parse()).expect("task");
    let mut scene = Scene::with_task(task, seed);
    let mut expert = Expert::new(&scene);
    println!("{}: {:?}", scene.instruction(), scene.arrangement());
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
