//! The scripted expert that demonstrates every task: a sequence of waypoints for one point of
//! the gripper, followed by damped-least-squares inverse kinematics, one goal per control
//! frame. Picking tasks (the bowl, the stack) go above the cube, descend, close, lift, go over
//! the place, lower, open and retreat; pushing goes down behind the cube, along the line to the
//! target, back and up.
//!
//! Picks are planned once (and again after a missed grasp). A push goes in short strokes, each
//! aimed from where the cube is at the target: pushed in one open-loop stroke, a cube kicked off
//! its line by a perturbed arm (the recovery demonstrations, [`crate::perturbation`]) ends centimetres
//! from the target.

use crate::arm::{self, FINGER_TIP_Y, FIXED_FINGER_FACE_X, FIXED_FINGER_THICKNESS, GRIPPER, GRIPPER_LINK, JOINT_COUNT};
use crate::arrangement::PUSH_APPROACH;
use crate::goal::Goal;
use crate::ik::{self, GripperTarget};
use crate::scene::{FPS, Scene};
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
/// How far above the lower cube's top a stacked cube is let go, metres.
const STACK_DROP: f32 = 0.003;
/// How far the fixed finger backs off a stacked cube before the gripper lifts, metres: lifted
/// straight up, the finger's friction would drag the cube off the stack (in the bowl the cube
/// drops clear of it).
const STACK_BACK_OFF: f32 = 0.006;
/// Height of the grasp point at the end, metres.
const RETREAT_HEIGHT: f32 = 0.13;
/// Gripper goals, robot units (0 closed .. 100 open). Closing towards 0 makes the jaw stall
/// on the cube.
const GRIPPER_OPEN: f32 = 40.0;
const GRIPPER_CLOSED: f32 = 0.0;
/// Height of the pushing point over the table, metres: the finger's tip skims the table and
/// its face covers the cube's side.
const PUSH_HEIGHT: f32 = 0.01;
/// How far above the finger's tip the pushing point is, metres.
const PUSH_ABOVE_TIP: f32 = 0.008;
/// Average speed of the pushing finger along its stroke, m/s: a stroke takes two to four
/// seconds.
const PUSH_SPEED: f32 = 0.03;
/// How far the finger backs off the pushed cube before it lifts, metres.
const PUSH_BACK_OFF: f32 = 0.01;
/// How far one stroke of a push moves the cube, metres: after each the expert aims again.
const PUSH_STROKE: f32 = 0.015;
/// How near the target the cube's centre has to be for the push to end, metres.
const PUSH_CLOSE_ENOUGH: f32 = 0.008;
/// Strokes a push takes at most before it backs off wherever the cube is.
const MAX_STROKES: u32 = 16;

/// One point of the plan: where the tool point goes, how the jaw is turned, what the gripper
/// is told, and in how many frames it gets there from the previous point.
#[derive(Clone, Copy, Debug)]
struct Waypoint {
    position: Vec3,
    /// Direction (about the vertical, radians) in which the jaw closes.
    closing_yaw: f32,
    gripper: f32,
    frames: u32,
}

impl Waypoint {
    fn new(position: Vec3, closing_yaw: f32, gripper: f32, frames: u32) -> Self {
        Self { position, closing_yaw, gripper, frames }
    }
}

/// What the expert does once a plan has been played to its end.
#[derive(Clone, Copy, Debug)]
enum Then {
    /// Holds the plan's last pose: the demonstration is over.
    Hold,
    /// Pushes on to `target`: another stroke aimed from where the cube is, or the back-off once it
    /// is there.
    PushOn { target: Vec3, side: FingerSide, strokes: u32 },
}

/// A demonstration as planned from one moment of the episode.
#[derive(Clone, Debug)]
struct Plan {
    /// The point of the gripper frame the waypoints lead: between the jaws for picking, a face
    /// of the fixed finger for pushing.
    tool_point: Vec3,
    waypoints: Vec<Waypoint>,
    /// For a plan that grasps, the index of the waypoint that ends the lift: if the task's cube
    /// is not held by then, the grasp missed and the expert plans again from where things are.
    lifted: Option<usize>,
    then: Then,
}

/// Index of the waypoint that ends the lift in a picking plan.
const LIFTED: usize = 4;
/// How many times a missed grasp, or a push whose finger lost the cube, starts over.
const MAX_RETRIES: u32 = 2;

/// Scripted expert for one episode; plans from the scene it is created with.
#[derive(Clone, Debug)]
pub struct Expert {
    base: Pose,
    plan: Plan,
    frame: u32,
    joints: [f32; JOINT_COUNT],
    retries: u32,
}

