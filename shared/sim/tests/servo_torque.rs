//! The servos' torque limits against gravity: a load within the limit is held at the goal, a
//! load beyond it pushes the joint back, the load grows with the arm's reach, and the speed
//! limit still holds.

use fedvla_sim::arm::{self, JOINT_COUNT, JOINT_NAMES, LINKS};
use fedvla_sim::scene::{FPS, GRAVITY, HOME};
use fedvla_sim::servo::{MAX_SPEED, NO_LOAD_SPEED, STALL_TORQUE};
use fedvla_sim::{Scene, run_expert_episode};
use rapier3d::math::Pose;

const SHOULDER_PAN: usize = 0;
const SHOULDER_LIFT: usize = 1;
/// Arm stretched out forward, radians: upper arm, forearm and gripper nearly horizontal.
const STRETCHED: [f32; JOINT_COUNT] = [0.0; JOINT_COUNT];
/// Arm pointing straight up, radians.
const UPRIGHT: [f32; JOINT_COUNT] = [0.0, -std::f32::consts::FRAC_PI_2, 0.0, 0.0, 0.0, 0.0];

/// Sends the goal `q` (radians) for `frames` control frames.
fn drive(scene: &mut Scene, q: &[f32; JOINT_COUNT], frames: u32) {
    for _ in 0..frames {
        scene.step(arm::to_robot_units(q));
    }
}

/// Gravity torque on each joint at `q` (radians), arm bare.
fn gravity_load(q: &[f32; JOINT_COUNT]) -> [f32; JOINT_COUNT] {
    arm::gravity_torques(&arm::forward_kinematics(Pose::IDENTITY, q), None, GRAVITY)
}

#[test]
fn joint_names_match_the_indices_used_here() {
    assert_eq!(JOINT_NAMES[SHOULDER_PAN], "shoulder_pan");
    assert_eq!(JOINT_NAMES[SHOULDER_LIFT], "shoulder_lift");
}

#[test]
fn a_load_within_the_limit_is_reached_and_held() {
    let mut scene = Scene::new(0);
    drive(&mut scene, &STRETCHED, 60);
    let load = gravity_load(&STRETCHED)[SHOULDER_LIFT];
    assert!((0.9..STALL_TORQUE).contains(&load.abs()), "shoulder load {load} N·m");
    for _ in 0..60 {
        scene.step(arm::to_robot_units(&STRETCHED));
        let q = scene.joint_positions();
        for i in 0..JOINT_COUNT {
            assert!((q[i] - STRETCHED[i]).abs() < 1e-5, "joint {i} at {}", q[i]);
        }
        // Holding still, each servo gives exactly the gravity torque on its joint.
        let torques = scene.joint_torques();
        assert!(
            (torques[SHOULDER_LIFT] - load).abs() < 1e-4,
            "shoulder gives {} N·m for a {load} N·m load",
            torques[SHOULDER_LIFT]
        );
    }
}

#[test]
fn shoulder_load_grows_from_upright_to_stretched_out_as_the_weights_lever() {
    let mut scene = Scene::new(0);
    drive(&mut scene, &UPRIGHT, 60);
    let upright = scene.joint_torques()[SHOULDER_LIFT];
    drive(&mut scene, &STRETCHED, 60);
    let stretched = scene.joint_torques()[SHOULDER_LIFT];
    assert!(upright.abs() < 0.1, "upright: {upright} N·m");
    assert!(stretched.abs() > 0.9, "stretched: {stretched} N·m");
    assert!(stretched.abs() > 10.0 * upright.abs());

    // Stretched out along -y, every link's weight pulls at a lever of its centre of mass's
    // distance along y from the shoulder axis (which lies along x).
    let shoulder_y = scene.link_pose(SHOULDER_LIFT + 1).translation.y;
    let by_hand: f32 = (SHOULDER_LIFT + 1..LINKS.len())
        .map(|link| {
            let center = scene.link_pose(link).transform_point(LINKS[link].center_of_mass);
            assert!(center.y < shoulder_y, "link {link} is not ahead of the shoulder");
            LINKS[link].mass * -GRAVITY.z * (shoulder_y - center.y)
        })
        .sum();
    assert!((stretched.abs() - by_hand).abs() < 1e-3, "{stretched} N·m vs {by_hand} N·m by hand");
}

