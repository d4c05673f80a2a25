//! Triangle meshes of the primitive shapes, for the software renderer.

use crate::shape::Primitive;
use rapier3d::math::Vec3;

/// Sides of the polygon approximating a cylinder's circle.
const CYLINDER_SIDES: usize = 16;

/// Triangles (three corners, counter-clockwise seen from outside) of a primitive in its own
/// frame, appended to `out`.
pub fn triangulate(primitive: &Primitive, out: &mut Vec<[Vec3; 3]>) {
    match *primitive {
        Primitive::Cuboid { half } => {
            let corner = |i: usize| {
                Vec3::new(
                    if i & 1 == 0 { -half.x } else { half.x },
                    if i & 2 == 0 { -half.y } else { half.y },
                    if i & 4 == 0 { -half.z } else { half.z },
                )
            };
            // Each face as a quad of corner indices, counter-clockwise from outside.
            const FACES: [[usize; 4]; 6] =
                [[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [2, 6, 7, 3], [0, 4, 6, 2], [1, 3, 7, 5]];
            for [a, b, c, d] in FACES {
                out.push([corner(a), corner(b), corner(c)]);
                out.push([corner(a), corner(c), corner(d)]);
            }
        }
        Primitive::Cylinder { half_height, radius } => {
            let rim = |k: usize, y: f32| {
                let angle = k as f32 * std::f32::consts::TAU / CYLINDER_SIDES as f32;
                Vec3::new(angle.cos() * radius, y, -angle.sin() * radius)
            };
            let top = Vec3::new(0.0, half_height, 0.0);
            let bottom = -top;
            for k in 0..CYLINDER_SIDES {
                let (a_top, b_top) = (rim(k, half_height), rim(k + 1, half_height));
                let (a_bottom, b_bottom) = (rim(k, -half_height), rim(k + 1, -half_height));
                out.push([a_bottom, b_bottom, b_top]);
                out.push([a_bottom, b_top, a_top]);
                out.push([top, a_top, b_top]);
                out.push([bottom, b_bottom, a_bottom]);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every triangle's normal must point away from the centre, or back-face culling would
    /// drop the visible side.
    #[test]
    fn triangles_face_outwards() {
        for primitive in [
            Primitive::Cuboid { half: Vec3::new(0.1, 0.2, 0.3) },
            Primitive::Cylinder { half_height: 0.1, radius: 0.2 },
        ] {
            let mut triangles = Vec::new();
            triangulate(&primitive, &mut triangles);
            for [a, b, c] in triangles {
                let normal = (b - a).cross(c - a);
                let centroid = (a + b + c) / 3.0;
                assert!(normal.dot(centroid) > 0.0, "{primitive:?}: {a:?} {b:?} {c:?}");
            }
        }
    }
}
