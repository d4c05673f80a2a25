//! Prints the task's cube's position and grip every few frames of one expert episode, to see
//! where an episode goes wrong: `cargo run -p fedvla-sim --example trace -- SEED [TASK [D]]` (TASK
//! by name, cube-in-bowl if left out; the arm perturbed by D degrees of recovery noise, none if
//! left out).
use fedvla_sim::{ActionNoise, ExpertEnd, TaskKind, drive_expert_on};

fn main() {
    let seed: u64 = std::env::args().nth(1).and_then(|s| s.parse().ok()).unwrap_or(0);
    let task = std::env::args().nth(2).map_or(Ok(TaskKind::CubeInBowl), |name| name.parse()).expect("task");
    let noise = ActionNoise::degrees(std::env::args().nth(3).and_then(|s| s.parse().ok()).unwrap_or(0.0));
    let scene = drive_expert_on(task, seed, ExpertEnd::PlanDone, 400, noise, |scene, action| {
        if scene.frame() == 0 {
            println!("{}: {:?}", scene.instruction(), scene.arrangement());
        }
        if scene.frame().is_multiple_of(5) {
            let cube = scene.cube_pose().translation;
            println!(
                "frame {:3} cube ({:.3}, {:.3}, {:.3}) gripped {} state {:.0?} action {:.0?}",
                scene.frame(),
                cube.x,
                cube.y,
                cube.z,
                scene.cube_gripped(),
                scene.state(),
                action
            );
        }
    });
    println!("success {} after {} frames", scene.success(), scene.frame());
}
