//! What each task asks for, judged on where the cubes are: the task's cube in the bowl with no
//! other cube there, resting on top of another cube, or resting on the target marker. What
//! every task asks besides (the gripper has let go, the arm touches no cube) the scene adds.

use crate::task::{
    CUBE_HALF, ON_TARGET_RADIUS, RESTING_TOLERANCE, STACK_MAX_OFFSET, SUCCESS_MAX_HEIGHT, SUCCESS_RADIUS,
};
use rapier3d::math::Vec3;

/// Where the task's cube has to end.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Goal {
    /// In the bowl whose base is centred here on the table, with no other cube in it.
    InBowl { bowl: Vec3 },
    /// Resting on top of cube `base` of the arrangement.
    OnCube { base: usize },
    /// Resting on the table on the target marker centred here.
    OnTarget { target: Vec3 },
}

impl Goal {
    /// Whether the goal is met with the cubes' centres at `cubes` (in the arrangement's order),
    /// `subject` being the index of the cube the task moves.
    pub fn met(&self, subject: usize, cubes: &[Vec3]) -> bool {
        let cube = cubes[subject];
        match *self {
            Goal::InBowl { bowl } => {
                in_bowl(cube, bowl)
                    && cubes.iter().enumerate().all(|(index, other)| index == subject || !in_bowl(*other, bowl))
            }
            Goal::OnCube { base } => {
                let below = cubes[base];
                (cube - below).truncate().length() < STACK_MAX_OFFSET
                    && (cube.z - below.z - 2.0 * CUBE_HALF).abs() < RESTING_TOLERANCE
            }
            Goal::OnTarget { target } => {
                (cube - target).truncate().length() < ON_TARGET_RADIUS && cube.z < CUBE_HALF + RESTING_TOLERANCE
            }
        }
    }
}

/// Whether a cube centred at `cube` rests in the bowl whose base is centred at `bowl`.
fn in_bowl(cube: Vec3, bowl: Vec3) -> bool {
    let offset = (cube - bowl).truncate().length();
    offset < SUCCESS_RADIUS && cube.z < SUCCESS_MAX_HEIGHT
}

#[cfg(test)]
mod tests {
    use super::*;

    const BOWL: Vec3 = Vec3::new(0.1, -0.2, 0.0);
    /// Where a cube rests on the bowl's floor.
    const IN_BOWL: Vec3 = Vec3::new(0.11, -0.2, 0.017);
    const ON_TABLE: Vec3 = Vec3::new(-0.1, -0.2, CUBE_HALF);

    #[test]
    fn the_bowl_takes_the_task_s_cube_and_no_other() {
        let goal = Goal::InBowl { bowl: BOWL };
        assert!(goal.met(0, &[IN_BOWL, ON_TABLE]));
        assert!(!goal.met(1, &[IN_BOWL, ON_TABLE]), "another cube in the bowl");
        assert!(!goal.met(0, &[IN_BOWL, IN_BOWL + Vec3::new(-0.02, 0.0, 0.0)]), "both cubes in the bowl");
        assert!(!goal.met(0, &[IN_BOWL + Vec3::new(0.0, 0.0, 0.05)]), "held above the bowl");
    }

    #[test]
    fn a_stacked_cube_rests_on_the_other_s_top() {
        let goal = Goal::OnCube { base: 1 };
        let stacked = ON_TABLE + Vec3::new(0.005, 0.0, 2.0 * CUBE_HALF);
        assert!(goal.met(0, &[stacked, ON_TABLE]));
        assert!(!goal.met(1, &[stacked, ON_TABLE]), "the lower cube is not the one to move");
        assert!(!goal.met(0, &[stacked + Vec3::new(0.0, 0.0, 0.02), ON_TABLE]), "held above");
        assert!(!goal.met(0, &[ON_TABLE + Vec3::new(2.0 * CUBE_HALF, 0.0, 0.0), ON_TABLE]), "beside it");
    }

    #[test]
    fn the_target_counts_a_cube_resting_over_its_middle() {
        let target = Vec3::new(-0.1, -0.2, 0.0);
        let goal = Goal::OnTarget { target };
        assert!(goal.met(0, &[ON_TABLE + Vec3::new(0.01, 0.01, 0.0)]));
        assert!(!goal.met(0, &[ON_TABLE + Vec3::new(ON_TARGET_RADIUS, 0.0, 0.0)]), "off the middle");
        assert!(!goal.met(0, &[ON_TABLE + Vec3::new(0.0, 0.0, 0.02)]), "lifted over it");
    }
}
