//! RGB <-> YUV 4:2:0 conversion with BT.601 limited-range coefficients.
//!
//! BT.601 limited range is what FFmpeg (and so PyAV inside LeRobot) assumes for untagged SD-sized
//! yuv420p video, and what the H.264 encoder signals in its VUI, so both sides agree on colours.

use crate::image::RgbImage;

/// Planar I420: the Y plane (w*h), then U and V planes ((w/2)*(h/2) each).
pub fn rgb_to_i420(image: &RgbImage) -> Vec<u8> {
    let (w, h) = (image.width as usize, image.height as usize);
    let (cw, ch) = (w / 2, h / 2);
    let mut out = vec![0u8; w * h + 2 * cw * ch];
    let px = |x: usize, y: usize| {
        let i = (y * w + x) * 3;
        (f32::from(image.data[i]), f32::from(image.data[i + 1]), f32::from(image.data[i + 2]))
    };
    for y in 0..h {
        for x in 0..w {
            let (r, g, b) = px(x, y);
            out[y * w + x] = clamp_u8(16.0 + 0.256_788 * r + 0.504_129 * g + 0.097_906 * b);
        }
    }
    let (u_plane, v_plane) = out[w * h..].split_at_mut(cw * ch);
    for cy in 0..ch {
        for cx in 0..cw {
            let (mut r, mut g, mut b) = (0.0, 0.0, 0.0);
            for (dx, dy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                let p = px(2 * cx + dx, 2 * cy + dy);
                r += p.0 / 4.0;
                g += p.1 / 4.0;
                b += p.2 / 4.0;
            }
            u_plane[cy * cw + cx] = clamp_u8(128.0 - 0.148_223 * r - 0.290_993 * g + 0.439_216 * b);
            v_plane[cy * cw + cx] = clamp_u8(128.0 + 0.439_216 * r - 0.367_788 * g - 0.071_427 * b);
        }
    }
    out
}

/// Converts 8-bit 4:2:0 planes (with strides) to packed RGB; chroma is upsampled by repetition.
pub fn yuv420_to_rgb(
    width: usize,
    height: usize,
    planes: (&[u8], &[u8], &[u8]),
    strides: (usize, usize, usize),
) -> RgbImage {
    let (yp, up, vp) = planes;
    let mut data = vec![0u8; width * height * 3];
    for y in 0..height {
        for x in 0..width {
            let luma = 1.164_383 * (f32::from(yp[y * strides.0 + x]) - 16.0);
            let cb = f32::from(up[(y / 2) * strides.1 + x / 2]) - 128.0;
            let cr = f32::from(vp[(y / 2) * strides.2 + x / 2]) - 128.0;
            let o = (y * width + x) * 3;
            data[o] = clamp_u8(luma + 1.596_027 * cr);
            data[o + 1] = clamp_u8(luma - 0.391_762 * cb - 0.812_968 * cr);
            data[o + 2] = clamp_u8(luma + 2.017_232 * cb);
        }
    }
    RgbImage { width: width as u32, height: height as u32, data }
}

fn clamp_u8(v: f32) -> u8 {
    v.round().clamp(0.0, 255.0) as u8
}
