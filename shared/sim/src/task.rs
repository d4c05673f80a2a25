//! The tasks the arm is set and their stable names; the sizes of the objects on the table that
//! their success tests are judged against; and the seeded placement of cube and bowl of the
//! first task, "put the cube in the bowl" ([`Layout`]), which every dataset recorded before
//! there were other tasks was drawn from. Where the objects of every task stand, and the
//! instruction that names them, are [`crate::arrangement`]'s; what each task asks for is
//! [`crate::goal`]'s.

use crate::splitmix::SplitMix64;
use rapier3d::math::Vec3;
use std::fmt;
use std::str::FromStr;

/// The language instruction of the cube-in-bowl task, recorded with every episode of it
/// (LeRobot `task`).
pub const TASK: &str = "put the cube in the bowl";

/// Half edge of the cube, metres (a 2.4 cm cube).
pub const CUBE_HALF: f32 = 0.012;
/// Inner radius of the bowl, metres.
pub const BOWL_INNER_RADIUS: f32 = 0.05;
/// Height of the bowl wall above the table, metres.
pub const BOWL_HEIGHT: f32 = 0.035;
/// Thickness of the bowl floor, metres.
pub const BOWL_FLOOR: f32 = 0.005;
/// Largest horizontal distance from cube centre to bowl centre that counts as "in", metres.
pub const SUCCESS_RADIUS: f32 = 0.04;
/// Highest cube centre above the table that counts as resting in the bowl, metres.
pub const SUCCESS_MAX_HEIGHT: f32 = 0.03;
/// Largest cube yaw, radians, either way.
pub const MAX_CUBE_YAW: f32 = 0.3;
/// Radius of the target marker drawn on the table, metres.
pub const TARGET_RADIUS: f32 = 0.03;
/// Largest horizontal distance from cube centre to target centre that counts as "on the
/// target", metres: the cube then covers the marker's middle.
pub const ON_TARGET_RADIUS: f32 = 0.02;
/// Largest horizontal distance between the centres of two stacked cubes, metres: the upper
/// one's centre of mass stays over the lower one's top.
pub const STACK_MAX_OFFSET: f32 = CUBE_HALF;
/// How far a cube's centre may lie from where it would rest on the table (or on the cube
/// below it) and still count as resting there, metres.
pub const RESTING_TOLERANCE: f32 = 0.004;

/// A task the sim sets: what is on the table, what the instruction asks, what counts as done.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum TaskKind {
    /// Put the (red) cube in the bowl: the task of every dataset recorded before the others.
    CubeInBowl,
    /// Put the red cube on top of the green cube.
    Stack,
    /// Push the red cube across the table onto the target marker drawn on it.
    PushToTarget,
    /// Put the cube of the colour the instruction names in the bowl, among cubes of other
    /// colours: only a policy that reads the instruction knows which.
    PickColour,
}

impl TaskKind {
    /// Every task, the first one first.
    pub const ALL: [TaskKind; 4] =
        [TaskKind::CubeInBowl, TaskKind::Stack, TaskKind::PushToTarget, TaskKind::PickColour];

    /// The task's stable name (kebab-case), as configurations and command lines spell it.
    pub fn name(self) -> &'static str {
        match self {
            TaskKind::CubeInBowl => "cube-in-bowl",
            TaskKind::Stack => "stack",
            TaskKind::PushToTarget => "push-to-target",
            TaskKind::PickColour => "pick-colour",
        }
    }

    /// The task named `name` (see [`TaskKind::name`]).
    pub fn from_name(name: &str) -> Result<Self, UnknownTask> {
        Self::ALL.into_iter().find(|task| task.name() == name).ok_or_else(|| UnknownTask { name: name.to_string() })
    }
}

impl fmt::Display for TaskKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for TaskKind {
    type Err = UnknownTask;

    fn from_str(name: &str) -> Result<Self, UnknownTask> {
        Self::from_name(name)
    }
}

/// A task name that names no task.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct UnknownTask {
    pub name: String,
}

impl fmt::Display for UnknownTask {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let known: Vec<&str> = TaskKind::ALL.iter().map(|task| task.name()).collect();
        write!(f, "unknown task {:?}; the tasks are {}", self.name, known.join(", "))
    }
}

impl std::error::Error for UnknownTask {}

/// Where the pan axis stands on the table (from the arm description), for placing objects at
/// reachable distances.
const PAN_AXIS: Vec3 = Vec3::new(0.0, -0.0452, 0.0);

/// The point of the table `distance` metres from the pan axis at `azimuth` radians from the
/// arm's forward direction (-y), at height `z`.
pub(crate) fn on_table(azimuth: f32, distance: f32, z: f32) -> Vec3 {
    PAN_AXIS + Vec3::new(azimuth.sin() * distance, -azimuth.cos() * distance, z)
}

/// Initial placement of the cube-in-bowl task's objects on the table (table top is z = 0).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Layout {
    /// Cube centre, metres.
    pub cube_position: Vec3,
    /// Cube rotation about the vertical, radians.
    pub cube_yaw: f32,
    /// Centre of the bowl's base on the table, metres.
    pub bowl_position: Vec3,
}

impl Layout {
    /// A placement drawn from `seed`: cube and bowl in front of the arm on opposite sides,
    /// at distances the arm reaches with the gripper pointing down.
    pub fn from_seed(seed: u64) -> Self {
        let mut rng = SplitMix64(seed);
        let side = rng.side();
        let cube_azimuth = side * rng.range(0.2, 0.6);
        let cube_distance = rng.range(0.15, 0.23);
        let bowl_azimuth = -side * rng.range(0.35, 0.7);
        let bowl_distance = rng.range(0.16, 0.22);
        let cube_yaw = rng.range(-MAX_CUBE_YAW, MAX_CUBE_YAW);
        Self {
            cube_position: on_table(cube_azimuth, cube_distance, CUBE_HALF),
            cube_yaw,
            bowl_position: on_table(bowl_azimuth, bowl_distance, 0.0),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn layouts_keep_cube_and_bowl_apart_and_yaw_bounded() {
        for seed in 0..200 {
            let layout = Layout::from_seed(seed);
            let apart = (layout.cube_position - layout.bowl_position).truncate().length();
            assert!(apart > BOWL_INNER_RADIUS + 0.035, "seed {seed}: {apart}");
            assert!(layout.cube_yaw.abs() <= MAX_CUBE_YAW);
        }
        assert_eq!(Layout::from_seed(7), Layout::from_seed(7));
        assert_ne!(Layout::from_seed(7), Layout::from_seed(8));
    }

    #[test]
    fn names_round_trip_and_an_unknown_name_lists_the_known_ones() {
        for task in TaskKind::ALL {
            assert_eq!(TaskKind::from_name(task.name()), Ok(task));
            assert_eq!(task.to_string().parse::<TaskKind>(), Ok(task));
        }
        let error = TaskKind::from_name("juggle").unwrap_err().to_string();
        assert!(error.contains("\"juggle\""), "{error}");
        for task in TaskKind::ALL {
            assert!(error.contains(task.name()), "{error}");
        }
    }
}
