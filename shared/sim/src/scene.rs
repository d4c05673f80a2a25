//! The simulated world: a table, the SO-100 arm driven by its servos, and what a task puts on
//! the table (cubes, and a bowl or a target marker: an [`Arrangement`]), in rapier3d. One
//! [`Scene::step`] is one 1/30 s control step (LeRobot SO-100 data is 30 fps) made of several
//! physics substeps; [`Scene::success`] says whether the task is done.
//!
//! The arm links are kinematic bodies posed by forward kinematics of the servo positions: the
//! real arm is position-controlled, so the servo model decides where the links are (each servo
//! moves towards its goal within its speed and torque limits, against the gravity torque of the
//! links outboard of its joint and of the cube while it is held; the gripper stalls on the
//! cube) and the physics decides what the cubes do.
//!
//! Grasping: the closing jaw presses the cube onto the fixed finger until the gripper servo
//! stalls. A real STS3215 grips with tens of newtons against the cube's 0.08 N weight, so
//! static friction never slips; rapier's velocity-level solver cannot hold a body squeezed
//! between two kinematic bodies steadily, so that static friction is modelled as a fixed
//! joint between gripper and cube that exists only while both fingers press on it; the fixed
//! finger's contacts with the cube are off while it holds, and the held cube keeps the jaw
//! from closing further. The cube stays a dynamic body throughout (it hits the bowl, and falls
//! when the jaw opens). With several cubes on the table the jaw holds the one it presses.

use crate::arm::{self, GRIPPER, GRIPPER_LINK, JAW_LINK, JOINT_COUNT, LINK_COUNT, Payload};
use crate::arrangement::Arrangement;
use crate::goal::Goal;
use crate::servo::Servo;
use crate::shape::{Part, Rgb};
use crate::task::{BOWL_FLOOR, BOWL_HEIGHT, BOWL_INNER_RADIUS, CUBE_HALF, TARGET_RADIUS, TaskKind};
use rapier3d::math::{Pose, Rot3, Vec3};
use rapier3d::prelude::{
    ColliderHandle, ContactPair, FixedJointBuilder, ImpulseJointHandle, PhysicsWorld, RigidBodyBuilder,
    RigidBodyHandle, RigidBodyType,
};
use std::f32::consts::FRAC_PI_2;

/// Control rate, frames per second.
pub const FPS: u32 = 30;
/// Gravity, m/s², world frame.
pub const GRAVITY: Vec3 = Vec3::new(0.0, 0.0, -9.81);
/// Physics substeps per control step (240 Hz physics keeps the grasp contacts stiff).
pub const SUBSTEPS: u32 = 8;
/// How far the closing jaw presses into the cube before the gripper servo stalls, metres:
/// the servo's torque limit and the compliance of its position loop, which together set the
/// grip force.
pub const GRIP_SQUEEZE: f32 = 0.0015;
/// Jaw angle above which the gripper counts as released, radians (opening past the cube).
pub const GRIPPER_RELEASED: f32 = 0.3;
/// Gap under which a finger counts as touching the cube, metres.
const TOUCHING: f32 = 0.001;

/// Starting pose of the arm, radians: the published model's "home" keyframe (upper arm up,
/// forearm forward, gripper pointing down), jaw slightly open.
pub const HOME: [f32; JOINT_COUNT] = [0.0, -FRAC_PI_2, FRAC_PI_2, FRAC_PI_2, -FRAC_PI_2, 0.0];

const TABLE_COLOR: Rgb = [0.78, 0.72, 0.62];
const BOWL_COLOR: Rgb = [0.2, 0.45, 0.85];
/// The target marker: white, apart from the table's beige and every cube's colour.
const TARGET_COLOR: Rgb = [0.96, 0.96, 0.94];
/// Thickness of the target marker, metres: paint-thin, yet above the table top for the
/// renderer's depth test.
const TARGET_THICKNESS: f32 = 0.001;
/// Segments of the bowl's wall.
const BOWL_SEGMENTS: usize = 16;
const BOWL_WALL: f32 = 0.004;
/// Table top half extents (x, y), metres; the top surface is z = 0.
const TABLE_HALF: [f32; 2] = [0.45, 0.35];
const TABLE_CENTER_Y: f32 = -0.15;