impl Expert {
    /// Plans the demonstration of the scene's task from the current arm pose and the objects
    /// on the table.
    pub fn new(scene: &Scene) -> Self {
        let joints = scene.joint_positions();
        Self { base: scene.base_pose(), plan: plan(scene, &joints), frame: 0, joints, retries: 0 }
    }

    /// Frames the part of the demonstration planned now takes (a retry or a push's next stroke is
    /// a new plan).
    fn planned_frames(&self) -> u32 {
        self.plan.waypoints.iter().map(|w| w.frames).sum()
    }

    /// Whether the demonstration has been played to its end.
    pub fn done(&self) -> bool {
        self.frame >= self.planned_frames() && matches!(self.plan.then, Then::Hold)
    }

    /// The next action, in robot units (degrees, gripper 0..100): goal positions for this
    /// control frame. Watches `scene` for a missed grasp and at the end of each part of the plan;
    /// after the end of the demonstration it keeps holding the final pose.
    pub fn act(&mut self, scene: &Scene) -> [f32; JOINT_COUNT] {
        if let Some(lifted) = self.plan.lifted {
            let lifted_at: u32 = self.plan.waypoints[..=lifted].iter().map(|w| w.frames).sum();
            let holding = scene.held_cube() == Some(scene.arrangement().subject);
            if self.frame == lifted_at && !holding && self.retries < MAX_RETRIES {
                self.retries += 1;
                self.start(plan(scene, &self.joints));
            }
        }
        if self.frame >= self.planned_frames()
            && let Some(next) = self.next_plan(scene)
        {
            self.start(next);
        }
        self.frame = (self.frame + 1).min(self.planned_frames());
        let waypoint = self.waypoint_at(self.frame);
        let target = GripperTarget {
            point: self.plan.tool_point,
            position: waypoint.position,
            orientation: pointing_down(waypoint.closing_yaw),
        };
        self.joints = ik::solve(self.base, &self.joints, &target);
        let mut action = arm::to_robot_units(&self.joints);
        action[GRIPPER] = waypoint.gripper;
        action
    }

    fn start(&mut self, plan: Plan) {
        self.plan = plan;
        self.frame = 0;
    }

    /// The plan that follows the one just played to its end, if any.
    fn next_plan(&mut self, scene: &Scene) -> Option<Plan> {
        match self.plan.then {
            Then::Hold => None,
            Then::PushOn { target, side, strokes } => {
                let arm = ArmAtStart::new(scene, &self.joints);
                match next_stroke(scene, &arm, target, side, strokes) {
                    Stroke::Planned(plan) => Some(plan),
                    Stroke::LostContact if self.retries < MAX_RETRIES => {
                        self.retries += 1;
                        Some(push(scene, &arm, target))
                    }
                    Stroke::LostContact => Some(back_off(&arm, side, target)),
                }
            }
        }
    }

    /// The plan interpolated at `frame`: smooth in position and yaw, linear in gripper.
    fn waypoint_at(&self, frame: u32) -> Waypoint {
        let waypoints = &self.plan.waypoints;
        let mut elapsed = 0;
        for pair in waypoints.windows(2) {
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
        waypoints[waypoints.len() - 1]
    }
}

/// The plan for the scene's task from the arm at `joints` (radians).
fn plan(scene: &Scene, joints: &[f32; JOINT_COUNT]) -> Plan {
    let arm = ArmAtStart::new(scene, joints);
    match scene.arrangement().goal {
        Goal::InBowl { bowl } => pick_and_place(scene, &arm, Place::InBowl(bowl)),
        Goal::OnCube { base } => pick_and_place(scene, &arm, Place::OnCube(scene.cube_pose_at(base))),
        Goal::OnTarget { target } => push(scene, &arm, target),
    }
}

/// Where a picked cube is let go.
#[derive(Clone, Copy, Debug)]
enum Place {
    /// In the bowl whose base is centred here.
    InBowl(Vec3),
    /// On top of the cube standing at this pose.
    OnCube(Pose),
}

/// The arm as a plan starts from it.
struct ArmAtStart {
    gripper: Pose,
    pan_axis: Vec3,
    pan: f32,
    /// Direction in which the jaw closes now, radians.
    closing_yaw: f32,
    /// The gripper's position, robot units.
    gripper_opening: f32,
}

impl ArmAtStart {
    fn new(scene: &Scene, joints: &[f32; JOINT_COUNT]) -> Self {
        let links = arm::forward_kinematics(scene.base_pose(), joints);
        let gripper = links[GRIPPER_LINK];
        Self {
            gripper,
            pan_axis: links[1].translation,
            pan: joints[0],
            closing_yaw: yaw_of(gripper.rotation * Vec3::X),
            gripper_opening: scene.state()[GRIPPER],
        }
    }

