//! Camera video: RGB frames, encoding a camera's episodes into one H.264 mp4, and decoding frames at
//! given timestamps from H.264 or (feature `av1`) AV1 mp4 files.

#[cfg(feature = "av1")]
mod av1;
mod color;
mod h264;
pub mod mp4;

use std::collections::BTreeMap;
use std::fs::File;
use std::path::{Path, PathBuf};

use crate::error::{DataError, Result};
pub use crate::image::RgbImage;
use mp4::{Mp4Track, Mp4Writer, TrackCodec};

/// How camera streams are encoded.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct VideoEncoding {
    /// Upper bound of the H.264 quantiser (0 best .. 51 worst).
    pub qp_max: u8,
    /// Key-frame interval in frames: short keeps random access (LeRobot's training reads) cheap.
    pub gop: u32,
}

impl Default for VideoEncoding {
    fn default() -> Self {
        Self { qp_max: 22, gop: 10 }
    }
}

/// Encodes one camera's frames into one mp4 file (many episodes back to back).
pub struct CameraVideoWriter {
    encoder: h264::H264Encoder,
    muxer: Mp4Writer,
}

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

enum FrameDecoder {
    H264(h264::H264Decoder),
    #[cfg(feature = "av1")]
    Av1(av1::Av1Decoder),
}

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

/// Decodes frames of one mp4 file by presentation timestamp.
pub struct VideoFile {
    track: Mp4Track,
    /// Sample indices sorted by presentation time.
    by_time: Vec<usize>,
}

impl VideoFile {
    pub fn open(path: &Path) -> Result<Self> {
        let track = Mp4Track::open(path)?;
        let mut by_time: Vec<usize> = (0..track.pts.len()).collect();
        by_time.sort_by_key(|&i| track.pts[i]);
        Ok(Self { track, by_time })
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

    /// Decodes the frames presented at `timestamps_s` (seconds from the file start), in the given order.
    /// Each run of requested frames is decoded forward from the last key frame before it; a decoder
    /// already positioned before a requested frame (and past its key frame) just keeps going.
    pub fn frames_at(&self, timestamps_s: &[f64], tolerance_s: f64) -> Result<Vec<RgbImage>> {
        let wanted: Vec<usize> = timestamps_s.iter().map(|&t| self.sample_at(t, tolerance_s)).collect::<Result<_>>()?;
        let mut targets = wanted.clone();
        targets.sort_unstable();
        targets.dedup();
        let path = self.track.path.clone();
        let mut file = File::open(&path).map_err(|e| DataError::io(&path, e))?;
        let mut decoded: BTreeMap<usize, RgbImage> = BTreeMap::new();
        // The decoder, the next sample it would take, and the samples whose pictures it still owes.
        let mut state: Option<(FrameDecoder, usize, std::collections::VecDeque<usize>)> = None;
        for &target in &targets {
            let key = (0..=target).rev().find(|&i| self.track.is_sync[i]).unwrap_or(0);
            let keep = matches!(&state, Some((_, next, _)) if *next <= target && *next > key);
            if !keep {
                state = Some((FrameDecoder::new(&self.track)?, key, std::collections::VecDeque::new()));
            }
            let Some((decoder, next, owed)) = state.as_mut() else { break };
            while *next <= target {
                let bytes = self.track.read_sample(&mut file, *next)?;
                owed.push_back(*next);
                *next += 1;
                // Pictures come out in decode order, one per sample; the decoder may hold some back.
                if let Some(image) = decoder.decode(&path, &bytes)?
                    && let Some(sample) = owed.pop_front()
                    && targets.binary_search(&sample).is_ok()
                {
                    decoded.insert(sample, image);
                }
            }
        }
        wanted
            .iter()
            .map(|s| {
                decoded.get(s).cloned().ok_or_else(|| DataError::Decode {
                    path: path.clone(),
                    reason: format!("sample {s} produced no picture"),
                })
            })
            .collect()
    }
}

/// Opened video files, by path, so that repeated frame reads skip re-parsing the sample tables.
#[derive(Default)]
pub struct VideoCache {
    files: std::sync::Mutex<BTreeMap<PathBuf, std::sync::Arc<VideoFile>>>,
}

impl VideoCache {
    pub fn get(&self, path: &Path) -> Result<std::sync::Arc<VideoFile>> {
        let mut files = self.files.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        if let Some(f) = files.get(path) {
            return Ok(f.clone());
        }
        let file = std::sync::Arc::new(VideoFile::open(path)?);
        files.insert(path.to_path_buf(), file.clone());
        Ok(file)
    }
}
