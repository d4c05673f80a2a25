//! SO-100 arm simulation for the browser federation: a rapier3d scene with the arm, a table,
//! a cube and a bowl; the "put the cube in the bowl" task; a scripted expert; and a software
//! renderer for the top and wrist cameras. Runs natively and on wasm32 (no threads, no clocks).
//!
//! ```
//! use fedvla_sim::{Camera, Expert, Scene, render};
//! let mut scene = Scene::new(7);
//! let mut expert = Expert::new(&scene);
//! let state = scene.state(); // observation.state: degrees, gripper 0..100
//! let action = expert.act(&scene); // action: goal positions, same units
//! scene.step(action); // 1/30 s
//! let top = render(&scene, Camera::Top, 256, 256); // RGB, HWC
//! assert_eq!(top.len(), 256 * 256 * 3);
//! # let _ = state;
//! ```

pub mod arm;
pub mod camera;
pub mod episode;
pub mod expert;
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
pub use camera::Camera;
pub use episode::{EpisodeOutcome, ExpertEnd, drive_expert, run_expert_episode};
pub use expert::Expert;
pub use perturbation::ActionNoise;
pub use render::render;
pub use scene::{FPS, Scene};
pub use task::TASK;
