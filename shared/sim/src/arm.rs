//! The SO-100 arm's kinematic description (joint origins, axes, limits, link masses) read from
//! the published SO-ARM100 / MuJoCo Menagerie `trs_so_arm100` model, its forward kinematics and
//! statics (the gravity torque on each joint), the joint units used on the real robot, and
//! primitive link geometry standing in for meshes.
//!
//! Frames follow the published model: the base frame has z up and the arm works towards -y
//! (the side its elbow folds to).

use crate::shape::{Part, Rgb};
use rapier3d::math::{Pose, Rot3, Vec3};
use std::f32::consts::{FRAC_PI_2, PI};

/// Number of servos (5 arm joints + the gripper jaw).
pub const JOINT_COUNT: usize = 6;
/// Number of links: base, shoulder, upper arm, lower arm, wrist, gripper (fixed jaw), moving jaw.
pub const LINK_COUNT: usize = JOINT_COUNT + 1;
/// Joint names in LeRobot's order for SO-100 (`observation.state` / `action` names).
pub const JOINT_NAMES: [&str; JOINT_COUNT] =
    ["shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll", "gripper"];
/// Index of the gripper in state/action vectors.
pub const GRIPPER: usize = 5;
/// Index of the gripper (fixed jaw) link, which carries the wrist camera and the grasp point.
pub const GRIPPER_LINK: usize = 5;
/// Index of the moving jaw link.
pub const JAW_LINK: usize = 6;

/// One revolute joint: where the child link's frame sits in the parent's, and how it turns.
#[derive(Clone, Copy, Debug)]
pub struct JointSpec {
    pub name: &'static str,
    /// Child frame origin in the parent link frame, metres.
    pub origin: Vec3,
    /// Child frame orientation in the parent link frame at joint angle 0.
    pub orientation: Rot3,
    /// Rotation axis in the child frame (unit vector).
    pub axis: Vec3,
    /// Joint limits, radians.
    pub lower: f32,
    pub upper: f32,
}

/// One link's mass properties from the published model (rendering/collision use primitives).
#[derive(Clone, Copy, Debug)]
pub struct LinkSpec {
    pub name: &'static str,
    /// Mass, kg.
    pub mass: f32,
    /// Centre of mass in the link frame, metres.
    pub center_of_mass: Vec3,
}

fn rot_x(angle: f32) -> Rot3 {
    Rot3::from_rotation_x(angle)
}

/// Joint table of the SO-100 (Menagerie `trs_so_arm100`, angles in radians).
pub fn joints() -> [JointSpec; JOINT_COUNT] {
    [
        JointSpec {
            name: "shoulder_pan",
            origin: Vec3::new(0.0, -0.0452, 0.0165),
            orientation: rot_x(FRAC_PI_2),
            axis: Vec3::Y,
            lower: -2.2,
            upper: 2.2,
        },
        JointSpec {
            name: "shoulder_lift",
            origin: Vec3::new(0.0, 0.1025, 0.0306),
            orientation: rot_x(FRAC_PI_2),
            axis: Vec3::X,
            lower: -3.14158,
            upper: 0.2,
        },
        JointSpec {
            name: "elbow_flex",
            origin: Vec3::new(0.0, 0.11257, 0.028),
            orientation: rot_x(-FRAC_PI_2),
            axis: Vec3::X,
            lower: 0.0,
            upper: 3.14158,
        },
        JointSpec {
            name: "wrist_flex",
            origin: Vec3::new(0.0, 0.0052, 0.1349),
            orientation: rot_x(-FRAC_PI_2),
            axis: Vec3::X,
            lower: -2.0,
            upper: 1.8,
        },
        JointSpec {
            name: "wrist_roll",
            origin: Vec3::new(0.0, -0.0601, 0.0),
            orientation: Rot3::from_rotation_y(FRAC_PI_2),
            axis: Vec3::Y,
            lower: -3.14158,
            upper: 3.14158,
        },
        JointSpec {
            name: "gripper",
            origin: Vec3::new(-0.0202, -0.0244, 0.0),
            orientation: Rot3::from_rotation_y(PI),
            axis: Vec3::Z,
            lower: -0.2,
            upper: 2.0,
        },
    ]
}

