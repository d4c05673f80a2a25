//! Camera video: RGB frames, encoding a camera's episodes into one H.264 mp4 (feature `io`), and frames at given
//! timestamps through a [`FrameSource`]: decoded from H.264 or (feature `av1`) AV1 mp4 files natively
//! ([`Mp4Frames`], feature `io`), or handed in already decoded ([`DecodedFrames`]: a browser page decodes with
//! WebCodecs). Both find samples by time and plan which to decode the same way ([`VideoFile`]).

#[cfg(feature = "av1")]
mod av1;
#[cfg(feature = "io")]
mod color;
#[cfg(feature = "io")]
mod h264;
pub mod mp4;

use std::collections::BTreeMap;
use std::ops::Range;
use std::path::{Path, PathBuf};

use crate::error::{DataError, Result};
use crate::files::DatasetFiles;
pub use crate::image::RgbImage;
use mp4::Mp4Track;
#[cfg(feature = "io")]
use mp4::{Mp4Writer, TrackCodec};

/// Where a dataset's camera frames come from.
pub trait FrameSource: Send + Sync {
    /// The frames of video `path` (relative to the dataset's root) presented at `timestamps_s` (seconds from the
    /// file's start, each within `tolerance_s` of a frame), in the given order.
    fn frames_at(&self, path: &Path, timestamps_s: &[f64], tolerance_s: f64) -> Result<Vec<RgbImage>>;
}

/// How camera streams are encoded.
#[cfg(feature = "io")]
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct VideoEncoding {
    /// Upper bound of the H.264 quantiser (0 best .. 51 worst).
    pub qp_max: u8,
    /// Key-frame interval in frames: short keeps random access (LeRobot's training reads) cheap.
    pub gop: u32,
}

#[cfg(feature = "io")]
impl Default for VideoEncoding {
    fn default() -> Self {
        Self { qp_max: 22, gop: 10 }
    }
}

/// Encodes one camera's frames into one mp4 file (many episodes back to back).
#[cfg(feature = "io")]
pub struct CameraVideoWriter {
    encoder: h264::H264Encoder,
    muxer: Mp4Writer,
}

#[cfg(feature = "io")]
impl CameraVideoWriter {
    pub fn create(path: &Path, width: u32, height: u32, fps: u32, encoding: VideoEncoding) -> Result<Self> {
        if !width.is_multiple_of(2) || !height.is_multiple_of(2) || width == 0 || height == 0 {
            return Err(DataError::InvalidInput(format!(
                "yuv420p video needs even, non-zero sizes; got {width}x{height}"
            )));
        }
        let (w16, h16) = (u16::try_from(width), u16::try_from(height));
        let (Ok(w16), Ok(h16)) = (w16, h16) else {
            return Err(DataError::InvalidInput(format!("{width}x{height} is too large for an mp4 track")));
        };
        Ok(Self {
            encoder: h264::H264Encoder::new(width, height, fps, encoding.qp_max, encoding.gop)?,
            muxer: Mp4Writer::create(path, w16, h16, fps)?,
        })
    }

    pub fn push_frame(&mut self, image: &RgbImage) -> Result<()> {
        let frame = self.encoder.encode(image)?;
        if let Some(sets) = frame.parameter_sets {
            self.muxer.set_parameter_sets(sets);
        }
        self.muxer.push_sample(&frame.avcc_sample, frame.is_sync)
    }

    /// Frames written so far: the next frame is presented at `frame_count() / fps` seconds.
    pub fn frame_count(&self) -> usize {
        self.muxer.frame_count()
    }

    pub fn bytes_written(&self) -> u64 {
        self.muxer.bytes_written()
    }

    pub fn finish(self) -> Result<()> {
        self.muxer.finish()
    }
}

#[cfg(feature = "io")]
enum FrameDecoder {
    H264(h264::H264Decoder),
    #[cfg(feature = "av1")]
    Av1(av1::Av1Decoder),
}

