//! The two cameras of a typical SO-100 setup: a fixed camera above and in front of the table
//! ("top") and a camera on the gripper looking along the fingers ("wrist"). Their names are
//! the LeRobot image keys: `observation.images.top` and `observation.images.wrist`.

use crate::arm::GRIPPER_LINK;
use crate::scene::Scene;
use rapier3d::math::Vec3;

/// A camera of the scene.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Camera {
    Top,
    Wrist,
}

/// Where a camera is and how it looks, in world coordinates (metres, radians).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CameraView {
    pub eye: Vec3,
    /// Unit viewing direction.
    pub forward: Vec3,
    /// Unit vector pointing up in the image, orthogonal to `forward`.
    pub up: Vec3,
    /// Vertical field of view, radians.
    pub fov_y: f32,
}

impl CameraView {
    fn looking_at(eye: Vec3, target: Vec3, up_hint: Vec3, fov_y: f32) -> Self {
        let forward = (target - eye).normalize();
        let up = (up_hint - forward * up_hint.dot(forward)).normalize();
        Self { eye, forward, up, fov_y }
    }

    /// Unit vector pointing right in the image.
    pub fn right(&self) -> Vec3 {
        self.forward.cross(self.up)
    }
}

impl Camera {
    /// All cameras, in the order datasets list them.
    pub const ALL: [Camera; 2] = [Camera::Top, Camera::Wrist];

    /// The LeRobot key suffix: `observation.images.<name>`.
    pub fn name(self) -> &'static str {
        match self {
            Camera::Top => "top",
            Camera::Wrist => "wrist",
        }
    }

    /// The camera's current view; the wrist camera moves with the gripper.
    pub fn view(self, scene: &Scene) -> CameraView {
        match self {
            // In front of the arm, above the table, looking down at the workspace.
            Camera::Top => CameraView::looking_at(
                Vec3::new(0.0, -0.58, 0.42),
                Vec3::new(0.0, -0.14, 0.07),
                Vec3::Z,
                55f32.to_radians(),
            ),
            // Mounted on the gripper body beside the jaw servo, looking past the finger tips
            // (gripper frame: x closes the jaw, fingers point along -y).
            Camera::Wrist => {
                let gripper = scene.link_pose(GRIPPER_LINK);
                let eye = gripper.transform_point(Vec3::new(0.0, -0.03, 0.045));
                let target = gripper.transform_point(Vec3::new(0.0, -0.12, -0.01));
                let up = gripper.transform_vector(Vec3::Z);
                CameraView::looking_at(eye, target, up, 75f32.to_radians())
            }
        }
    }
}