/// Link masses and centres of mass from the published model.
pub const LINKS: [LinkSpec; LINK_COUNT] = [
    LinkSpec { name: "base", mass: 1.0, center_of_mass: Vec3::ZERO },
    LinkSpec { name: "shoulder", mass: 0.119226, center_of_mass: Vec3::new(-9.07886e-05, 0.0590972, 0.031089) },
    LinkSpec { name: "upper_arm", mass: 0.162409, center_of_mass: Vec3::new(-1.72052e-05, 0.0701802, 0.00310545) },
    LinkSpec { name: "lower_arm", mass: 0.147968, center_of_mass: Vec3::new(-0.00339604, 0.00137796, 0.0768007) },
    LinkSpec { name: "wrist", mass: 0.0661321, center_of_mass: Vec3::new(-0.00852653, -0.0352279, -2.34622e-05) },
    LinkSpec { name: "gripper", mass: 0.0929859, center_of_mass: Vec3::new(0.00552377, -0.0280167, 0.000483583) },
    LinkSpec { name: "jaw", mass: 0.0202444, center_of_mass: Vec3::new(-0.00161745, -0.0303473, 0.000449646) },
];

/// Inner face of the fixed jaw's finger, along the gripper frame's x axis, metres.
pub const FIXED_FINGER_FACE_X: f32 = 0.0079;
/// Thickness of the fixed jaw's finger along the gripper frame's x axis, metres: its outer face
/// is at `FIXED_FINGER_FACE_X + FIXED_FINGER_THICKNESS`.
pub const FIXED_FINGER_THICKNESS: f32 = 0.008;
/// Tip of the fixed jaw's finger along the gripper frame's y axis, metres.
pub const FINGER_TIP_Y: f32 = -0.106;
/// Height along the gripper frame's y axis where a cube is held (fingers span -0.055..-0.106).
pub const GRASP_DEPTH_Y: f32 = -0.085;

/// Point between the jaws, in the gripper (fixed jaw) frame, where a cube of half size
/// `half` sits when it rests against the fixed jaw: only one jaw moves, so a grasp is aimed
/// at the fixed finger and the moving jaw pushes the cube onto it.
pub fn grasp_point(half: f32) -> Vec3 {
    Vec3::new(FIXED_FINGER_FACE_X - half, GRASP_DEPTH_Y, 0.0)
}

/// World poses of all links for joint angles `q` (radians), the base standing at `base`.
pub fn forward_kinematics(base: Pose, q: &[f32; JOINT_COUNT]) -> [Pose; LINK_COUNT] {
    let mut poses = [base; LINK_COUNT];
    for (i, joint) in joints().iter().enumerate() {
        let local = Pose::from_parts(joint.origin, joint.orientation * Rot3::from_axis_angle(joint.axis, q[i]));
        poses[i + 1] = poses[i] * local;
    }
    poses
}

/// A point mass carried by one link, such as the held cube.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Payload {
    /// Index of the link that carries it.
    pub link: usize,
    /// Mass, kg.
    pub mass: f32,
    /// Centre of mass, world frame, metres.
    pub position: Vec3,
}