    /// The jaw's closing direction when the arm turns to face `p` without rolling the wrist:
    /// plans keep the jaw's yaw near it, for the wrist's roll stays far from its limits there.
    fn facing(&self, p: Vec3) -> f32 {
        self.closing_yaw - self.pan + (p.x - self.pan_axis.x).atan2(self.pan_axis.y - p.y)
    }

    /// The first waypoint of a plan leading `tool_point`: where it is now.
    fn waypoint(&self, tool_point: Vec3) -> Waypoint {
        Waypoint::new(self.gripper.transform_point(tool_point), self.closing_yaw, self.gripper_opening, 0)
    }
}

/// Picks the task's cube and lets it go at `place`; on a cube, with the faces of both turned
/// the same way.
fn pick_and_place(scene: &Scene, arm: &ArmAtStart, place: Place) -> Plan {
    let grasp_point = arm::grasp_point(CUBE_HALF + FINGER_CLEARANCE);
    let cube = scene.cube_pose();
    let cube_yaw = yaw_of(cube.rotation * Vec3::X);
    // The grasp picks the cube face nearest to the natural closing direction to keep the roll
    // small.
    let natural = arm.facing(cube.translation);
    let grasp_yaw = nearest_face(cube_yaw, natural);
    // The jaw's yaw over `p`, turned with the arm from the grasp.
    let turned = |p: Vec3| grasp_yaw - natural + arm.facing(p);
    // Where the grasp point lets go, and the jaw's yaw there.
    let (release, release_yaw) = match place {
        Place::InBowl(bowl) => (over(bowl, RELEASE_HEIGHT), turned(bowl)),
        Place::OnCube(below) => {
            let release = below.translation + Vec3::Z * (2.0 * CUBE_HALF + GRASP_ABOVE_CENTER + STACK_DROP);
            (release, nearest_face(yaw_of(below.rotation * Vec3::X), turned(below.translation)))
        }
    };
    let grasp_z = cube.translation.z + GRASP_ABOVE_CENTER;
    let at = Waypoint::new;
    let mut waypoints = vec![
        arm.waypoint(grasp_point),
        at(over(cube.translation, HOVER_HEIGHT), grasp_yaw, GRIPPER_OPEN, 45),
        at(over(cube.translation, grasp_z), grasp_yaw, GRIPPER_OPEN, 30),
        at(over(cube.translation, grasp_z), grasp_yaw, GRIPPER_CLOSED, 18),
        at(over(cube.translation, HOVER_HEIGHT), grasp_yaw, GRIPPER_CLOSED, 25),
        at(over(release, HOVER_HEIGHT), release_yaw, GRIPPER_CLOSED, 40),
        at(over(release, release.z), release_yaw, GRIPPER_CLOSED, 18),
        at(over(release, release.z), release_yaw, GRIPPER_OPEN, 12),
    ];
    let mut retreat = release;
    if let Place::OnCube(_) = place {
        // The fixed finger lies on the cube's side the jaw closes towards.
        retreat += Vec3::new(release_yaw.cos(), release_yaw.sin(), 0.0) * STACK_BACK_OFF;
        waypoints.push(at(retreat, release_yaw, GRIPPER_OPEN, 8));
    }
    waypoints.extend([
        at(over(retreat, RETREAT_HEIGHT), release_yaw, GRIPPER_OPEN, 20),
        // Hold still while the cube settles.
        at(over(retreat, RETREAT_HEIGHT), release_yaw, GRIPPER_OPEN, 6),
    ]);
    Plan { tool_point: grasp_point, waypoints, lifted: Some(LIFTED), then: Then::Hold }
}

/// Which face of the fixed finger pushes: the outer one pushes towards where the jaw closes, the
/// inner one the other way.
#[derive(Clone, Copy, Debug)]
enum FingerSide {
    Outer,
    Inner,
}

impl FingerSide {
    /// The pushing point on this face, gripper frame.
    fn tool_point(self) -> Vec3 {
        let face_x = match self {
            FingerSide::Outer => FIXED_FINGER_FACE_X + FIXED_FINGER_THICKNESS,
            FingerSide::Inner => FIXED_FINGER_FACE_X,
        };
        Vec3::new(face_x, FINGER_TIP_Y + PUSH_ABOVE_TIP, 0.0)
    }

