//! The scripted expert solves the task, within the joint limits, deterministically.

use fedvla_sim::arm::{self, JOINT_COUNT};
use fedvla_sim::{ActionNoise, run_expert_episode};

const MAX_FRAMES: u32 = 400;

#[test]
fn expert_puts_the_cube_in_the_bowl_in_at_least_18_of_20_seeds() {
    let outcomes: Vec<_> = (0..20).map(|seed| run_expert_episode(seed, MAX_FRAMES, ActionNoise::NONE)).collect();
    let successes = outcomes.iter().filter(|o| o.success).count();
    let failed: Vec<_> = outcomes.iter().enumerate().filter(|(_, o)| !o.success).map(|(seed, _)| seed).collect();
    assert!(successes >= 18, "{successes}/20 succeeded; failed seeds {failed:?}");
    for (seed, outcome) in outcomes.iter().enumerate() {
        assert!((150..=250).contains(&outcome.frames), "seed {seed}: {} frames", outcome.frames);
    }
}

#[test]
fn states_and_actions_stay_within_joint_limits() {
    let joints = arm::joints();
    for seed in [0, 1, 2] {
        let outcome = run_expert_episode(seed, MAX_FRAMES, ActionNoise::NONE);
        for (frame, (state, action)) in outcome.states.iter().zip(&outcome.actions).enumerate() {
            let (state, action) = (arm::from_robot_units(state), arm::from_robot_units(action));
            for i in 0..JOINT_COUNT {
                let (lower, upper) = (joints[i].lower - 1e-4, joints[i].upper + 1e-4);
                assert!((lower..=upper).contains(&state[i]), "seed {seed} frame {frame} joint {i}: {}", state[i]);
                assert!((lower..=upper).contains(&action[i]), "seed {seed} frame {frame} joint {i}: {}", action[i]);
            }
            let units = fedvla_sim::arm::to_robot_units(&state);
            assert!((0.0..=100.0).contains(&units[arm::GRIPPER]), "gripper {}", units[arm::GRIPPER]);
        }
    }
}

#[test]
fn same_seed_gives_identical_trajectory() {
    let first = run_expert_episode(5, MAX_FRAMES, ActionNoise::NONE);
    let second = run_expert_episode(5, MAX_FRAMES, ActionNoise::NONE);
    assert_eq!(first, second);
    let other = run_expert_episode(6, MAX_FRAMES, ActionNoise::NONE);
    assert_ne!(first.states, other.states);
}

/// Perturbed execution (recovery demonstrations) takes the arm off the clean path, the recorded goals still
/// solve the task from there, and the same seed perturbs the same way.
#[test]
fn expert_recovers_from_perturbed_execution() {
    let noise = ActionNoise::degrees(2.0);
    let outcomes: Vec<_> = (0..10).map(|seed| run_expert_episode(seed, MAX_FRAMES, noise)).collect();
    let successes = outcomes.iter().filter(|o| o.success).count();
    assert!(successes >= 8, "{successes}/10 perturbed demonstrations succeeded");
    let clean = run_expert_episode(0, MAX_FRAMES, ActionNoise::NONE);
    assert_ne!(outcomes[0].states, clean.states, "the perturbation moved the arm");
    assert_eq!(outcomes[0], run_expert_episode(0, MAX_FRAMES, noise));
}

/// Data generation runs one scene per worker thread natively.
#[test]
fn scene_and_expert_can_move_to_another_thread() {
    fn assert_send<T: Send>() {}
    assert_send::<fedvla_sim::Scene>();
    assert_send::<fedvla_sim::Expert>();
}
