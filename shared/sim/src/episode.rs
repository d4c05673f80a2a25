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

/// When an expert episode ends.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ExpertEnd {
    /// When its plan is done (a recorded demonstration ends there).
    PlanDone,
    /// When the task succeeds, as a policy's episode ends (after its plan the expert holds its last pose, so it
    /// gets no extra help).
    Success,
}

/// The one expert episode loop: the expert on the scene of `seed`, frame by frame, until `end` or `max_frames`
/// frames. `on_frame` sees the scene before each action and the action; returns the scene as it ended.
pub fn drive_expert(
    seed: u64,
    end: ExpertEnd,
    max_frames: u32,
    mut on_frame: impl FnMut(&Scene, &[f32; JOINT_COUNT]),
) -> Scene {
    let mut scene = Scene::new(seed);
    let mut expert = Expert::new(&scene);
    while scene.frame() < max_frames {
        let over = match end {
            ExpertEnd::PlanDone => expert.done(),
            ExpertEnd::Success => scene.success(),
        };
        if over {
            break;
        }
        let action = expert.act(&scene);
        on_frame(&scene, &action);
        scene.step(action);
    }
    scene
}

/// Runs the expert on the scene of `seed` until its plan is done or `max_frames` pass.
pub fn run_expert_episode(seed: u64, max_frames: u32) -> EpisodeOutcome {
    let mut states = Vec::new();
    let mut actions = Vec::new();
    let scene = drive_expert(seed, ExpertEnd::PlanDone, max_frames, |scene, action| {
        states.push(scene.state());
        actions.push(*action);
    });
    EpisodeOutcome {
        success: scene.success(),
        frames: scene.frame(),
        states,
        actions,
        final_cube_position: scene.cube_pose().translation,
    }
}
