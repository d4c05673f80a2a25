//! H.264 through OpenH264 (compiled from Cisco's source by the `openh264` crate): encoding camera
//! frames into mp4 samples, and decoding mp4 samples back to RGB.

use openh264::OpenH264API;
use openh264::decoder::Decoder;
use openh264::encoder::{
    BitRate, Complexity, Encoder, EncoderConfig, FrameRate, IntraFramePeriod, QpRange, RateControlMode, UsageType,
    VuiConfig,
};
use openh264::formats::{YUVBuffer, YUVSource};

use super::color;
use super::mp4::AvcParameterSets;
use crate::error::{DataError, Result};
use crate::image::RgbImage;
use std::path::Path;

/// One encoded frame as an mp4 sample.
pub struct EncodedFrame {
    /// NAL units with 4-byte big-endian length prefixes (SPS/PPS removed).
    pub avcc_sample: Vec<u8>,
    pub is_sync: bool,
    /// The SPS/PPS the encoder emitted with this frame (on key frames).
    pub parameter_sets: Option<AvcParameterSets>,
}

pub struct H264Encoder {
    encoder: Encoder,
    width: u32,
    height: u32,
}

impl H264Encoder {
    /// `qp_max` bounds the quantiser (0 best .. 51 worst); `gop` is the key-frame interval in frames.
    pub fn new(width: u32, height: u32, fps: u32, qp_max: u8, gop: u32) -> Result<Self> {
        let pixels_per_second = u64::from(width) * u64::from(height) * u64::from(fps);
        // About 2 bits per pixel: far above what the qp bound lets the encoder spend, so quality is
        // governed by `qp_max`, not by the rate controller.
        let bitrate = (pixels_per_second * 2).clamp(200_000, u64::from(u32::MAX)) as u32;
        let config = EncoderConfig::new()
            .usage_type(UsageType::CameraVideoRealTime)
            // Buffer-based control: the bitrate-targeting modes need frame skipping, which must stay off.
            .rate_control_mode(RateControlMode::Bufferbased)
            .bitrate(BitRate::from_bps(bitrate))
            .max_frame_rate(FrameRate::from_hz(fps as f32))
            // A skipped frame would shift every later frame's timestamp in the file.
            .skip_frames(false)
            .qp(QpRange::new(0, qp_max.min(51)))
            // Low complexity encodes twice as fast as High at about the same size and fidelity here.
            .complexity(Complexity::Low)
            .intra_frame_period(IntraFramePeriod::from_num_frames(gop))
            .scene_change_detect(false)
            .vui(VuiConfig::bt601());
        let encoder = Encoder::with_api_config(OpenH264API::from_source(), config)
            .map_err(|e| DataError::Encode(e.to_string()))?;
        Ok(Self { encoder, width, height })
    }

    pub fn encode(&mut self, image: &RgbImage) -> Result<EncodedFrame> {
        if image.width != self.width || image.height != self.height {
            return Err(DataError::InvalidInput(format!(
                "frame is {}x{}, the camera is {}x{}",
                image.width, image.height, self.width, self.height
            )));
        }
        let yuv = YUVBuffer::from_vec(color::rgb_to_i420(image), self.width as usize, self.height as usize);
        let bitstream = self.encoder.encode(&yuv).map_err(|e| DataError::Encode(e.to_string()))?;
        let annexb = bitstream.to_vec();
        let mut avcc_sample = Vec::with_capacity(annexb.len());
        let (mut sps, mut pps) = (None, None);
        let mut is_sync = false;
        for nal in split_annexb(&annexb) {
            match nal.first().map(|b| b & 0x1F) {
                Some(7) => sps = Some(nal.to_vec()),
                Some(8) => pps = Some(nal.to_vec()),
                Some(t) => {
                    is_sync |= t == 5;
                    avcc_sample.extend_from_slice(&(nal.len() as u32).to_be_bytes());
                    avcc_sample.extend_from_slice(nal);
                }
                None => {}
            }
        }
        if avcc_sample.is_empty() {
            return Err(DataError::Encode("the encoder produced no picture for a frame".into()));
        }
        let parameter_sets = match (sps, pps) {
            (Some(sps), Some(pps)) => Some(AvcParameterSets { sps, pps }),
            _ => None,
        };
        Ok(EncodedFrame { avcc_sample, is_sync, parameter_sets })
    }
}