/// A body with the primitives that make it up, for rendering.
#[derive(Clone, Debug)]
struct Visual {
    body: RigidBodyHandle,
    parts: Vec<Part>,
}

/// One cube's body and its collider.
#[derive(Clone, Copy, Debug)]
struct CubeBody {
    body: RigidBodyHandle,
    collider: ColliderHandle,
}

/// The static-friction hold on a gripped cube (see the module notes on grasping).
#[derive(Clone, Copy, Debug)]
struct Grip {
    joint: ImpulseJointHandle,
    /// Index of the held cube in the arrangement.
    cube: usize,
}

/// The whole simulated scene for one episode.
pub struct Scene {
    world: PhysicsWorld,
    arrangement: Arrangement,
    base: Pose,
    links: [RigidBodyHandle; LINK_COUNT],
    arm_colliders: Vec<ColliderHandle>,
    jaw_colliders: Vec<ColliderHandle>,
    finger_colliders: Vec<ColliderHandle>,
    grip: Option<Grip>,
    /// The cubes, in the arrangement's order.
    cubes: Vec<CubeBody>,
    servos: [Servo; JOINT_COUNT],
    visuals: Vec<Visual>,
    frame: u32,
}

impl Scene {
    /// A new episode of the cube-in-bowl task with cube and bowl placed from `seed`, the arm at
    /// [`HOME`].
    pub fn new(seed: u64) -> Self {
        Self::with_task(TaskKind::CubeInBowl, seed)
    }

    /// A new episode of `task` with its objects placed from `seed`, the arm at [`HOME`].
    pub fn with_task(task: TaskKind, seed: u64) -> Self {
        Self::from_arrangement(Arrangement::from_seed(task, seed))
    }

    /// A new episode with the objects of `arrangement` (one drawn from a seed, or set by hand),
    /// the arm at [`HOME`].
    pub fn from_arrangement(arrangement: Arrangement) -> Self {
        let mut world = PhysicsWorld::new();
        world.gravity = GRAVITY;
        world.integration_parameters.dt = 1.0 / (FPS * SUBSTEPS) as f32;
        // Grasp forces come from penetration depths: keep contacts exact, not recycled.
        world.integration_parameters.contact_recycling = false;
        // Objects here are centimetres across: scale rapier's tolerances (allowed penetration,
        // corrective speed) down from their metre-sized defaults, or a squeeze of a few
        // millimetres would fall inside the allowed error and produce no grip force.
        world.integration_parameters.length_unit = 0.1;
        let mut visuals = Vec::new();

        let table_parts = vec![Part::cuboid(
            Vec3::new(0.0, TABLE_CENTER_Y, -0.02),
            Vec3::new(TABLE_HALF[0], TABLE_HALF[1], 0.02),
            TABLE_COLOR,
        )];
        let (table, _) = add_body(&mut world, &mut visuals, RigidBodyBuilder::fixed(), table_parts, 0.6);
        match arrangement.goal {
            Goal::InBowl { bowl } => {
                add_body(&mut world, &mut visuals, RigidBodyBuilder::fixed().translation(bowl), bowl_parts(), 0.6);
            }
            // Painted on the table: drawn with it, and nothing a pushed cube could catch on.
            Goal::OnTarget { target } => visuals.push(Visual { body: table, parts: vec![target_marker(target)] }),
            Goal::OnCube { .. } => {}
        }
        let cubes = arrangement
            .cubes
            .iter()
            .map(|cube| {
                let parts = vec![Part::cuboid(Vec3::ZERO, Vec3::splat(CUBE_HALF), cube.colour.rgb())];
                let body =
                    RigidBodyBuilder::dynamic().translation(cube.position).rotation(Vec3::new(0.0, 0.0, cube.yaw));
                let (body, colliders) = add_body(&mut world, &mut visuals, body, parts, 1.0);
                CubeBody { body, collider: colliders[0] }
            })
            .collect();

        let base = Pose::IDENTITY;
        let link_poses = arm::forward_kinematics(base, &HOME);
        let mut arm_colliders = Vec::new();
        let mut jaw_colliders = Vec::new();
        let mut finger_colliders = Vec::new();
        let links = {
            let parts = arm::link_parts();
            let mut handles = Vec::with_capacity(LINK_COUNT);
            for (i, parts) in parts.into_iter().enumerate() {
                let builder =
                    if i == 0 { RigidBodyBuilder::fixed() } else { RigidBodyBuilder::kinematic_position_based() }
                        .pose(link_poses[i])
                        .additional_mass(arm::LINKS[i].mass);
                let (handle, colliders) = add_body(&mut world, &mut visuals, builder, parts, 1.0);
                if i == JAW_LINK {
                    jaw_colliders.extend(&colliders);
                }
                if i == GRIPPER_LINK {
                    finger_colliders.extend(&colliders);
                }
                arm_colliders.extend(colliders);
                handles.push(handle);
            }
            <[RigidBodyHandle; LINK_COUNT]>::try_from(handles).expect("one body per link")
        };
        Self {
            world,
            arrangement,
            base,
            links,
            arm_colliders,
            jaw_colliders,
            finger_colliders,
            grip: None,
            cubes,
            servos: HOME.map(Servo::new),
            visuals,
            frame: 0,
        }
    }

