//! Primitive shapes (boxes and cylinders) shared by the physics colliders and the renderer,
//! so that what the cameras see is exactly what collides.

use rapier3d::math::{Pose, Rot3, Vec3};
use rapier3d::prelude::{ColliderBuilder, SharedShape};

/// An RGB colour, each channel in 0..=1.
pub type Rgb = [f32; 3];

/// The shape of one primitive, in metres, centred on its local origin.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Primitive {
    /// A box with the given half extents along local x, y, z.
    Cuboid { half: Vec3 },
    /// A cylinder whose axis is local y (rapier's convention).
    Cylinder { half_height: f32, radius: f32 },
}

/// A primitive placed in the frame of the body it belongs to, with its colour.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Part {
    pub primitive: Primitive,
    /// Pose of the primitive in the body frame.
    pub local: Pose,
    pub color: Rgb,
}

impl Part {
    pub fn cuboid(center: Vec3, half: Vec3, color: Rgb) -> Self {
        Self { primitive: Primitive::Cuboid { half }, local: Pose::from_translation(center), color }
    }

    /// A box of square-ish cross-section (`half_width` along local x, `half_depth` along the
    /// third axis) spanning the segment `from -> to`: how link bones are drawn between joints.
    pub fn segment(from: Vec3, to: Vec3, half_width: f32, half_depth: f32, color: Rgb) -> Self {
        let along = to - from;
        let rotation = Rot3::from_rotation_arc(Vec3::Y, along.normalize());
        let half = Vec3::new(half_width, along.length() * 0.5, half_depth);
        Self { primitive: Primitive::Cuboid { half }, local: Pose::from_parts((from + to) * 0.5, rotation), color }
    }

    pub fn cylinder(center: Vec3, rotation: Rot3, half_height: f32, radius: f32, color: Rgb) -> Self {
        Self {
            primitive: Primitive::Cylinder { half_height, radius },
            local: Pose::from_parts(center, rotation),
            color,
        }
    }

    /// A rapier collider builder for this part, positioned relative to its parent body.
    pub fn collider(&self) -> ColliderBuilder {
        let shape = match self.primitive {
            Primitive::Cuboid { half } => SharedShape::cuboid(half.x, half.y, half.z),
            Primitive::Cylinder { half_height, radius } => SharedShape::cylinder(half_height, radius),
        };
        ColliderBuilder::new(shape).position(self.local)
    }
}
