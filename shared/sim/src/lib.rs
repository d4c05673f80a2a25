//! SO-100 arm simulation for the browser federation: a rapier3d scene with the arm, a table,
//! a cube and a bowl; the "put the cube in the bowl" task; a scripted expert; and a software
//! renderer for the top and wrist cameras. Runs natively and on wasm32 (no threads, no clocks).

pub mod arm;
pub mod shape;
pub mod scene;
pub mod servo;
pub mod task;

pub use scene::Scene;
pub use task::TASK;
pub mod camera;
pub mod mesh;
pub mod render;

pub use camera::Camera;
pub use render::render;
pub mod episode;
pub mod expert;
pub mod ik;

pub use episode::{EpisodeOutcome, run_expert_episode};
pub use expert::Expert;