    /// The jaw's closing yaw that turns this face to push along `push_yaw`.
    fn closing_yaw(self, push_yaw: f32) -> f32 {
        match self {
            FingerSide::Outer => push_yaw,
            FingerSide::Inner => wrap(push_yaw + PI),
        }
    }
}

/// Goes down behind the task's cube, on the side away from `target`, with a face of the fixed
/// finger held flat against the cube's face turned most towards the target, the jaw open behind
/// the finger or beyond the cube; the strokes follow ([`next_stroke`]). The servos move the finger
/// in a burst each control frame, so each contact kicks the cube a few millimetres along the
/// contact's normal: the cube goes straight only pushed face to face, and the arrangement puts the
/// target straight out from a face.
fn push(scene: &Scene, arm: &ArmAtStart, target: Vec3) -> Plan {
    let cube = scene.cube_pose();
    let heading = (target - cube.translation).truncate().normalize_or_zero().extend(0.0);
    let face_yaw = nearest_face(yaw_of(cube.rotation * Vec3::X), yaw_of(heading));
    // Of the finger's two faces, the one that keeps the jaw's yaw nearer the natural one.
    let side = if angle_between(face_yaw, arm.facing(cube.translation)) <= FRAC_PI_2 {
        FingerSide::Outer
    } else {
        FingerSide::Inner
    };
    let closing_yaw = side.closing_yaw(face_yaw);
    let behind = over(cube.translation - heading * PUSH_APPROACH, PUSH_HEIGHT);
    let at = |position, frames| Waypoint::new(position, closing_yaw, GRIPPER_OPEN, frames);
    let waypoints = vec![arm.waypoint(side.tool_point()), at(over(behind, HOVER_HEIGHT), 45), at(behind, 30)];
    Plan { tool_point: side.tool_point(), waypoints, lifted: None, then: Then::PushOn { target, side, strokes: 0 } }
}

/// What follows a stroke of a push.
enum Stroke {
    /// The next stroke, or the back-off once the cube is on the target.
    Planned(Plan),
    /// The finger is no longer behind the cube as seen from the target: the push has to start over.
    LostContact,
}

/// The stroke after `strokes` strokes, judged from where the finger's face is: a push of the cube by
/// at most [`PUSH_STROKE`] along the line from where it is now to `target`, the finger's face
/// square to that line (squared to the cube's own face instead, the push lost 5 of 20 seeds
/// without any perturbation); or, once the cube is there (or after [`MAX_STROKES`]), the back-off.
fn next_stroke(scene: &Scene, arm: &ArmAtStart, target: Vec3, side: FingerSide, strokes: u32) -> Stroke {
    let cube = scene.cube_pose();
    let to_target = (target - cube.translation).truncate();
    let distance = to_target.length();
    if distance < PUSH_CLOSE_ENOUGH || strokes >= MAX_STROKES {
        return Stroke::Planned(back_off(arm, side, target));
    }
    let heading = to_target / distance;
    let finger = scene.link_pose(GRIPPER_LINK).transform_point(side.tool_point());
    let from_cube = (finger - cube.translation).truncate();
    if from_cube.dot(heading) > -0.5 * CUBE_HALF || from_cube.perp_dot(heading).abs() > 0.75 * CUBE_HALF {
        return Stroke::LostContact;
    }
    let heading = heading.extend(0.0);
    let closing_yaw = side.closing_yaw(yaw_of(heading));
    let start = arm.waypoint(side.tool_point());
    let end = over(cube.translation + heading * (distance.min(PUSH_STROKE) - CUBE_HALF), PUSH_HEIGHT);
    let frames = ((end - start.position).length() / PUSH_SPEED * FPS as f32).ceil().max(4.0) as u32;
    Stroke::Planned(Plan {
        tool_point: side.tool_point(),
        waypoints: vec![start, Waypoint::new(end, closing_yaw, GRIPPER_OPEN, frames)],
        lifted: None,
        then: Then::PushOn { target, side, strokes: strokes + 1 },
    })
}

/// Backs the pushing finger off, away from `target`, and lifts it.
fn back_off(arm: &ArmAtStart, side: FingerSide, target: Vec3) -> Plan {
    let start = arm.waypoint(side.tool_point());
    let away = (start.position - target).truncate().normalize_or_zero().extend(0.0);
    let back = start.position + away * PUSH_BACK_OFF;
    let at = |position, frames| Waypoint::new(position, arm.closing_yaw, GRIPPER_OPEN, frames);
    Plan {
        tool_point: side.tool_point(),
        waypoints: vec![start, at(back, 10), at(over(back, RETREAT_HEIGHT), 20), at(over(back, RETREAT_HEIGHT), 6)],
        lifted: None,
        then: Then::Hold,
    }
}

/// The point at height `z` above or below `p`.
fn over(p: Vec3, z: f32) -> Vec3 {
    Vec3::new(p.x, p.y, z)
}

/// Of the four directions a cube of yaw `cube_yaw` has its faces along, the nearest to `towards`.
fn nearest_face(cube_yaw: f32, towards: f32) -> f32 {
    (0..4)
        .map(|k| cube_yaw + k as f32 * FRAC_PI_2)
        .min_by(|a, b| angle_between(*a, towards).total_cmp(&angle_between(*b, towards)))
        .unwrap_or(towards)
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
