//! Running the scripted expert through whole episodes of a task, for tests, evaluation and data
//! checks.

use crate::arm::JOINT_COUNT;
use crate::arrangement::Arrangement;
use crate::expert::Expert;
use crate::perturbation::{ActionNoise, Perturbation};
use crate::scene::Scene;
use crate::task::TaskKind;
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
    /// Where the task's cube ended, metres.
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

/// [`drive_expert_on`] the cube-in-bowl task.
pub fn drive_expert(
    seed: u64,
    end: ExpertEnd,
    max_frames: u32,
    noise: ActionNoise,
    on_frame: impl FnMut(&Scene, &[f32; JOINT_COUNT]),
) -> Scene {
    drive_expert_on(TaskKind::CubeInBowl, seed, end, max_frames, noise, on_frame)
}

/// The one expert episode loop: the expert on the scene of `task` and `seed`, frame by frame, until `end` or
/// `max_frames` frames, the arm executing its goals perturbed by `noise` (none: as they are). `on_frame` sees the
/// scene before each action and the expert's action (unperturbed: what a demonstration records); returns the
/// scene as it ended.
pub fn drive_expert_on(
    task: TaskKind,
    seed: u64,
    end: ExpertEnd,
    max_frames: u32,
    noise: ActionNoise,
    on_frame: impl FnMut(&Scene, &[f32; JOINT_COUNT]),
) -> Scene {
    drive_expert_in(Arrangement::from_seed(task, seed), seed, end, max_frames, noise, on_frame)
}

/// [`drive_expert_on`] from `arrangement` instead of the one `seed` draws (its goal changed, say:
/// [`Arrangement::with_subject`]); `seed` still seeds the perturbation.
pub fn drive_expert_in(
    arrangement: Arrangement,
    seed: u64,
    end: ExpertEnd,
    max_frames: u32,
    noise: ActionNoise,
    mut on_frame: impl FnMut(&Scene, &[f32; JOINT_COUNT]),
) -> Scene {
    let mut scene = Scene::from_arrangement(arrangement);
    let mut expert = Expert::new(&scene);
    let mut perturbation = Perturbation::new(noise, seed);
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
        scene.step(perturbation.apply(&action));
    }
    scene
}

/// [`run_expert_episode_on`] the cube-in-bowl task.
pub fn run_expert_episode(seed: u64, max_frames: u32, noise: ActionNoise) -> EpisodeOutcome {
    run_expert_episode_on(TaskKind::CubeInBowl, seed, max_frames, noise)
}

/// Runs the expert on the scene of `task` and `seed` until its plan is done or `max_frames` pass, executing its
/// goals perturbed by `noise`.
pub fn run_expert_episode_on(task: TaskKind, seed: u64, max_frames: u32, noise: ActionNoise) -> EpisodeOutcome {
    let mut states = Vec::new();
    let mut actions = Vec::new();
    let scene = drive_expert_on(task, seed, ExpertEnd::PlanDone, max_frames, noise, |scene, action| {
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
