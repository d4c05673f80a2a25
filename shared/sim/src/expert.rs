//! The scripted expert that demonstrates the task: a fixed sequence of gripper waypoints
//! (above the cube, descend, close, lift, over the bowl, lower, open, retreat) followed by
//! damped-least-squares inverse kinematics, one goal per control frame.

use crate::arm::{self, GRIPPER, GRIPPER_LINK, JOINT_COUNT};
use crate::ik::{self, GripperTarget};
use crate::scene::Scene;
use crate::task::CUBE_HALF;
use rapier3d::math::{Mat3, Pose, Rot3, Vec3};
use std::f32::consts::{FRAC_PI_2, PI, TAU};

/// Gap left between the fixed finger and the cube on the way down, metres: the closing jaw
/// then pushes the cube onto the fixed finger.
const FINGER_CLEARANCE: f32 = 0.003;
/// How far above the cube centre the grasp point is held, metres: grasping the cube's upper
/// part keeps the finger tips off the table.
const GRASP_ABOVE_CENTER: f32 = 0.006;
/// Height of the grasp point when moving above objects, metres.
const HOVER_HEIGHT: f32 = 0.09;
/// Height of the grasp point when the cube is let go over the bowl, metres.
const RELEASE_HEIGHT: f32 = 0.045;
/// Height of the grasp point at the end, metres.
const RETREAT_HEIGHT: f32 = 0.13;
/// Gripper goals, robot units (0 closed .. 100 open). Closing towards 0 makes the jaw stall
/// on the cube.
const GRIPPER_OPEN: f32 = 40.0;
const GRIPPER_CLOSED: f32 = 0.0;

/// One point of the plan: where the grasp point goes, how the jaw is turned, what the gripper
/// is told, and in how many frames it gets there from the previous point.
#[derive(Clone, Copy, Debug)]
struct Waypoint {
    position: Vec3,
    /// Direction (about the vertical, radians) in which the jaw closes.
    closing_yaw: f32,
    gripper: f32,
    frames: u32,
}

/// Index of the waypoint that ends the lift: if the cube is not held by then, the grasp
/// missed and the expert plans again from where things are.
const LIFTED: usize = 4;
/// How many times a missed grasp is tried again.
const MAX_RETRIES: u32 = 2;

/// Scripted expert for one episode; plans from the scene it is created with.
#[derive(Clone, Debug)]
pub struct Expert {
    base: Pose,
    grasp_point: Vec3,
    waypoints: Vec<Waypoint>,
    frame: u32,
    joints: [f32; JOINT_COUNT],
    retries: u32,
}

impl Expert {
    /// Plans the demonstration from the current arm pose and the cube and bowl positions.
    pub fn new(scene: &Scene) -> Self {
        let joints = scene.joint_positions();
        let grasp_point = arm::grasp_point(CUBE_HALF + FINGER_CLEARANCE);
        Self {
            base: scene.base_pose(),
            grasp_point,
            waypoints: plan(scene, &joints, grasp_point),
            frame: 0,
            joints,
            retries: 0,
        }
    }

    /// Frames the whole demonstration takes (as planned now; a retry adds a new plan).
    pub fn planned_frames(&self) -> u32 {
        self.waypoints.iter().map(|w| w.frames).sum()
    }

    /// Whether the plan has been played to its end.
    pub fn done(&self) -> bool {
        self.frame >= self.planned_frames()
    }

    /// The next action, in robot units (degrees, gripper 0..100): goal positions for this
    /// control frame. Watches `scene` for a missed grasp; after the end of the plan it keeps
    /// holding the final pose.
    pub fn act(&mut self, scene: &Scene) -> [f32; JOINT_COUNT] {
        let lifted_at: u32 = self.waypoints[..=LIFTED].iter().map(|w| w.frames).sum();
        if self.frame == lifted_at && !scene.cube_gripped() && self.retries < MAX_RETRIES {
            self.retries += 1;
            self.waypoints = plan(scene, &self.joints, self.grasp_point);
            self.frame = 0;
        }
        self.frame = (self.frame + 1).min(self.planned_frames());
        let waypoint = self.waypoint_at(self.frame);
        let target = GripperTarget {
            point: self.grasp_point,
            position: waypoint.position,
            orientation: pointing_down(waypoint.closing_yaw),
        };
        self.joints = ik::solve(self.base, &self.joints, &target);
        let mut action = arm::to_robot_units(&self.joints);
        action[GRIPPER] = waypoint.gripper;
        action
    }