/// NAL unit payloads (without start codes) of an Annex-B byte stream.
fn split_annexb(stream: &[u8]) -> Vec<&[u8]> {
    let mut starts = Vec::new();
    let mut i = 0;
    while i + 3 <= stream.len() {
        if stream[i] == 0 && stream[i + 1] == 0 && stream[i + 2] == 1 {
            starts.push(i + 3);
            i += 3;
        } else {
            i += 1;
        }
    }
    let mut nals = Vec::new();
    for (k, &s) in starts.iter().enumerate() {
        let mut end = starts.get(k + 1).map_or(stream.len(), |&n| n - 3);
        // A 4-byte start code leaves one extra zero before the next 00 00 01.
        while end > s && stream[end - 1] == 0 && k + 1 < starts.len() {
            end -= 1;
        }
        nals.push(&stream[s..end]);
    }
    nals
}

/// Decodes the samples of one H.264 track, in decode order, starting at a sync sample.
pub struct H264Decoder {
    decoder: Decoder,
    /// SPS and PPS from `avcC`, as Annex-B, fed before the first sample.
    parameter_sets: Vec<u8>,
    nal_length_size: usize,
    started: bool,
}

impl H264Decoder {
    pub fn new(path: &Path, avcc: &[u8]) -> Result<Self> {
        let bad = |what: &str| DataError::mp4(path, format!("avcC: {what}"));
        if avcc.len() < 7 {
            return Err(bad("too short"));
        }
        let nal_length_size = usize::from(avcc[4] & 3) + 1;
        let mut parameter_sets = Vec::new();
        let mut pos = 5;
        for group in 0..2 {
            let count = if group == 0 {
                usize::from(*avcc.get(pos).ok_or_else(|| bad("truncated"))? & 0x1F)
            } else {
                usize::from(*avcc.get(pos).ok_or_else(|| bad("truncated"))?)
            };
            pos += 1;
            for _ in 0..count {
                let len = usize::from(u16::from_be_bytes([
                    *avcc.get(pos).ok_or_else(|| bad("truncated"))?,
                    *avcc.get(pos + 1).ok_or_else(|| bad("truncated"))?,
                ]));
                pos += 2;
                let nal = avcc.get(pos..pos + len).ok_or_else(|| bad("truncated"))?;
                parameter_sets.extend_from_slice(&[0, 0, 0, 1]);
                parameter_sets.extend_from_slice(nal);
                pos += len;
            }
        }
        let decoder =
            Decoder::new().map_err(|e| DataError::Decode { path: path.to_path_buf(), reason: e.to_string() })?;
        Ok(Self { decoder, parameter_sets, nal_length_size, started: false })
    }

    /// Decodes one sample; `None` when the decoder holds the picture back.
    pub fn decode(&mut self, path: &Path, sample: &[u8]) -> Result<Option<RgbImage>> {
        let mut annexb = Vec::with_capacity(sample.len() + self.parameter_sets.len() + 16);
        if !self.started {
            annexb.extend_from_slice(&self.parameter_sets);
            self.started = true;
        }
        let mut pos = 0;
        while pos + self.nal_length_size <= sample.len() {
            let len =
                sample[pos..pos + self.nal_length_size].iter().fold(0usize, |acc, &b| (acc << 8) | usize::from(b));
            pos += self.nal_length_size;
            let nal = sample
                .get(pos..pos + len)
                .ok_or_else(|| DataError::mp4(path, "a NAL unit runs past the end of its sample"))?;
            annexb.extend_from_slice(&[0, 0, 0, 1]);
            annexb.extend_from_slice(nal);
            pos += len;
        }
        let decoded = self
            .decoder
            .decode(&annexb)
            .map_err(|e| DataError::Decode { path: path.to_path_buf(), reason: e.to_string() })?;
        Ok(decoded.map(|yuv| {
            let (w, h) = yuv.dimensions();
            color::yuv420_to_rgb(w, h, (yuv.y(), yuv.u(), yuv.v()), yuv.strides())
        }))
    }
}