    /// Advances one control step (1/30 s) towards the goal positions `action`, in robot units
    /// (degrees for the five arm joints, 0..100 for the gripper). Goals outside the joint
    /// limits are clamped to them, as the servo firmware does; a non-finite goal (a policy
    /// gone wrong) leaves that servo's previous goal in place.
    pub fn step(&mut self, action: [f32; JOINT_COUNT]) {
        let goal = arm::clamp_to_limits(&arm::from_robot_units(&action));
        for (servo, goal) in self.servos.iter_mut().zip(goal) {
            if goal.is_finite() {
                servo.goal = goal;
            }
        }
        let dt = self.world.integration_parameters.dt;
        let joints = arm::joints();
        for _ in 0..SUBSTEPS {
            let (pressed_cube, jaw_penetration) = self.jaw_press();
            self.update_grip(pressed_cube, jaw_penetration);
            let loads = self.gravity_loads();
            // The squeezed cube stops the closing jaw, and keeps it from closing further for as
            // long as it is held (the jaw's contact with the held cube jitters about the squeeze).
            let squeezed = self.grip.is_some() || jaw_penetration > GRIP_SQUEEZE;
            let jaw_blocked = squeezed.then_some(-1.0);
            for (i, servo) in self.servos.iter_mut().enumerate() {
                servo.advance(dt, loads[i], if i == GRIPPER { jaw_blocked } else { None });
                // The joint's mechanical stops hold an overloaded servo that is pushed back.
                servo.position = servo.position.clamp(joints[i].lower, joints[i].upper);
            }
            let poses = arm::forward_kinematics(self.base, &self.joint_positions());
            for (handle, pose) in self.links.iter().zip(poses).skip(1) {
                self.world.bodies[*handle].set_next_kinematic_position(pose);
            }
            self.world.step();
        }
        self.frame += 1;
    }

    /// Measured joint positions in robot units (degrees, gripper 0..100): `observation.state`.
    pub fn state(&self) -> [f32; JOINT_COUNT] {
        arm::to_robot_units(&self.joint_positions())
    }

    /// Measured joint positions, radians.
    pub fn joint_positions(&self) -> [f32; JOINT_COUNT] {
        self.servos.map(|servo| servo.position)
    }

    /// Torque each servo drove its joint with in the last physics substep, N·m, positive along
    /// the joint axis (see [`Servo::torque`]).
    pub fn joint_torques(&self) -> [f32; JOINT_COUNT] {
        self.servos.map(|servo| servo.torque)
    }

    /// Sets the torque limit of the servo of `joint`, N·m (a weaker or stronger servo than the
    /// STS3215 at 7.4 V, e.g. the 12 V version or one on a sagging supply).
    pub fn set_stall_torque(&mut self, joint: usize, torque: f32) {
        self.servos[joint].stall_torque = torque;
    }

    /// Whether the task is done: its cube is where the task's [`Goal`] asks (for the cube-in-bowl
    /// task: centre within [`crate::task::SUCCESS_RADIUS`] horizontally of the bowl centre and
    /// below [`crate::task::SUCCESS_MAX_HEIGHT`]), the gripper has let go and no part of the arm
    /// touches a cube.
    pub fn success(&self) -> bool {
        let cubes: Vec<Vec3> = (0..self.cubes.len()).map(|cube| self.cube_pose_at(cube).translation).collect();
        self.arrangement.goal.met(self.arrangement.subject, &cubes)
            && self.servos[GRIPPER].position > GRIPPER_RELEASED
            && !self.arm_touches_cube()
    }

