//! Running the scripted expert through whole episodes, for tests, evaluation and data checks.

use crate::arm::JOINT_COUNT;
use crate::expert::Expert;
use crate::scene::Scene;
use rapier3d::math::Vec3;

/// What happened in one expert episode.
#[derive(Clone, Debug, PartialEq)]
pub struct EpisodeOutcome {
    /// Whether [`Scene::success`] held at the end.
    pub success: bool,
    /// Control frames run.
    pub frames: u32,
    /// `observation.state` of every frame, before its action (robot units).
    pub states: Vec<[f32; JOINT_COUNT]>,
    /// The action of every frame (robot units).
    pub actions: Vec<[f32; JOINT_COUNT]>,
    /// Where the cube ended, metres.
    pub final_cube_position: Vec3,
}

/// Runs the expert on the scene of `seed` until its plan is done or `max_frames` pass.
pub fn run_expert_episode(seed: u64, max_frames: u32) -> EpisodeOutcome {
    let mut scene = Scene::new(seed);
    let mut expert = Expert::new(&scene);
    let mut states = Vec::new();
    let mut actions = Vec::new();
    while !expert.done() && scene.frame() < max_frames {
        states.push(scene.state());
        let action = expert.act(&scene);
        actions.push(action);
        scene.step(action);
    }
    EpisodeOutcome {
        success: scene.success(),
        frames: scene.frame(),
        states,
        actions,
        final_cube_position: scene.cube_pose().translation,
    }
}
