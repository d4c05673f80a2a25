//! Perturbed execution for recording recoveries (DART, Laskey et al. 2017): while the expert
//! demonstrates, the arm executes its goals plus a slowly wandering, seeded offset, and the
//! dataset records the expert's own goals. A policy trained on such demonstrations has seen
//! the arm off the expert's path (the cube off-centre in the wrist camera) together with the
//! goals that bring it back, which unperturbed demonstrations never show it.

use crate::arm::{GRIPPER, JOINT_COUNT};
use crate::splitmix::SplitMix64;

/// How the executed goals are perturbed: an Ornstein-Uhlenbeck offset on every arm joint (not the
/// gripper), stationary standard deviation `std_degrees`, correlated over about `correlation_frames`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ActionNoise {
    pub std_degrees: f32,
    pub correlation_frames: f32,
}

impl ActionNoise {
    /// No perturbation: the expert's goals are executed as they are.
    pub const NONE: Self = Self { std_degrees: 0.0, correlation_frames: 15.0 };

    /// `std_degrees` of offset, correlated over half a second (15 frames): slow enough to carry the
    /// gripper off the cube, as a policy's error does, rather than jitter in place.
    pub fn degrees(std_degrees: f32) -> Self {
        Self { std_degrees, ..Self::NONE }
    }

    pub fn is_none(&self) -> bool {
        self.std_degrees <= 0.0
    }
}

/// The offset process of one episode.
pub struct Perturbation {
    noise: ActionNoise,
    rng: SplitMix64,
    offset: [f32; JOINT_COUNT],
}

impl Perturbation {
    /// The process for the episode of `seed` (its own stream, apart from the layout's).
    pub fn new(noise: ActionNoise, seed: u64) -> Self {
        Self { noise, rng: SplitMix64(seed ^ 0xD1B5_4A32_D192_ED03), offset: [0.0; JOINT_COUNT] }
    }

    /// The goals the arm executes this frame for the expert's `action`: one step of the offset
    /// process added to every arm joint.
    pub fn apply(&mut self, action: &[f32; JOINT_COUNT]) -> [f32; JOINT_COUNT] {
        if self.noise.is_none() {
            return *action;
        }
        // Discrete OU: x <- a x + sqrt(1 - a^2) sigma n keeps the stationary deviation at sigma.
        let decay = (-1.0 / self.noise.correlation_frames.max(1.0)).exp();
        let kick = (1.0 - decay * decay).sqrt() * self.noise.std_degrees;
        let mut executed = *action;
        for (joint, (offset, executed)) in self.offset.iter_mut().zip(executed.iter_mut()).enumerate() {
            if joint == GRIPPER {
                continue;
            }
            *offset = decay * *offset + kick * self.rng.gaussian();
            *executed += *offset;
        }
        executed
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn offsets_have_the_asked_deviation_leave_the_gripper_and_repeat_by_seed() {
        let action = [10.0, 20.0, 30.0, 40.0, 50.0, 60.0];
        let mut perturbation = Perturbation::new(ActionNoise::degrees(2.0), 3);
        let frames = 20_000;
        let mut sum_sq = 0.0f64;
        for _ in 0..frames {
            let executed = perturbation.apply(&action);
            assert_eq!(executed[GRIPPER], action[GRIPPER]);
            sum_sq += f64::from((executed[0] - action[0]).powi(2));
        }
        let std = (sum_sq / frames as f64).sqrt();
        assert!((1.6..2.4).contains(&std), "stationary deviation {std}");
        let first = |seed| Perturbation::new(ActionNoise::degrees(2.0), seed).apply(&action);
        assert_eq!(first(3), first(3));
        assert_ne!(first(3), first(4));
        assert_eq!(Perturbation::new(ActionNoise::NONE, 3).apply(&action), action);
    }
}