    /// The task this episode sets.
    pub fn task(&self) -> TaskKind {
        self.arrangement.task
    }

    /// The task's language instruction for this episode (LeRobot `task`).
    pub fn instruction(&self) -> String {
        self.arrangement.instruction()
    }

    /// Control steps taken since the episode started.
    pub fn frame(&self) -> u32 {
        self.frame
    }

    /// What stood on the table as the episode started, and what the task asks.
    pub fn arrangement(&self) -> &Arrangement {
        &self.arrangement
    }

    /// Pose of the arm's base on the table.
    pub fn base_pose(&self) -> Pose {
        self.base
    }

    /// Current pose of the cube the task moves (centre), world frame, metres.
    pub fn cube_pose(&self) -> Pose {
        self.cube_pose_at(self.arrangement.subject)
    }

    /// Current pose of cube `index` of the arrangement (centre), world frame, metres.
    pub fn cube_pose_at(&self, index: usize) -> Pose {
        *self.world.bodies[self.cubes[index].body].position()
    }

    /// Current pose of arm link `index` (see [`arm::LINKS`]), world frame.
    pub fn link_pose(&self, index: usize) -> Pose {
        *self.world.bodies[self.links[index]].position()
    }

    /// Everything to draw, with each body's current pose.
    pub fn visuals(&self) -> impl Iterator<Item = (Pose, &[Part])> {
        self.visuals.iter().map(|visual| (*self.world.bodies[visual.body].position(), visual.parts.as_slice()))
    }

    /// Whether any arm collider is in contact with any cube.
    pub fn arm_touches_cube(&self) -> bool {
        (0..self.cubes.len()).any(|cube| {
            self.cube_contacts(cube, &self.arm_colliders).any(rapier3d::geometry::ContactPair::has_any_active_contact)
        })
    }

    /// Whether a cube is held by the gripper (see the module notes on grasping).
    pub fn cube_gripped(&self) -> bool {
        self.grip.is_some()
    }

    /// Index in the arrangement of the cube the gripper holds, if it holds one.
    pub fn held_cube(&self) -> Option<usize> {
        self.grip.map(|grip| grip.cube)
    }

    /// Torque each joint needs to hold the arm still against gravity as it stands now, with the
    /// cube while it is gripped, N·m.
    fn gravity_loads(&self) -> [f32; JOINT_COUNT] {
        let links = self.links.map(|link| *self.world.bodies[link].position());
        let held = self.grip.map(|grip| {
            let cube = &self.world.bodies[self.cubes[grip.cube].body];
            Payload { link: GRIPPER_LINK, mass: cube.mass(), position: cube.center_of_mass() }
        });
        arm::gravity_torques(&links, held, GRAVITY)
    }

    /// Starts holding cube `pressed_cube` when the jaw presses it `jaw_penetration` deep onto
    /// the fixed finger, and lets go as soon as the gripper is told to open.
    fn update_grip(&mut self, pressed_cube: usize, jaw_penetration: f32) {
        let jaw = self.servos[GRIPPER];
        let opening = jaw.goal > jaw.position;
        match self.grip {
            None if !opening
                && jaw_penetration > GRIP_SQUEEZE
                && self.deepest_contact(pressed_cube, &self.finger_colliders) > -TOUCHING =>
            {
                let gripper = self.links[GRIPPER_LINK];
                let relative = self.world.bodies[gripper].position().inv_mul(&self.cube_pose_at(pressed_cube));
                // The hold stands in for the fixed finger's contact with the cube: left on, that
                // contact fights the joint, stores impulse and flings the cube when it lets go.
                let hold = FixedJointBuilder::new()
                    .local_frame1(relative)
                    .local_frame2(Pose::IDENTITY)
                    .contacts_enabled(false);
                let joint = self.world.impulse_joints.insert(gripper, self.cubes[pressed_cube].body, hold, true);
                self.grip = Some(Grip { joint, cube: pressed_cube });
            }
            Some(grip) if opening => {
                self.world.impulse_joints.remove(grip.joint, true);
                self.grip = None;
            }
            _ => {}
        }
    }

