//! AV1 mp4 decoding (feature `av1`, the system libdav1d), against clips encoded here by Debian's ffmpeg with
//! libsvtav1 exactly as LeRobot encodes its datasets (yuv420p, GOP 2): every frame within codec tolerance of the
//! frame that went in, looked up by timestamp. Skipped with a message when ffmpeg is missing, unless
//! FEDVLA_REQUIRE_AV1=1 (tests/run.sh), which makes that a failure.
#![cfg(feature = "av1")]

mod common;

use std::path::Path;
use std::process::Command;

use fedvla_data::DirFiles;
use fedvla_data::video::{FrameSource, Mp4Frames, RgbImage, VideoFile};

const W: u32 = 96;
const H: u32 = 64;
const FPS: u32 = 30;
const FRAMES: u32 = 12;

/// Smooth gradients with a square moving across them: the kind of content a codec keeps well, so a real
/// decoding error shows as a large difference.
fn frame(i: u32) -> RgbImage {
    let mut data = Vec::with_capacity((W * H * 3) as usize);
    for y in 0..H {
        for x in 0..W {
            let in_square = (x as i32 - (10 + 5 * i) as i32).abs() < 8 && (y as i32 - 32).abs() < 8;
            let (r, g, b) = if in_square { (230, 40, 30) } else { ((x * 255 / W) as u8, (y * 255 / H) as u8, 128u8) };
            data.extend([r, g, b]);
        }
    }
    RgbImage { width: W, height: H, data }
}

fn ffmpeg_missing() -> bool {
    let missing = Command::new("ffmpeg").arg("-version").output().is_err();
    if missing && std::env::var("FEDVLA_REQUIRE_AV1").is_ok_and(|v| v == "1") {
        panic!("FEDVLA_REQUIRE_AV1=1 but ffmpeg (Debian package ffmpeg) is not installed");
    }
    missing
}

fn encode_av1(frames: &[RgbImage], out: &Path) {
    let raw = out.with_extension("rgb");
    std::fs::write(&raw, frames.iter().flat_map(|f| f.data.iter().copied()).collect::<Vec<u8>>()).unwrap();
    let status = Command::new("ffmpeg")
        // SVT-AV1 prints its configuration at info level whatever ffmpeg's log level says.
        .env("SVT_LOG", "1")
        .args(["-hide_banner", "-loglevel", "error", "-y", "-f", "rawvideo", "-pix_fmt", "rgb24"])
        .args(["-s", &format!("{W}x{H}"), "-r", &FPS.to_string(), "-i"])
        .arg(&raw)
        .args(["-c:v", "libsvtav1", "-g", "2", "-crf", "30", "-pix_fmt", "yuv420p"])
        .arg(out)
        .status()
        .expect("ffmpeg runs");
    assert!(status.success(), "ffmpeg failed to encode {}", out.display());
}

#[test]
fn av1_frames_decode_within_codec_tolerance_by_timestamp() {
    if ffmpeg_missing() {
        eprintln!("SKIPPED: ffmpeg is not installed (Debian package ffmpeg) to encode the AV1 test clip");
        return;
    }
    let path = common::temp_dir("av1").join("camera.mp4");
    let originals: Vec<RgbImage> = (0..FRAMES).map(frame).collect();
    encode_av1(&originals, &path);

    let files = std::sync::Arc::new(DirFiles::new(path.parent().unwrap()));
    let video = VideoFile::open(&*files, Path::new("camera.mp4")).unwrap();
    assert_eq!(video.frame_count(), FRAMES as usize);
    // Out of order and repeated, as a batch of delta_timestamps asks.
    let order = [7u32, 0, 11, 3, 3, 10];
    let timestamps: Vec<f64> = order.iter().map(|&i| f64::from(i) / f64::from(FPS)).collect();
    let decoded = Mp4Frames::new(files).frames_at(Path::new("camera.mp4"), &timestamps, 1e-4).unwrap();
    for (&i, image) in order.iter().zip(&decoded) {
        assert_eq!((image.width, image.height), (W, H));
        let original = &originals[i as usize];
        let mean_abs = image.data.iter().zip(&original.data).map(|(a, b)| f64::from(a.abs_diff(*b))).sum::<f64>()
            / image.data.len() as f64;
        // 4:2:0 chroma subsampling blurs the square's edges; anything beyond a few levels is a decoding error.
        assert!(mean_abs < 6.0, "frame {i}: mean absolute difference {mean_abs:.2} of 255");
        eprintln!("frame {i}: mean absolute difference {mean_abs:.2}/255");
    }
    assert!(video.samples_at(&[1.0], 1e-4).is_err(), "a timestamp past the clip is refused");
}
