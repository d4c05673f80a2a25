//! Procedural SO-100-shaped episodes (smooth joint trajectories, gradient images with a moving square):
//! small, deterministic data for tests, demos and LeRobot compatibility checks, made without the sim.

use crate::image::RgbImage;
use crate::writer::{CameraSpec, Episode, Frame};

/// Episode `episode` of `frames` frames for `cameras`, with `task`; the same arguments give the same data.
pub fn episode(episode: usize, frames: usize, cameras: &[CameraSpec], task: &str) -> Episode {
    let frames = (0..frames)
        .map(|f| {
            let t = f as f32 / 30.0;
            let e = episode as f32;
            let state: Vec<f32> = (0..6)
                .map(|j| {
                    let j = j as f32;
                    10.0 * (j - 2.5) + 20.0 * (2.0 * std::f32::consts::PI * 0.7 * t + j + 0.3 * e).sin()
                })
                .collect();
            let action: Vec<f32> =
                state.iter().enumerate().map(|(j, s)| s + 2.0 * (t * 3.0 + j as f32).cos()).collect();
            let images =
                cameras.iter().enumerate().map(|(c, cam)| image(cam.width, cam.height, episode, f, c)).collect();
            Frame { state, action, images }
        })
        .collect();
    Episode { task: task.to_string(), frames }
}

/// A smooth colour gradient that drifts with the frame, plus a dark square moving across it.
pub fn image(width: u32, height: u32, episode: usize, frame: usize, camera: usize) -> RgbImage {
    let (w, h) = (width as usize, height as usize);
    let phase = 0.15 * frame as f32 + 0.9 * episode as f32 + 1.7 * camera as f32;
    let side = (w.min(h) / 4).max(1);
    let x0 = (frame * 3 + 11 * camera) % (w - side + 1);
    let y0 = (frame * 2 + 7 * episode) % (h - side + 1);
    let mut data = Vec::with_capacity(w * h * 3);
    for y in 0..h {
        for x in 0..w {
            let (xf, yf) = (x as f32 / (w.max(2) - 1) as f32, y as f32 / (h.max(2) - 1) as f32);
            let tau = 2.0 * std::f32::consts::PI;
            let mut rgb = [
                0.5 + 0.4 * (tau * (xf + 0.05 * frame as f32) + phase).sin(),
                0.3 + 0.5 * yf,
                0.5 + 0.4 * (tau * (xf + yf) - phase).cos(),
            ];
            if (x0..x0 + side).contains(&x) && (y0..y0 + side).contains(&y) {
                for v in &mut rgb {
                    *v *= 0.2;
                }
            }
            data.extend(rgb.iter().map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8));
        }
    }
    RgbImage { width, height, data }
}