    /// The cube the moving jaw presses deepest into, and how deep, metres (0 when apart from
    /// every cube).
    fn jaw_press(&self) -> (usize, f32) {
        (0..self.cubes.len())
            .map(|cube| (cube, self.deepest_contact(cube, &self.jaw_colliders).max(0.0)))
            .fold((0, 0.0), |deepest, press| if press.1 > deepest.1 { press } else { deepest })
    }

    /// Largest penetration (negative: gap) between cube `cube` and any of `colliders`, metres;
    /// minus infinity when none is near.
    fn deepest_contact(&self, cube: usize, colliders: &[ColliderHandle]) -> f32 {
        self.cube_contacts(cube, colliders)
            .filter_map(|pair| pair.find_deepest_contact())
            .map(|(_, contact)| -contact.dist)
            .fold(f32::NEG_INFINITY, f32::max)
    }

    /// Contact pairs between cube `cube` and any of `colliders`.
    fn cube_contacts<'a>(
        &'a self,
        cube: usize,
        colliders: &'a [ColliderHandle],
    ) -> impl Iterator<Item = &'a ContactPair> {
        self.world
            .narrow_phase
            .contact_pairs_with(self.cubes[cube].collider)
            .filter(move |pair| colliders.contains(&pair.collider1) || colliders.contains(&pair.collider2))
    }
}

/// Inserts a body and one collider per part; returns the body and its colliders.
fn add_body(
    world: &mut PhysicsWorld,
    visuals: &mut Vec<Visual>,
    builder: RigidBodyBuilder,
    parts: Vec<Part>,
    friction: f32,
) -> (RigidBodyHandle, Vec<ColliderHandle>) {
    let body = builder.build();
    let is_dynamic = body.body_type() == RigidBodyType::Dynamic;
    let handle = world.bodies.insert(body);
    let colliders = parts
        .iter()
        .map(|part| {
            // Wood-like density for the cube; other bodies are fixed or kinematic.
            let collider = part.collider().friction(friction).density(if is_dynamic { 600.0 } else { 0.0 });
            world.colliders.insert_with_parent(collider, handle, &mut world.bodies)
        })
        .collect();
    visuals.push(Visual { body: handle, parts });
    (handle, colliders)
}

/// The target marker: a thin white disc on the table centred on `target`.
fn target_marker(target: Vec3) -> Part {
    let center = Vec3::new(target.x, target.y, TARGET_THICKNESS * 0.5);
    Part::cylinder(center, upright(), TARGET_THICKNESS * 0.5, TARGET_RADIUS, TARGET_COLOR)
}

/// Rapier cylinders stand along local y: this turns one to stand along z.
fn upright() -> Rot3 {
    Rot3::from_rotation_x(FRAC_PI_2)
}

/// The bowl: a round floor and a wall of flat segments, centred on the body origin.
fn bowl_parts() -> Vec<Part> {
    let outer = BOWL_INNER_RADIUS + BOWL_WALL;
    let mut parts =
        vec![Part::cylinder(Vec3::new(0.0, 0.0, BOWL_FLOOR * 0.5), upright(), BOWL_FLOOR * 0.5, outer, BOWL_COLOR)];
    let segment_half_length = outer * (std::f32::consts::PI / BOWL_SEGMENTS as f32).tan();
    for k in 0..BOWL_SEGMENTS {
        let angle = k as f32 * std::f32::consts::TAU / BOWL_SEGMENTS as f32;
        let radial = BOWL_INNER_RADIUS + BOWL_WALL * 0.5;
        let center = Vec3::new(angle.cos() * radial, angle.sin() * radial, BOWL_HEIGHT * 0.5);
        let mut wall =
            Part::cuboid(Vec3::ZERO, Vec3::new(BOWL_WALL * 0.5, segment_half_length, BOWL_HEIGHT * 0.5), BOWL_COLOR);
        wall.local = Pose::from_parts(center, Rot3::from_rotation_z(angle));
        parts.push(wall);
    }
    parts
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn out_of_range_and_non_finite_actions_keep_the_arm_in_its_limits() {
        let mut scene = Scene::new(0);
        for action in [[1e6; JOINT_COUNT], [f32::NAN; JOINT_COUNT], [-1e6; JOINT_COUNT]] {
            for _ in 0..30 {
                scene.step(action);
            }
            let q = scene.joint_positions();
            assert!(q.iter().all(|v| v.is_finite()), "{q:?}");
            assert_eq!(arm::clamp_to_limits(&q), q);
        }
    }
}