    /// The plan interpolated at `frame`: smooth in position and yaw, linear in gripper.
    fn waypoint_at(&self, frame: u32) -> Waypoint {
        let mut elapsed = 0;
        for pair in self.waypoints.windows(2) {
            let (from, to) = (pair[0], pair[1]);
            if frame <= elapsed + to.frames {
                let t = (frame - elapsed) as f32 / to.frames as f32;
                let smooth = t * t * (3.0 - 2.0 * t);
                return Waypoint {
                    position: from.position.lerp(to.position, smooth),
                    closing_yaw: from.closing_yaw + wrap(to.closing_yaw - from.closing_yaw) * smooth,
                    gripper: from.gripper + (to.gripper - from.gripper) * t,
                    frames: 0,
                };
            }
            elapsed += to.frames;
        }
        self.waypoints[self.waypoints.len() - 1]
    }
}

/// Waypoints from the arm at `joints` (radians) to the cube in the bowl, for the grasp point
/// `grasp_point` (gripper frame).
fn plan(scene: &Scene, joints: &[f32; JOINT_COUNT], grasp_point: Vec3) -> Vec<Waypoint> {
    let links = arm::forward_kinematics(scene.base_pose(), joints);
    let gripper = links[GRIPPER_LINK];
    let pan_axis = links[1].translation;
    let start_yaw = yaw_of(gripper.rotation * Vec3::X);

    let cube = scene.cube_pose();
    let cube_yaw = yaw_of(cube.rotation * Vec3::X);
    let bowl = scene.layout().bowl_position;
    // The jaw's closing direction when the arm turns to face a point without rolling the
    // wrist; the grasp picks the cube face nearest to it to keep the roll small.
    let facing = |p: Vec3| start_yaw - joints[0] + (p.x - pan_axis.x).atan2(pan_axis.y - p.y);
    let natural = facing(cube.translation);
    let grasp_yaw = (0..4)
        .map(|k| cube_yaw + k as f32 * FRAC_PI_2)
        .min_by(|a, b| angle_between(*a, natural).total_cmp(&angle_between(*b, natural)))
        .unwrap_or(natural);
    let release_yaw = grasp_yaw - natural + facing(bowl);
    let grasp_z = cube.translation.z + GRASP_ABOVE_CENTER;
    let over = |p: Vec3, z: f32| Vec3::new(p.x, p.y, z);

    let start = Waypoint {
        position: gripper.transform_point(grasp_point),
        closing_yaw: start_yaw,
        gripper: scene.state()[GRIPPER],
        frames: 0,
    };
    let at = |position, closing_yaw, gripper, frames| Waypoint { position, closing_yaw, gripper, frames };
    vec![
        start,
        at(over(cube.translation, HOVER_HEIGHT), grasp_yaw, GRIPPER_OPEN, 45),
        at(over(cube.translation, grasp_z), grasp_yaw, GRIPPER_OPEN, 30),
        at(over(cube.translation, grasp_z), grasp_yaw, GRIPPER_CLOSED, 18),
        at(over(cube.translation, HOVER_HEIGHT), grasp_yaw, GRIPPER_CLOSED, 25),
        at(over(bowl, HOVER_HEIGHT), release_yaw, GRIPPER_CLOSED, 40),
        at(over(bowl, RELEASE_HEIGHT), release_yaw, GRIPPER_CLOSED, 18),
        at(over(bowl, RELEASE_HEIGHT), release_yaw, GRIPPER_OPEN, 12),
        at(over(bowl, RETREAT_HEIGHT), release_yaw, GRIPPER_OPEN, 20),
        // Hold still while the cube settles.
        at(over(bowl, RETREAT_HEIGHT), release_yaw, GRIPPER_OPEN, 6),
    ]
}

/// Gripper orientation with the fingers pointing straight down and the jaw closing along
/// `closing_yaw` (gripper frame: x closes the jaw, fingers along -y).
fn pointing_down(closing_yaw: f32) -> Rot3 {
    let closing = Vec3::new(closing_yaw.cos(), closing_yaw.sin(), 0.0);
    Rot3::from_mat3(&Mat3::from_cols(closing, Vec3::Z, closing.cross(Vec3::Z)))
}

fn yaw_of(direction: Vec3) -> f32 {
    direction.y.atan2(direction.x)
}

/// Angle wrapped into (-pi, pi].
fn wrap(angle: f32) -> f32 {
    let wrapped = (angle + PI).rem_euclid(TAU) - PI;
    if wrapped <= -PI { wrapped + TAU } else { wrapped }
}

fn angle_between(a: f32, b: f32) -> f32 {
    wrap(a - b).abs()
}
