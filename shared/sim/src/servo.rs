//! Position-controlled servo model (Feetech STS3215 as on the SO-100). Rapier ignores the
//! published effort and velocity limits, so the servo is modelled here as a saturated
//! controller driving a geared DC motor: it asks for the torque that moves its joint towards
//! the goal at up to [`MAX_SPEED`] while holding the joint's load (gravity, computed by the
//! scene), and gets no more than its motor gives at that speed. Short of torque, the joint moves
//! slower than asked, stalls where the load equals the servo's torque, and is pushed back when
//! the load exceeds it.
//!
//! The motor follows the DC motor's torque-speed line: at full drive it gives its stall torque
//! at standstill and nothing at its no-load speed, so moving at a speed costs torque in
//! proportion (back-EMF). Inertia is left out: the joint is at once at the speed where drive and
//! load balance, where the real arm takes a few hundredths of a second to get there (link
//! inertia over the back-EMF damping: about 0.06 s for the stretched arm's shoulder).

/// Stall torque of the STS3215, N·m: 19.5 kg·cm at 7.4 V for the 7.4 V, 1:345 version (C001)
/// that the SO-100 follower's bill of materials lists for all six joints. The 12 V version
/// gives about 30 kg·cm (2.9 N·m).
pub const STALL_TORQUE: f32 = 1.9;
/// No-load speed of the STS3215 (7.4 V, 1:345) at 7.4 V, rad/s: 0.222 s per 60 degrees.
pub const NO_LOAD_SPEED: f32 = 4.7;
/// Top speed the position loop asks for, rad/s. It is below the no-load speed, so a lightly
/// loaded joint keeps to it and a heavily loaded one falls behind.
pub const MAX_SPEED: f32 = 4.0;

/// One servo's state: where it is, where it is told to go, its torque limit, and the torque it
/// drives with.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Servo {
    /// Measured position, radians.
    pub position: f32,
    /// Goal position, radians (already clamped to the joint limits).
    pub goal: f32,
    /// Torque limit, N·m: the motor's torque at standstill and full drive.
    pub stall_torque: f32,
    /// Torque the servo drives its joint with in the last step, N·m, positive along the joint
    /// axis: the load it holds plus what moving at its speed costs the motor (back-EMF),
    /// saturated at `stall_torque`. Holding still, it equals the load; the real servo reports
    /// it as its load (drive duty).
    pub torque: f32,
}

impl Servo {
    /// An STS3215 at rest at `position`.
    pub fn new(position: f32) -> Self {
        Self { position, goal: position, stall_torque: STALL_TORQUE, torque: 0.0 }
    }

    /// Moves towards the goal for `dt` seconds while carrying `load` (N·m about the joint axis,
    /// positive along it: the torque needed to hold the joint still). When `blocked` is the
    /// direction (+1 or -1) in which an obstacle stops the joint, it moves no further that way,
    /// and its position error keeps its drive saturated against the obstacle.
    pub fn advance(&mut self, dt: f32, load: f32, blocked: Option<f32>) {
        // Torque the motor loses per rad/s of speed at full drive (its back-EMF).
        let back_emf = self.stall_torque / NO_LOAD_SPEED;
        let wanted = ((self.goal - self.position) / dt).clamp(-MAX_SPEED, MAX_SPEED);
        let needed = load + back_emf * wanted;
        let drive = needed.clamp(-self.stall_torque, self.stall_torque);
        // On the torque-speed line: the speed at which this drive balances the load.
        let speed = wanted - (needed - drive) / back_emf;
        match blocked {
            Some(direction) if speed * direction > 0.0 => {
                self.torque = direction * self.stall_torque;
            }
            _ => {
                self.torque = drive;
                self.position += speed * dt;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const DT: f32 = 0.01;

    #[test]
    fn unloaded_servo_runs_at_its_top_speed_and_stops_at_goal() {
        let mut servo = Servo::new(0.0);
        servo.goal = 1.0;
        servo.advance(DT, 0.0, None);
        assert!((servo.position - MAX_SPEED * DT).abs() < 1e-6);
        // Running at top speed costs the motor its back-EMF at that speed.
        let expected = STALL_TORQUE * MAX_SPEED / NO_LOAD_SPEED;
        assert!((servo.torque - expected).abs() < 1e-5, "{}", servo.torque);
        for _ in 0..30 {
            servo.advance(DT, 0.0, None);
        }
        assert_eq!(servo.position, 1.0);
        assert_eq!(servo.torque, 0.0);
    }

    #[test]
    fn load_within_the_limit_is_held_at_the_goal() {
        let mut servo = Servo::new(0.5);
        for _ in 0..10 {
            servo.advance(DT, -1.2, None);
        }
        assert_eq!(servo.position, 0.5);
        assert_eq!(servo.torque, -1.2);
    }

    #[test]
    fn lifting_a_heavy_load_is_slower_than_the_top_speed() {
        let mut servo = Servo::new(0.0);
        servo.goal = 1.0;
        let load = 1.4;
        servo.advance(DT, load, None);
        // Full drive, on the torque-speed line where it balances the load.
        let speed = NO_LOAD_SPEED * (1.0 - load / STALL_TORQUE);
        assert!((servo.position - speed * DT).abs() < 1e-6, "{}", servo.position);
        assert_eq!(servo.torque, STALL_TORQUE);
    }

    #[test]
    fn overloaded_servo_is_back_driven() {
        let mut servo = Servo::new(0.0);
        servo.advance(DT, 2.0 * STALL_TORQUE, None);
        assert!((servo.position + NO_LOAD_SPEED * DT).abs() < 1e-6, "{}", servo.position);
        assert_eq!(servo.torque, STALL_TORQUE);
    }

    #[test]
    fn blocked_servo_pushes_at_full_torque_but_can_back_off() {
        let mut servo = Servo::new(0.5);
        servo.goal = 0.0;
        servo.advance(DT, 0.0, Some(-1.0));
        assert_eq!(servo.position, 0.5);
        assert_eq!(servo.torque, -STALL_TORQUE);
        servo.goal = 1.0;
        servo.advance(DT, 0.0, Some(-1.0));
        assert!((servo.position - (0.5 + MAX_SPEED * DT)).abs() < 1e-6);
    }
}