#[test]
fn a_servo_weaker_than_its_load_sags_and_cannot_lift() {
    let mut scene = Scene::new(0);
    drive(&mut scene, &STRETCHED, 60);
    let load = gravity_load(&STRETCHED)[SHOULDER_LIFT];
    // Lifting the stretched arm means turning the shoulder towards -pi/2 (upright).
    assert!(load < 0.0);
    let weak = 0.6;
    scene.set_stall_torque(SHOULDER_LIFT, weak);
    let mut lift = STRETCHED;
    lift[SHOULDER_LIFT] = -0.5;

    scene.step(arm::to_robot_units(&lift));
    // Full drive upwards, yet pushed down along the torque-speed line.
    assert_eq!(scene.joint_torques()[SHOULDER_LIFT], -weak);
    let sag_speed = NO_LOAD_SPEED * (load.abs() / weak - 1.0);
    let sagged = scene.joint_positions()[SHOULDER_LIFT];
    let expected = sag_speed / FPS as f32;
    assert!((sagged - expected).abs() < 0.1 * expected, "sagged {sagged} rad in one frame, expected about {expected}");

    // It ends on the joint's mechanical stop, still pushing with all it has.
    drive(&mut scene, &lift, 30);
    let stop = arm::joints()[SHOULDER_LIFT].upper;
    assert_eq!(scene.joint_positions()[SHOULDER_LIFT], stop);
    assert_eq!(scene.joint_torques()[SHOULDER_LIFT], -weak);

    // Given its torque back, it lifts the arm to the goal.
    scene.set_stall_torque(SHOULDER_LIFT, STALL_TORQUE);
    drive(&mut scene, &lift, 30);
    assert!((scene.joint_positions()[SHOULDER_LIFT] - lift[SHOULDER_LIFT]).abs() < 1e-5);
}

#[test]
fn a_servo_just_short_of_its_load_sags_until_the_load_eases_to_its_limit_and_stalls() {
    let mut scene = Scene::new(0);
    drive(&mut scene, &STRETCHED, 60);
    // Stretched out, the shoulder's load is largest with the upper arm a little above
    // horizontal and eases as the arm sinks below it.
    let limit = gravity_load(&STRETCHED)[SHOULDER_LIFT].abs() - 0.013;
    scene.set_stall_torque(SHOULDER_LIFT, limit);
    drive(&mut scene, &STRETCHED, 240);
    let sagged = scene.joint_positions();
    let stop = arm::joints()[SHOULDER_LIFT].upper;
    assert!((0.02..stop - 0.02).contains(&sagged[SHOULDER_LIFT]), "shoulder at {}", sagged[SHOULDER_LIFT]);
    let load = gravity_load(&sagged)[SHOULDER_LIFT];
    assert!((load.abs() - limit).abs() < 1e-3, "load {load} N·m against a {limit} N·m limit");
    assert_eq!(scene.joint_torques()[SHOULDER_LIFT], -limit);
    scene.step(arm::to_robot_units(&STRETCHED));
    let moved = scene.joint_positions()[SHOULDER_LIFT] - sagged[SHOULDER_LIFT];
    assert!(moved.abs() < 1e-4, "still moving: {moved} rad per frame");
}

#[test]
fn speed_limits_hold_and_a_heavy_lift_is_slower() {
    let mut scene = Scene::new(0);
    // The pan axis is vertical: no gravity load, so it turns at the top speed.
    let mut pan = HOME;
    pan[SHOULDER_PAN] = 1.5;
    let mut previous = scene.joint_positions()[SHOULDER_PAN];
    for _ in 0..5 {
        scene.step(arm::to_robot_units(&pan));
        let q = scene.joint_positions()[SHOULDER_PAN];
        assert!(((q - previous) - MAX_SPEED / FPS as f32).abs() < 1e-5, "{q}");
        previous = q;
    }

    // Lifting the stretched-out arm needs more torque than the servo has at the top speed: it
    // goes at the speed where its stall torque, less the back-EMF, carries the load.
    drive(&mut scene, &STRETCHED, 60);
    let load = gravity_load(&STRETCHED)[SHOULDER_LIFT].abs();
    scene.step(arm::to_robot_units(&UPRIGHT));
    let lifted = -scene.joint_positions()[SHOULDER_LIFT];
    let expected = NO_LOAD_SPEED * (1.0 - load / STALL_TORQUE) / FPS as f32;
    assert!(
        lifted < MAX_SPEED / FPS as f32 && (lifted - expected).abs() < 0.1 * expected,
        "lifted {lifted} rad in one frame, expected about {expected}"
    );
    assert_eq!(scene.joint_torques()[SHOULDER_LIFT], -STALL_TORQUE);

    // Through a whole expert episode no joint outruns the top speed.
    let outcome = run_expert_episode(3, 400, fedvla_sim::ActionNoise::NONE);
    for pair in outcome.states.windows(2) {
        let (from, to) = (arm::from_robot_units(&pair[0]), arm::from_robot_units(&pair[1]));
        for i in 0..JOINT_COUNT {
            assert!(
                (to[i] - from[i]).abs() <= MAX_SPEED / FPS as f32 + 1e-5,
                "joint {i}: {} rad in one frame",
                to[i] - from[i]
            );
        }
    }
}
