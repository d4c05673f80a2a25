//! AV1 decoding through the system libdav1d (feature `av1`): the codec of most LeRobot datasets on the Hub.

use std::path::Path;

use dav1d::{Decoder, PlanarImageComponent, Settings};

use super::color;
use crate::error::{DataError, Result};
use crate::image::RgbImage;

pub struct Av1Decoder {
    decoder: Decoder,
    /// Configuration OBUs from `av1C` (the sequence header), sent before the first sample.
    config_obus: Vec<u8>,
    started: bool,
}

impl Av1Decoder {
    pub fn new(path: &Path, av1c: &[u8]) -> Result<Self> {
        let mut settings = Settings::new();
        // One picture out per sample in, in order: the caller maps samples to timestamps.
        settings.set_n_threads(1);
        settings.set_max_frame_delay(1);
        let decoder = Decoder::with_settings(&settings).map_err(|e| decode_error(path, e))?;
        Ok(Self { decoder, config_obus: av1c.get(4..).unwrap_or_default().to_vec(), started: false })
    }

    pub fn decode(&mut self, path: &Path, sample: &[u8]) -> Result<Option<RgbImage>> {
        let mut data = Vec::with_capacity(sample.len() + self.config_obus.len());
        if !self.started {
            data.extend_from_slice(&self.config_obus);
            self.started = true;
        }
        data.extend_from_slice(sample);
        match self.decoder.send_data(data, None, None, None) {
            Ok(()) | Err(dav1d::Error::Again) => {}
            Err(e) => return Err(decode_error(path, e)),
        }
        let picture = match self.decoder.get_picture() {
            Ok(p) => p,
            Err(dav1d::Error::Again) => return Ok(None),
            Err(e) => return Err(decode_error(path, e)),
        };
        if picture.bit_depth() != 8 || !matches!(picture.pixel_layout(), dav1d::PixelLayout::I420) {
            return Err(DataError::Decode {
                path: path.to_path_buf(),
                reason: format!(
                    "only 8-bit 4:2:0 AV1 is supported, got {}-bit {:?}",
                    picture.bit_depth(),
                    picture.pixel_layout()
                ),
            });
        }
        let (y, u, v) = (
            picture.plane(PlanarImageComponent::Y),
            picture.plane(PlanarImageComponent::U),
            picture.plane(PlanarImageComponent::V),
        );
        let strides = (
            picture.stride(PlanarImageComponent::Y) as usize,
            picture.stride(PlanarImageComponent::U) as usize,
            picture.stride(PlanarImageComponent::V) as usize,
        );
        Ok(Some(color::yuv420_to_rgb(picture.width() as usize, picture.height() as usize, (&y, &u, &v), strides)))
    }
}

fn decode_error(path: &Path, e: dav1d::Error) -> DataError {
    DataError::Decode { path: path.to_path_buf(), reason: format!("dav1d: {e:?}") }
}
