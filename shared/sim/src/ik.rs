//! Inverse kinematics of the SO-100's five arm joints by damped least squares: joint angles
//! that put a point of the gripper frame at a target position with a target orientation.

use crate::arm::{self, GRIPPER_LINK, JOINT_COUNT};
use rapier3d::math::{Pose, Rot3, Vec3};

/// Joints the solver moves: all but the gripper jaw.
const ARM_JOINTS: usize = JOINT_COUNT - 1;
/// Metres of position error that weigh as much as one radian of orientation error.
const ORIENTATION_WEIGHT: f32 = 0.1;
/// Damping (metres): keeps steps bounded near singularities (arm stretched or folded).
const DAMPING: f32 = 0.005;
/// Largest change of one joint per iteration, radians.
const MAX_STEP: f32 = 0.2;
const ITERATIONS: usize = 60;
/// Error norm (metres, weighted radians) under which the solution is good enough.
const TOLERANCE: f32 = 1e-4;
/// Finite-difference step for the Jacobian, radians.
const DELTA: f32 = 1e-3;

/// A desired pose of the gripper: where `point` (gripper frame) should be and how the
/// gripper frame should be turned, world frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GripperTarget {
    pub point: Vec3,
    pub position: Vec3,
    pub orientation: Rot3,
}

/// Pose error as a 6-vector: position (m) then weighted rotation vector.
fn error(base: Pose, q: &[f32; JOINT_COUNT], target: &GripperTarget) -> [f32; 6] {
    let gripper = arm::forward_kinematics(base, q)[GRIPPER_LINK];
    let position = target.position - gripper.transform_point(target.point);
    let mut turn = target.orientation * gripper.rotation.inverse();
    if turn.w < 0.0 {
        turn = -turn;
    }
    let rotation = turn.to_scaled_axis() * ORIENTATION_WEIGHT;
    [position.x, position.y, position.z, rotation.x, rotation.y, rotation.z]
}

/// Joint angles (radians) reaching `target`, starting the search from `start`; the gripper
/// joint is left as in `start` and every joint stays within its limits. Returns the best
/// angles found even when the target is out of reach.
pub fn solve(base: Pose, start: &[f32; JOINT_COUNT], target: &GripperTarget) -> [f32; JOINT_COUNT] {
    let mut q = arm::clamp_to_limits(start);
    for _ in 0..ITERATIONS {
        let e = error(base, &q, target);
        if norm(&e) < TOLERANCE {
            break;
        }
        // Jacobian of the error by finite differences; d(error)/dq = -J.
        let mut jacobian = [[0.0f32; ARM_JOINTS]; 6];
        for j in 0..ARM_JOINTS {
            let mut shifted = q;
            shifted[j] += DELTA;
            let e_shifted = error(base, &shifted, target);
            for r in 0..6 {
                jacobian[r][j] = (e[r] - e_shifted[r]) / DELTA;
            }
        }
        // (J^T J + lambda^2 I) dq = J^T e
        let mut normal = [[0.0f32; ARM_JOINTS]; ARM_JOINTS];
        let mut rhs = [0.0f32; ARM_JOINTS];
        for a in 0..ARM_JOINTS {
            for b in 0..ARM_JOINTS {
                normal[a][b] = (0..6).map(|r| jacobian[r][a] * jacobian[r][b]).sum();
            }
            normal[a][a] += DAMPING * DAMPING;
            rhs[a] = (0..6).map(|r| jacobian[r][a] * e[r]).sum();
        }
        let step = solve_linear(normal, rhs);
        for j in 0..ARM_JOINTS {
            q[j] += step[j].clamp(-MAX_STEP, MAX_STEP);
        }
        q = arm::clamp_to_limits(&q);
    }
    q
}

fn norm(v: &[f32]) -> f32 {
    v.iter().map(|x| x * x).sum::<f32>().sqrt()
}

/// Gaussian elimination with partial pivoting for the small symmetric positive system.
fn solve_linear<const N: usize>(mut a: [[f32; N]; N], mut b: [f32; N]) -> [f32; N] {
    for col in 0..N {
        let pivot = (col..N).max_by(|&i, &j| a[i][col].abs().total_cmp(&a[j][col].abs())).unwrap_or(col);
        a.swap(col, pivot);
        b.swap(col, pivot);
        for row in col + 1..N {
            let factor = a[row][col] / a[col][col];
            let pivot_row = a[col];
            for (entry, pivot_entry) in a[row].iter_mut().zip(pivot_row).skip(col) {
                *entry -= factor * pivot_entry;
            }
            b[row] -= factor * b[col];
        }
    }
    let mut x = [0.0; N];
    for row in (0..N).rev() {
        let sum: f32 = (row + 1..N).map(|k| a[row][k] * x[k]).sum();
        x[row] = (b[row] - sum) / a[row][row];
    }
    x
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::HOME;

    /// Remaining error of `q` against `target`: position (m) and orientation (rad).
    fn residual(base: Pose, q: &[f32; JOINT_COUNT], target: &GripperTarget) -> (f32, f32) {
        let e = error(base, q, target);
        let position = Vec3::new(e[0], e[1], e[2]).length();
        let orientation = Vec3::new(e[3], e[4], e[5]).length() / ORIENTATION_WEIGHT;
        (position, orientation)
    }

    #[test]
    fn reaches_a_pose_produced_by_forward_kinematics() {
        let goal_q = [0.4, -1.2, 1.9, 1.0, -1.2, 0.0];
        let gripper = arm::forward_kinematics(Pose::IDENTITY, &goal_q)[GRIPPER_LINK];
        let point = arm::grasp_point(0.012);
        let target = GripperTarget { point, position: gripper.transform_point(point), orientation: gripper.rotation };
        let q = solve(Pose::IDENTITY, &HOME, &target);
        let (position, orientation) = residual(Pose::IDENTITY, &q, &target);
        assert!(position < 1e-3 && orientation < 1e-2, "{position} m, {orientation} rad");
    }
}
