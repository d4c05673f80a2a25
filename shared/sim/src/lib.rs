//! SO-100 arm simulation for the browser federation: a rapier3d scene with the arm on a table;
//! four tabletop tasks, each with a language instruction, a seeded arrangement of cubes (and a
//! bowl or a target marker) and a success test ([`TaskKind`]: "put the cube in the bowl", the
//! first, and stacking, pushing onto a target, picking the named colour); a scripted expert
//! for each; and a software renderer for the top and wrist cameras. Runs natively and on wasm32
//! (no threads, no clocks).
//!
//! ```
//! use fedvla_sim::{Camera, Expert, Scene, TaskKind, render};
//! let mut scene = Scene::with_task(TaskKind::PickColour, 7); // Scene::new(7): the first task
//! let instruction = scene.instruction(); // e.g. "put the green cube in the bowl"
//! let mut expert = Expert::new(&scene);
//! let state = scene.state(); // observation.state: degrees, gripper 0..100
//! let action = expert.act(&scene); // action: goal positions, same units
//! scene.step(action); // 1/30 s
//! let top = render(&scene, Camera::Top, 256, 256); // RGB, HWC
//! assert_eq!(top.len(), 256 * 256 * 3);
//! # let _ = (state, instruction);
//! ```

pub mod arm;
pub mod arrangement;
pub mod camera;
pub mod episode;
pub mod expert;
pub mod goal;
pub mod ik;
pub mod mesh;
pub mod perturbation;
pub mod render;
pub mod scene;
pub mod servo;
pub mod shape;
mod splitmix;
pub mod task;

pub use arm::{JOINT_COUNT, JOINT_NAMES};
pub use arrangement::{Arrangement, CubeColour};
pub use camera::Camera;
pub use episode::{
    EpisodeOutcome, ExpertEnd, drive_expert, drive_expert_in, drive_expert_on, run_expert_episode,
    run_expert_episode_on,
};
pub use expert::Expert;
pub use goal::Goal;
pub use perturbation::ActionNoise;
pub use render::render;
pub use scene::{FPS, Scene};
pub use task::{TASK, TaskKind, UnknownTask};
