//! The "put the cube in the bowl" task: its language instruction, the seeded random placement
//! of cube and bowl on the table, and the dimensions the success test is judged against.

use crate::splitmix::SplitMix64;
use rapier3d::math::Vec3;

/// The language instruction recorded with every episode (LeRobot `task`).
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

/// Where the pan axis stands on the table (from the arm description), for placing objects at
/// reachable distances.
const PAN_AXIS: Vec3 = Vec3::new(0.0, -0.0452, 0.0);

/// Initial placement of the objects on the table (table top is z = 0).
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
        let cube_on_left = rng.next_f32() < 0.5;
        let side = if cube_on_left { 1.0 } else { -1.0 };
        let cube_azimuth = side * rng.range(0.2, 0.6);
        let cube_distance = rng.range(0.15, 0.23);
        let bowl_azimuth = -side * rng.range(0.35, 0.7);
        let bowl_distance = rng.range(0.16, 0.22);
        let cube_yaw = rng.range(-MAX_CUBE_YAW, MAX_CUBE_YAW);
        let on_table = |azimuth: f32, distance: f32, z: f32| {
            // Azimuth is measured from the arm's forward direction (-y).
            PAN_AXIS + Vec3::new(azimuth.sin() * distance, -azimuth.cos() * distance, z)
        };
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
}
