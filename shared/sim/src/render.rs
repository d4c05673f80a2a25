//! The software renderer: every camera image is drawn here by a triangle rasterizer with a
//! z-buffer and flat Lambert shading, on the CPU, so the same code runs headless natively and
//! in wasm32 (the browser blits the RGB buffer to a canvas). No shadows, no anti-aliasing.

use crate::camera::{Camera, CameraView};
use crate::mesh;
use crate::scene::Scene;
use crate::shape::Rgb;
use rapier3d::math::Vec3;

/// Colour behind everything (a light grey room), RGB.
const BACKGROUND: [u8; 3] = [186, 190, 196];
/// Direction towards the light (from above, front-left), normalised at use.
const LIGHT_TOWARDS: Vec3 = Vec3::new(-0.35, 0.45, 1.0);
/// Share of the light that reaches faces turned away from it.
const AMBIENT: f32 = 0.35;
/// Nearest distance drawn, metres (the wrist camera sits a few centimetres from the fingers).
const NEAR: f32 = 0.005;

/// Renders `camera`'s view of `scene` as RGB bytes, row-major, `height * width * 3` long
/// (HWC, as stored in LeRobot video frames).
pub fn render(scene: &Scene, camera: Camera, width: usize, height: usize) -> Vec<u8> {
    let mut rasterizer = Rasterizer::new(camera.view(scene), width, height);
    let light = LIGHT_TOWARDS.normalize();
    let mut local_triangles = Vec::new();
    for (body_pose, parts) in scene.visuals() {
        for part in parts {
            let pose = body_pose * part.local;
            local_triangles.clear();
            mesh::triangulate(&part.primitive, &mut local_triangles);
            for triangle in &local_triangles {
                let world = triangle.map(|corner| pose.transform_point(corner));
                let normal = (world[1] - world[0]).cross(world[2] - world[0]).normalize_or_zero();
                let brightness = AMBIENT + (1.0 - AMBIENT) * normal.dot(light).max(0.0);
                rasterizer.draw(world, normal, shade(part.color, brightness));
            }
        }
    }
    rasterizer.into_rgb()
}

fn shade(color: Rgb, brightness: f32) -> [u8; 3] {
    color.map(|channel| (channel * brightness * 255.0).clamp(0.0, 255.0) as u8)
}

/// A corner after projection: pixel coordinates and inverse depth (affine in screen space,
/// hence interpolated linearly; larger is nearer).
#[derive(Clone, Copy)]
struct ScreenVertex {
    x: f32,
    y: f32,
    inv_depth: f32,
}

struct Rasterizer {
    view: CameraView,
    right: Vec3,
    width: usize,
    height: usize,
    /// Focal length in pixels.
    focal: f32,
    color: Vec<u8>,
    inv_depth: Vec<f32>,
}

impl Rasterizer {
    fn new(view: CameraView, width: usize, height: usize) -> Self {
        let mut color = Vec::with_capacity(width * height * 3);
        for _ in 0..width * height {
            color.extend_from_slice(&BACKGROUND);
        }
        Self {
            right: view.right(),
            view,
            width,
            height,
            focal: height as f32 * 0.5 / (view.fov_y * 0.5).tan(),
            color,
            inv_depth: vec![0.0; width * height],
        }
    }

    fn into_rgb(self) -> Vec<u8> {
        self.color
    }

    /// Draws one world-space triangle with outward `normal` in a flat colour.
    fn draw(&mut self, world: [Vec3; 3], normal: Vec3, color: [u8; 3]) {
        // Back-face culling: closed primitives never show their inside.
        if normal.dot(world[0] - self.view.eye) >= 0.0 {
            return;
        }
        let camera = world.map(|p| {
            let d = p - self.view.eye;
            Vec3::new(d.dot(self.right), d.dot(self.view.up), d.dot(self.view.forward))
        });
        if camera.iter().all(|p| p.z >= NEAR) {
            let screen = camera.map(|p| self.project(p));
            self.fill(screen, color);
            return;
        }
        // Clip against the near plane (Sutherland-Hodgman on one plane), then fan out.
        let mut clipped: Vec<Vec3> = Vec::with_capacity(4);
        for i in 0..3 {
            let (a, b) = (camera[i], camera[(i + 1) % 3]);
            if a.z >= NEAR {
                clipped.push(a);
            }
            if (a.z >= NEAR) != (b.z >= NEAR) {
                let t = (NEAR - a.z) / (b.z - a.z);
                clipped.push(a + (b - a) * t);
            }
        }
        for i in 1..clipped.len().saturating_sub(1) {
            let screen = [clipped[0], clipped[i], clipped[i + 1]].map(|p| self.project(p));
            self.fill(screen, color);
        }
    }

    fn project(&self, p: Vec3) -> ScreenVertex {
        let inv_depth = 1.0 / p.z;
        ScreenVertex {
            x: self.width as f32 * 0.5 + self.focal * p.x * inv_depth,
            y: self.height as f32 * 0.5 - self.focal * p.y * inv_depth,
            inv_depth,
        }
    }

    /// Fills the pixels whose centres fall inside the triangle and are nearer than what is
    /// already drawn there.
    fn fill(&mut self, [a, b, c]: [ScreenVertex; 3], color: [u8; 3]) {
        let area = (b.x - a.x) * (c.y - a.y) - (b.y - a.y) * (c.x - a.x);
        if area.abs() < 1e-12 {
            return;
        }
        let min_x = a.x.min(b.x).min(c.x).floor().max(0.0) as usize;
        let max_x = (a.x.max(b.x).max(c.x).ceil() as isize).min(self.width as isize - 1);
        let min_y = a.y.min(b.y).min(c.y).floor().max(0.0) as usize;
        let max_y = (a.y.max(b.y).max(c.y).ceil() as isize).min(self.height as isize - 1);
        if max_x < min_x as isize || max_y < min_y as isize {
            return;
        }
        let (max_x, max_y) = (max_x as usize, max_y as usize);
        // Edge functions, normalised so that all three are positive inside whatever the winding.
        let inv_area = 1.0 / area;
        let edge = |p: ScreenVertex, q: ScreenVertex| {
            let dx = (p.y - q.y) * inv_area;
            let dy = (q.x - p.x) * inv_area;
            (dx, dy, -(p.x * dx + p.y * dy))
        };
        let edges = [edge(b, c), edge(c, a), edge(a, b)];
        let depth_dx = edges[0].0 * a.inv_depth + edges[1].0 * b.inv_depth + edges[2].0 * c.inv_depth;
        for y in min_y..=max_y {
            let py = y as f32 + 0.5;
            let px = min_x as f32 + 0.5;
            let mut w = edges.map(|(dx, dy, c0)| dx * px + dy * py + c0);
            let mut depth = w[0] * a.inv_depth + w[1] * b.inv_depth + w[2] * c.inv_depth;
            let row = y * self.width;
            for x in min_x..=max_x {
                if w[0] >= 0.0 && w[1] >= 0.0 && w[2] >= 0.0 && depth > self.inv_depth[row + x] {
                    self.inv_depth[row + x] = depth;
                    self.color[(row + x) * 3..(row + x) * 3 + 3].copy_from_slice(&color);
                }
                for (wi, (dx, _, _)) in w.iter_mut().zip(&edges) {
                    *wi += dx;
                }
                depth += depth_dx;
            }
        }
    }
}
