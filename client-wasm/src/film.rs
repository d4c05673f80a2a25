//! Filming rollouts in the page: each frame of the sim is rendered by the shared software renderer (both
//! cameras side by side), drawn to the page's canvas, and recorded from the canvas with `MediaRecorder` as WebM,
//! which every current browser plays.

use std::cell::RefCell;
use std::rc::Rc;

use fedvla_federation::Video;
use fedvla_sim::{Camera, Scene, render};
use wasm_bindgen::prelude::*;
use wasm_bindgen::{Clamped, JsCast};
use wasm_bindgen_futures::JsFuture;
use web_sys::{
    Blob, BlobEvent, CanvasRenderingContext2d, HtmlCanvasElement, ImageData, MediaRecorder, MediaRecorderOptions,
    MediaStream,
};

/// The recording's container and codec; VP8 is encoded in software everywhere, headless Chromium included.
const MIME: &str = "video/webm;codecs=vp8";

/// Draws scenes on a canvas: the cameras side by side, each `size`² pixels.
pub struct CanvasView {
    canvas: HtmlCanvasElement,
    context: CanvasRenderingContext2d,
    size: usize,
    rgba: Vec<u8>,
}

impl CanvasView {
    pub fn new(canvas: HtmlCanvasElement, size: usize) -> Result<Self, JsValue> {
        canvas.set_width((size * Camera::ALL.len()) as u32);
        canvas.set_height(size as u32);
        let context =
            canvas.get_context("2d")?.ok_or("the canvas has no 2d context")?.dyn_into::<CanvasRenderingContext2d>()?;
        Ok(Self { canvas, context, size, rgba: vec![255; size * size * 4] })
    }

    pub fn draw(&mut self, scene: &Scene) -> Result<(), JsValue> {
        let size = self.size;
        for (slot, camera) in Camera::ALL.into_iter().enumerate() {
            let rgb = render(scene, camera, size, size);
            for (px, out) in rgb.chunks_exact(3).zip(self.rgba.chunks_exact_mut(4)) {
                out[..3].copy_from_slice(px);
            }
            let image = ImageData::new_with_u8_clamped_array_and_sh(Clamped(&self.rgba), size as u32, size as u32)?;
            self.context.put_image_data(&image, (slot * size) as f64, 0.0)?;
        }
        Ok(())
    }
}

/// A `MediaRecorder` on a canvas, collecting its chunks until stopped.
pub struct Recorder {
    recorder: MediaRecorder,
    chunks: Rc<RefCell<Vec<Blob>>>,
    stopped: js_sys::Promise,
    _on_data: Closure<dyn FnMut(BlobEvent)>,
}

impl Recorder {
    /// Starts recording `view`'s canvas at `fps` frames per second.
    pub fn start(view: &CanvasView, fps: f64) -> Result<Self, JsValue> {
        if !MediaRecorder::is_type_supported(MIME) {
            return Err(JsValue::from_str(&format!("this browser cannot record {MIME}")));
        }
        let stream: MediaStream = view.canvas.capture_stream_with_frame_request_rate(fps)?;
        let options = MediaRecorderOptions::new();
        options.set_mime_type(MIME);
        let recorder = MediaRecorder::new_with_media_stream_and_media_recorder_options(&stream, &options)?;
        let chunks = Rc::new(RefCell::new(Vec::new()));
        let sink = Rc::clone(&chunks);
        let on_data = Closure::<dyn FnMut(BlobEvent)>::new(move |event: BlobEvent| {
            if let Some(blob) = event.data().filter(|b| b.size() > 0.0) {
                sink.borrow_mut().push(blob);
            }
        });
        recorder.set_ondataavailable(Some(on_data.as_ref().unchecked_ref()));
        let target = recorder.clone();
        let stopped = js_sys::Promise::new(&mut |resolve, _| target.set_onstop(Some(&resolve)));
        recorder.start()?;
        Ok(Self { recorder, chunks, stopped, _on_data: on_data })
    }

    /// Stops and returns the recording as `file_name`.
    pub async fn finish(self, file_name: String) -> Result<Video, JsValue> {
        self.recorder.stop()?;
        JsFuture::from(self.stopped).await?;
        let parts = js_sys::Array::new();
        for blob in self.chunks.borrow().iter() {
            parts.push(blob);
        }
        let bag = web_sys::BlobPropertyBag::new();
        bag.set_type("video/webm");
        let blob = Blob::new_with_blob_sequence_and_options(&parts, &bag)?;
        let buffer = JsFuture::from(blob.array_buffer()).await?;
        Ok(Video { file_name, mime: "video/webm".into(), bytes: js_sys::Uint8Array::new(&buffer).to_vec() })
    }
}
