//! RGB images (HWC, u8) and SmolVLA's resize-with-pad to the policy's input size.

use crate::error::{DataError, Result};

/// An 8-bit RGB image, height x width x 3 (HWC), row-major.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RgbImage {
    pub width: u32,
    pub height: u32,
    pub data: Vec<u8>,
}

impl RgbImage {
    pub fn new(width: u32, height: u32, data: Vec<u8>) -> Result<Self> {
        if data.len() != width as usize * height as usize * 3 {
            return Err(DataError::InvalidInput(format!(
                "{width}x{height} RGB image needs {} bytes, got {}",
                width * height * 3,
                data.len()
            )));
        }
        Ok(Self { width, height, data })
    }

    /// Mean absolute difference per channel value, in 0..255 units.
    pub fn mean_abs_diff(&self, other: &RgbImage) -> f64 {
        let sum: u64 = self.data.iter().zip(&other.data).map(|(a, b)| u64::from(a.abs_diff(*b))).sum();
        sum as f64 / self.data.len().max(1) as f64
    }

    /// SmolVLA's `resize_with_pad`: scale by `max(W/width, H/height)` keeping the aspect ratio (bilinear,
    /// align_corners=false, no antialias, as torch's `interpolate`), then pad with black on the left and
    /// top only. Done once on u8 here instead of on floats in every training step, so values can
    /// differ from LeRobot's by rounding (at most 0.5/255).
    ///
    /// This mirrors `fedvla_policy::batch::prepare_image` (minus its final `x·2 − 1`), which works on
    /// f32 tensors; this crate must not depend on the policy (burn), so the two are kept in step by
    /// testing both against the same torch reference values.
    pub fn resized_with_pad(&self, width: u32, height: u32) -> RgbImage {
        let ratio = (f64::from(self.width) / f64::from(width)).max(f64::from(self.height) / f64::from(height));
        let scaled_w = ((f64::from(self.width) / ratio) as u32).clamp(1, width);
        let scaled_h = ((f64::from(self.height) / ratio) as u32).clamp(1, height);
        let scaled = self.resized_bilinear(scaled_w, scaled_h);
        let (pad_x, pad_y) = ((width - scaled_w) as usize, (height - scaled_h) as usize);
        let mut data = vec![0u8; width as usize * height as usize * 3];
        for y in 0..scaled_h as usize {
            let src = &scaled.data[y * scaled_w as usize * 3..(y + 1) * scaled_w as usize * 3];
            let start = ((y + pad_y) * width as usize + pad_x) * 3;
            data[start..start + src.len()].copy_from_slice(src);
        }
        RgbImage { width, height, data }
    }

    /// Bilinear resize with torch's `align_corners=false` source coordinates, rounded to u8; the u8
    /// counterpart of `fedvla_policy::batch::resize_bilinear`.
    pub fn resized_bilinear(&self, width: u32, height: u32) -> RgbImage {
        if (width, height) == (self.width, self.height) {
            return self.clone();
        }
        let taps = |out: u32, input: u32| -> Vec<(usize, usize, f32)> {
            let scale = f64::from(input) / f64::from(out);
            (0..out)
                .map(|o| {
                    let src = ((f64::from(o) + 0.5) * scale - 0.5).max(0.0);
                    let i0 = (src.floor() as usize).min(input as usize - 1);
                    let i1 = (i0 + 1).min(input as usize - 1);
                    (i0, i1, (src - i0 as f64) as f32)
                })
                .collect()
        };
        let (xs, ys) = (taps(width, self.width), taps(height, self.height));
        let sw = self.width as usize;
        let mut data = Vec::with_capacity(width as usize * height as usize * 3);
        for &(y0, y1, fy) in &ys {
            for &(x0, x1, fx) in &xs {
                for c in 0..3 {
                    let p = |x: usize, y: usize| f32::from(self.data[(y * sw + x) * 3 + c]);
                    let top = p(x0, y0) + (p(x1, y0) - p(x0, y0)) * fx;
                    let bottom = p(x0, y1) + (p(x1, y1) - p(x0, y1)) * fx;
                    data.push((top + (bottom - top) * fy).round().clamp(0.0, 255.0) as u8);
                }
            }
        }
        RgbImage { width, height, data }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn wide_image_is_padded_on_top() {
        // 480x640 -> 384x512 content, 128 black rows on top (SmolVLA's layout).
        let image = RgbImage::new(640, 480, vec![200; 640 * 480 * 3]).expect("valid");
        let out = image.resized_with_pad(512, 512);
        let row = |y: usize| &out.data[y * 512 * 3..(y + 1) * 512 * 3];
        assert!(row(127).iter().all(|&v| v == 0));
        assert!(row(128).iter().all(|&v| v == 200));
        assert!(row(511).iter().all(|&v| v == 200));
    }

    #[test]
    fn bilinear_upsample_matches_torch() {
        // The policy's reference scaled by 100 to stay exact in u8:
        // torch F.interpolate([[0., 1.]], size=(1, 4), mode="bilinear", align_corners=False) = [0, .25, .75, 1]
        let image = RgbImage::new(2, 1, vec![0, 0, 0, 100, 100, 100]).expect("valid");
        let out = image.resized_bilinear(4, 1);
        let red: Vec<u8> = out.data.chunks(3).map(|p| p[0]).collect();
        assert_eq!(red, vec![0, 25, 75, 100]);
    }

    #[test]
    fn resize_with_pad_pads_left_and_top_like_the_policy() {
        // The policy's case: a 2x4 (HxW) image into 4x4 keeps its 2x4 content under two rows of padding.
        let out = RgbImage::new(4, 2, vec![255; 4 * 2 * 3]).expect("valid").resized_with_pad(4, 4);
        assert!(out.data[..4 * 2 * 3].iter().all(|&v| v == 0));
        assert!(out.data[4 * 2 * 3..].iter().all(|&v| v == 255));
    }

    #[test]
    fn downsample_with_pad_matches_torch() {
        // 3x6 (HxW) into 4x4: ratio 1.5, content 2x4 under two padding rows. torch 2.14:
        // F.interpolate(img, size=(2, 4), mode="bilinear", align_corners=False) =
        // [[54.6875, 80.9375, 140.9375, 82.8125], [177.5, 91.25, 70.625, 80.0]]
        let grey: [u8; 18] = [10, 200, 30, 90, 250, 0, 60, 5, 140, 220, 35, 180, 255, 120, 75, 15, 100, 45];
        let image = RgbImage::new(6, 3, grey.iter().flat_map(|&v| [v; 3]).collect()).expect("valid");
        let out = image.resized_with_pad(4, 4);
        let red: Vec<u8> = out.data.chunks(3).map(|p| p[0]).collect();
        #[rustfmt::skip]
        assert_eq!(red, vec![
            0, 0, 0, 0,
            0, 0, 0, 0,
            55, 81, 141, 83,
            178, 91, 71, 80,
        ]);
    }
}