#[cfg(feature = "io")]
impl FrameDecoder {
    fn new(track: &Mp4Track) -> Result<Self> {
        match &track.codec {
            TrackCodec::H264 { avcc } => Ok(FrameDecoder::H264(h264::H264Decoder::new(&track.path, avcc)?)),
            #[cfg(feature = "av1")]
            TrackCodec::Av1 { av1c } => Ok(FrameDecoder::Av1(av1::Av1Decoder::new(&track.path, av1c)?)),
            #[cfg(not(feature = "av1"))]
            TrackCodec::Av1 { .. } => Err(DataError::UnsupportedCodec {
                path: track.path.clone(),
                codec: "av1".into(),
                hint: " (build fedvla-data with feature `av1`, which needs libdav1d-dev)",
            }),
            TrackCodec::Other { fourcc } => {
                Err(DataError::UnsupportedCodec { path: track.path.clone(), codec: fourcc.clone(), hint: "" })
            }
        }
    }

    fn decode(&mut self, path: &Path, sample: &[u8]) -> Result<Option<RgbImage>> {
        match self {
            FrameDecoder::H264(d) => d.decode(path, sample),
            #[cfg(feature = "av1")]
            FrameDecoder::Av1(d) => d.decode(path, sample),
        }
    }
}

/// One mp4 file's samples by presentation time, and which to decode to serve given timestamps.
pub struct VideoFile {
    track: Mp4Track,
    /// Sample indices sorted by presentation time.
    by_time: Vec<usize>,
}

impl VideoFile {
    /// Parses the sample tables of video `path` of `files`.
    pub fn open(files: &dyn DatasetFiles, path: &Path) -> Result<Self> {
        let track = Mp4Track::open(files, path)?;
        let mut by_time: Vec<usize> = (0..track.pts.len()).collect();
        by_time.sort_by_key(|&i| track.pts[i]);
        Ok(Self { track, by_time })
    }

    pub fn track(&self) -> &Mp4Track {
        &self.track
    }

    pub fn path(&self) -> &Path {
        &self.track.path
    }

    pub fn frame_count(&self) -> usize {
        self.track.pts.len()
    }

    /// The sample presented closest to `t` seconds, if within `tolerance_s` (LeRobot uses 1e-4 s).
    fn sample_at(&self, t: f64, tolerance_s: f64) -> Result<usize> {
        let ticks = t * f64::from(self.track.timescale);
        let pos = self.by_time.partition_point(|&i| (self.track.pts[i] as f64) < ticks);
        let candidates = [pos.checked_sub(1), Some(pos)];
        let best = candidates.into_iter().flatten().filter_map(|p| self.by_time.get(p).copied()).min_by(|&a, &b| {
            let da = (self.track.sample_time_s(a) - t).abs();
            let db = (self.track.sample_time_s(b) - t).abs();
            da.total_cmp(&db)
        });
        match best {
            Some(s) if (self.track.sample_time_s(s) - t).abs() <= tolerance_s => Ok(s),
            _ => Err(DataError::FrameTimestamp { path: self.track.path.clone(), timestamp_s: t, tolerance_s }),
        }
    }

    /// The samples presented at `timestamps_s`, in the given order.
    pub fn samples_at(&self, timestamps_s: &[f64], tolerance_s: f64) -> Result<Vec<usize>> {
        timestamps_s.iter().map(|&t| self.sample_at(t, tolerance_s)).collect()
    }

    /// The runs of samples (in decode order) to decode for the pictures of `samples`: each starts at the last key
    /// frame before a wanted sample, and a run already past that key frame just keeps going to the next one.
    pub fn decode_runs(&self, samples: &[usize]) -> Vec<Range<usize>> {
        let mut targets = samples.to_vec();
        targets.sort_unstable();
        targets.dedup();
        let mut runs: Vec<Range<usize>> = Vec::new();
        for target in targets {
            let key = (0..=target).rev().find(|&i| self.track.is_sync.get(i) == Some(&true)).unwrap_or(0);
            match runs.last_mut() {
                Some(run) if run.end > key => run.end = target + 1,
                _ => runs.push(key..target + 1),
            }
        }
        runs
    }
}