/// Torque each joint's servo must exert about its axis to hold everything outboard of that
/// joint (the links of [`LINKS`] and `payload`) still against `gravity` (m/s², world frame),
/// N·m, positive along the joint axis; `links` are the link poses from [`forward_kinematics`].
pub fn gravity_torques(links: &[Pose; LINK_COUNT], payload: Option<Payload>, gravity: Vec3) -> [f32; JOINT_COUNT] {
    let specs = joints();
    let weights: [(usize, f32, Vec3); LINK_COUNT] = std::array::from_fn(|link| {
        let spec = LINKS[link];
        (link, spec.mass, links[link].transform_point(spec.center_of_mass))
    });
    let carried = payload.map(|p| (p.link, p.mass, p.position));
    std::array::from_fn(|joint| {
        let pivot = links[joint + 1];
        let axis = pivot.rotation * specs[joint].axis;
        let moment: Vec3 = weights
            .iter()
            .chain(carried.iter())
            // Link `joint + 1` is the joint's child, so links after `joint` are outboard of it.
            .filter(|(link, _, _)| *link > joint)
            .map(|(_, mass, position)| (*position - pivot.translation).cross(gravity * *mass))
            .sum();
        // The servo cancels gravity's moment about its axis.
        -axis.dot(moment)
    })
}

/// Degrees for the five arm joints and 0..100 for the gripper, as LeRobot records SO-100
/// data. Gripper 0 is the jaw's closed limit, 100 its open limit.
pub fn to_robot_units(q: &[f32; JOINT_COUNT]) -> [f32; JOINT_COUNT] {
    let jaw = joints()[GRIPPER];
    let mut units = q.map(f32::to_degrees);
    units[GRIPPER] = (q[GRIPPER] - jaw.lower) / (jaw.upper - jaw.lower) * 100.0;
    units
}

/// Inverse of [`to_robot_units`]: radians from degrees / gripper 0..100.
pub fn from_robot_units(units: &[f32; JOINT_COUNT]) -> [f32; JOINT_COUNT] {
    let jaw = joints()[GRIPPER];
    let mut q = units.map(f32::to_radians);
    q[GRIPPER] = jaw.lower + units[GRIPPER] / 100.0 * (jaw.upper - jaw.lower);
    q
}

/// Clamps joint angles (radians) into the joint limits.
pub fn clamp_to_limits(q: &[f32; JOINT_COUNT]) -> [f32; JOINT_COUNT] {
    let specs = joints();
    std::array::from_fn(|i| q[i].clamp(specs[i].lower, specs[i].upper))
}

const ORANGE: Rgb = [0.95, 0.42, 0.08];
const DARK: Rgb = [0.12, 0.12, 0.13];

/// An STS3215 servo body (about 45 x 24 x 35 mm) centred at `center`.
fn servo(center: Vec3, half: Vec3) -> Part {
    Part::cuboid(center, half, DARK)
}

