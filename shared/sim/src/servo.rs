//! Position-controlled servo model (Feetech STS3215 as on the SO-100). Rapier ignores the
//! published effort/velocity limits, so the servo is modelled here: the measured position
//! moves towards the goal at no more than the servo's top speed, and a servo whose load
//! exceeds its torque (reported by the scene as `stalled`) stops advancing.

/// Top speed of the arm servos, rad/s (STS3215 no-load speed is about 0.16 s per 60 degrees
/// at 12 V; LeRobot's acceleration settings keep the real arm below that).
pub const ARM_MAX_SPEED: f32 = 4.0;
/// Top speed of the gripper servo, rad/s.
pub const GRIPPER_MAX_SPEED: f32 = 6.0;

/// One servo's state: where it is, where it is told to go, and how fast it may move.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Servo {
    /// Measured position, radians.
    pub position: f32,
    /// Goal position, radians (already clamped to the joint limits).
    pub goal: f32,
    /// Top speed, rad/s.
    pub max_speed: f32,
}

impl Servo {
    pub fn new(position: f32, max_speed: f32) -> Self {
        Self {
            position,
            goal: position,
            max_speed,
        }
    }

    /// Moves towards the goal for `dt` seconds. A stalled servo holds its position rather than
    /// moving further in the `stall_direction` (the direction in which its torque is
    /// saturated); it may still back off.
    pub fn advance(&mut self, dt: f32, stall_direction: Option<f32>) {
        let max_step = self.max_speed * dt;
        let step = (self.goal - self.position).clamp(-max_step, max_step);
        let pushes_into_stall = stall_direction.is_some_and(|dir| step * dir > 0.0);
        if !pushes_into_stall {
            self.position += step;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn servo_is_rate_limited_and_stops_at_goal() {
        let mut servo = Servo::new(0.0, 2.0);
        servo.goal = 1.0;
        servo.advance(0.1, None);
        assert!((servo.position - 0.2).abs() < 1e-6);
        for _ in 0..10 {
            servo.advance(0.1, None);
        }
        assert_eq!(servo.position, 1.0);
    }

    #[test]
    fn stalled_servo_holds_but_can_back_off() {
        let mut servo = Servo::new(0.5, 2.0);
        servo.goal = 0.0;
        servo.advance(0.1, Some(-1.0));
        assert_eq!(servo.position, 0.5);
        servo.goal = 1.0;
        servo.advance(0.1, Some(-1.0));
        assert!((servo.position - 0.7).abs() < 1e-6);
    }
}