/// Frames decoded natively from a dataset's mp4 files, each file's sample tables parsed once.
#[cfg(feature = "io")]
pub struct Mp4Frames {
    files: std::sync::Arc<dyn DatasetFiles>,
    opened: std::sync::Mutex<BTreeMap<PathBuf, std::sync::Arc<VideoFile>>>,
}

#[cfg(feature = "io")]
impl Mp4Frames {
    pub fn new(files: std::sync::Arc<dyn DatasetFiles>) -> Self {
        Self { files, opened: std::sync::Mutex::default() }
    }

    fn video(&self, path: &Path) -> Result<std::sync::Arc<VideoFile>> {
        let mut opened = self.opened.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        if let Some(video) = opened.get(path) {
            return Ok(video.clone());
        }
        let video = std::sync::Arc::new(VideoFile::open(&*self.files, path)?);
        opened.insert(path.to_path_buf(), video.clone());
        Ok(video)
    }
}

#[cfg(feature = "io")]
impl FrameSource for Mp4Frames {
    /// Each run of [`VideoFile::decode_runs`] is decoded forward from its key frame by a fresh decoder.
    fn frames_at(&self, path: &Path, timestamps_s: &[f64], tolerance_s: f64) -> Result<Vec<RgbImage>> {
        let video = self.video(path)?;
        let wanted = video.samples_at(timestamps_s, tolerance_s)?;
        let mut decoded: BTreeMap<usize, RgbImage> = BTreeMap::new();
        for run in video.decode_runs(&wanted) {
            let mut decoder = FrameDecoder::new(&video.track)?;
            // The samples whose pictures the decoder still owes: pictures come out in decode order, one per
            // sample, and the decoder may hold some back.
            let mut owed = std::collections::VecDeque::new();
            for sample in run {
                let bytes = video.track.read_sample(&*self.files, sample)?;
                owed.push_back(sample);
                if let Some(image) = decoder.decode(video.path(), &bytes)?
                    && let Some(sample) = owed.pop_front()
                    && wanted.contains(&sample)
                {
                    decoded.insert(sample, image);
                }
            }
        }
        pictures_of(video.path(), &wanted, &decoded)
    }
}

/// Frames a caller decoded (a browser page, with WebCodecs), by video file and sample: what it was asked to
/// decode by [`VideoFile::decode_runs`] of the samples [`VideoFile::samples_at`] names.
#[derive(Default)]
pub struct DecodedFrames {
    videos: BTreeMap<PathBuf, (VideoFile, BTreeMap<usize, RgbImage>)>,
}

impl DecodedFrames {
    /// Adds the pictures of `samples` of `video`, file `path` of the dataset.
    pub fn insert(&mut self, path: &Path, video: VideoFile, pictures: BTreeMap<usize, RgbImage>) {
        self.videos.insert(path.to_path_buf(), (video, pictures));
    }
}

impl FrameSource for DecodedFrames {
    fn frames_at(&self, path: &Path, timestamps_s: &[f64], tolerance_s: f64) -> Result<Vec<RgbImage>> {
        let (video, pictures) = self.videos.get(path).ok_or_else(|| {
            DataError::InvalidInput(format!("{}: no frames of this video were decoded", path.display()))
        })?;
        pictures_of(video.path(), &video.samples_at(timestamps_s, tolerance_s)?, pictures)
    }
}

/// The pictures of `samples`, in order, from `decoded`: an error naming the first one missing.
fn pictures_of(path: &Path, samples: &[usize], decoded: &BTreeMap<usize, RgbImage>) -> Result<Vec<RgbImage>> {
    samples
        .iter()
        .map(|s| {
            decoded.get(s).cloned().ok_or_else(|| DataError::Decode {
                path: path.to_path_buf(),
                reason: format!("sample {s} produced no picture"),
            })
        })
        .collect()
}