/// Primitive geometry of each link in its own frame: printed parts as orange bones from the
/// link's joint to the next joint, servos as dark boxes, fingers as thin plates.
pub fn link_parts() -> [Vec<Part>; LINK_COUNT] {
    let j = joints();
    [
        // Base: a plate under the pan servo.
        vec![
            Part::cuboid(Vec3::new(0.0, -0.0452, 0.006), Vec3::new(0.045, 0.045, 0.006), ORANGE),
            servo(Vec3::new(0.0, -0.0452, 0.012 + 0.0175), Vec3::new(0.0175, 0.0225, 0.0175)),
        ],
        // Shoulder: the pan bracket rising to the shoulder-lift servo (local y is up).
        vec![
            Part::segment(Vec3::new(0.0, 0.03, 0.0), j[1].origin, 0.02, 0.014, ORANGE),
            servo(j[1].origin - Vec3::new(0.0, 0.0, 0.004), Vec3::new(0.0225, 0.0175, 0.012)),
        ],
        // Upper arm, with the elbow servo at its far end.
        vec![
            Part::segment(Vec3::ZERO, j[2].origin, 0.016, 0.012, ORANGE),
            servo(j[2].origin, Vec3::new(0.0225, 0.012, 0.0175)),
        ],
        // Lower arm, with the wrist-flex servo at its far end.
        vec![
            Part::segment(Vec3::ZERO, j[3].origin, 0.015, 0.011, ORANGE),
            servo(j[3].origin - Vec3::new(0.0, 0.0, 0.01), Vec3::new(0.0225, 0.0175, 0.012)),
        ],
        // Wrist: the bracket holding the wrist-roll servo.
        vec![
            Part::segment(Vec3::ZERO, j[4].origin * 0.7, 0.015, 0.014, ORANGE),
            servo(j[4].origin * 0.75, Vec3::new(0.012, 0.0175, 0.0225)),
        ],
        // Gripper: the jaw servo and the fixed finger, inner face at FIXED_FINGER_FACE_X.
        vec![
            servo(Vec3::new(-0.002, -0.03, 0.0), Vec3::new(0.018, 0.016, 0.016)),
            Part::cuboid(Vec3::new(0.008, -0.05, 0.0), Vec3::new(0.008, 0.006, 0.009), ORANGE),
            Part::cuboid(
                Vec3::new(FIXED_FINGER_FACE_X + FIXED_FINGER_THICKNESS * 0.5, -0.0805, 0.0),
                Vec3::new(FIXED_FINGER_THICKNESS * 0.5, 0.0255, 0.009),
                ORANGE,
            ),
        ],
        // Moving jaw, in its own frame (x mirrored): a finger swinging about the jaw axis.
        vec![Part::segment(Vec3::new(-0.008, -0.012, 0.0), Vec3::new(-0.0138, -0.082, 0.0), 0.003, 0.009, ORANGE)],
    ]
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::GRAVITY;

    #[test]
    fn robot_units_round_trip() {
        let q = [0.3, -1.2, 1.4, 0.5, -0.7, 0.9];
        let back = from_robot_units(&to_robot_units(&q));
        for i in 0..JOINT_COUNT {
            assert!((back[i] - q[i]).abs() < 1e-5, "joint {i}: {} vs {}", back[i], q[i]);
        }
        assert_eq!(to_robot_units(&[0.0, 0.0, 0.0, 0.0, 0.0, -0.2])[GRIPPER], 0.0);
    }

    #[test]
    fn a_payload_loads_the_joints_inboard_of_its_link_by_its_weight_times_its_lever() {
        // Arm stretched out forward (-y); the pan axis is vertical and carries nothing.
        let links = forward_kinematics(Pose::IDENTITY, &[0.0; JOINT_COUNT]);
        let bare = gravity_torques(&links, None, GRAVITY);
        assert!(bare[0].abs() < 1e-6, "pan {}", bare[0]);
        let payload = Payload {
            link: GRIPPER_LINK,
            mass: 0.1,
            position: links[GRIPPER_LINK].transform_point(grasp_point(0.012)),
        };
        let loaded = gravity_torques(&links, Some(payload), GRAVITY);
        // Shoulder lift, elbow and wrist flex turn about horizontal axes across the arm: the
        // lever is the distance along y from the joint to the payload.
        for joint in 1..=3 {
            let lever = (links[joint + 1].translation.y - payload.position.y).abs();
            let added = (loaded[joint] - bare[joint]).abs();
            assert!(
                (added - 0.1 * -GRAVITY.z * lever).abs() < 1e-4,
                "joint {joint}: {added} N·m for a {lever} m lever"
            );
        }
        // The jaw does not carry what the fixed finger holds.
        assert_eq!(loaded[GRIPPER], bare[GRIPPER]);
    }

    #[test]
    fn home_pose_holds_the_gripper_ahead_pointing_down() {
        // The published "home" keyframe: upper arm up, forearm forward (-y), fingers down.
        let home = [0.0, -FRAC_PI_2, FRAC_PI_2, FRAC_PI_2, -FRAC_PI_2, 0.0];
        let poses = forward_kinematics(Pose::IDENTITY, &home);
        let shoulder = poses[2].translation;
        let gripper = poses[GRIPPER_LINK];
        assert!(shoulder.y - gripper.translation.y > 0.15, "shoulder {shoulder:?} gripper {gripper:?}");
        let fingers = gripper.transform_vector(-Vec3::Y);
        assert!(fingers.z < -0.99, "fingers point along {fingers:?}");
    }
}
