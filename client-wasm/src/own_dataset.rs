//! The volunteer's own LeRobot dataset in the page: the folder it picked (www/dataset.js lists it and reads a file
//! only when asked), read stage by stage through the shared reader (`meta/info.json`, checked against the run's
//! signature before anything else is read; the metadata the reader names; the data files; the videos of the run's
//! cameras holding the episodes that fit the memory budget), its video samples decoded by the browser's WebCodecs
//! `VideoDecoder` (www/dataset.js), and packed by the shared packing ([`fedvla_learner::own_data`]). Every file read
//! is reported to the page, which lists it.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

use fedvla_data::video::{DecodedFrames, VideoFile};
use fedvla_data::{DatasetMeta, LeRobotDataset, MemoryFiles, RgbImage};
use fedvla_federation::{BoxError, VolunteerSetup};
use fedvla_learner::own_data::{OwnShard, bytes_per_frame, check_fits_run, episodes_within, pack_own_dataset};
use fedvla_learner::volunteer::{Fetch, fetch_tokenizer, policy_config, volunteer_seed};
use js_sys::{Array, Reflect, Uint8Array};
use serde_json::json;
use wasm_bindgen::JsCast;
use wasm_bindgen::prelude::*;
use wasm_bindgen_futures::JsFuture;

use crate::browser::yield_to_page;
use crate::status::StatusSink;

/// Memory the own dataset's examples may take in the page (see [`bytes_per_frame`]): the first episodes that fit
/// are trained on. wasm32 addresses 4 GiB, and the model and its training need their share.
pub const OWN_DATASET_BUDGET_BYTES: u64 = 1 << 30;

/// LeRobot's tolerance when matching a requested time to a video frame (the reader's).
const TOLERANCE_S: f64 = fedvla_data::reader::VIDEO_TOLERANCE_S;

/// The folder the page picked: its name, every file's path (relative to it) and size, and the page's functions that
/// read one file (`read(path) -> Promise<Uint8Array>`) and decode video samples with WebCodecs
/// (`decode(request) -> Promise<[{timestamp, width, height, rgba}]>`).
pub struct PickedFolder {
    name: String,
    listing: Vec<(PathBuf, u64)>,
    read: js_sys::Function,
    decode: js_sys::Function,
}

fn field(object: &JsValue, name: &str) -> Result<JsValue, BoxError> {
    Reflect::get(object, &name.into()).map_err(|_| format!("the picked folder has no {name}").into())
}

fn js_message(e: JsValue) -> String {
    e.as_string()
        .or_else(|| e.dyn_ref::<js_sys::Error>().and_then(|e| e.message().as_string()))
        .unwrap_or_else(|| "JavaScript error".into())
}

impl PickedFolder {
    /// The page's folder object `{name, paths, sizes, read, decode}`.
    pub fn from_js(folder: &JsValue) -> Result<Self, BoxError> {
        let name = field(folder, "name")?.as_string().ok_or("the picked folder's name is not a string")?;
        let paths = Array::from(&field(folder, "paths")?);
        let sizes = Array::from(&field(folder, "sizes")?);
        let listing = paths
            .iter()
            .zip(sizes.iter())
            .map(|(path, size)| {
                let path = path.as_string().ok_or("a picked file's path is not a string")?;
                let size = size.as_f64().ok_or_else(|| format!("{path}: no size"))?;
                Ok((PathBuf::from(path), size as u64))
            })
            .collect::<Result<Vec<_>, BoxError>>()?;
        let function = |name: &str| -> Result<js_sys::Function, BoxError> {
            field(folder, name)?.dyn_into().map_err(|_| format!("the picked folder's {name} is not a function").into())
        };
        Ok(Self { name, listing, read: function("read")?, decode: function("decode")? })
    }

    /// Reads `path` of the folder into `files`, telling the page.
    async fn read_into(&self, files: &mut MemoryFiles, path: &Path, status: &StatusSink) -> Result<(), BoxError> {
        let shown = path.display().to_string();
        let promise = self.read.call1(&JsValue::NULL, &JsValue::from_str(&shown)).map_err(js_message)?;
        let bytes = Uint8Array::new(&JsFuture::from(js_sys::Promise::from(promise)).await.map_err(js_message)?);
        files.insert(path, bytes.to_vec())?;
        status.send("dataset_read", json!({ "path": shown, "bytes": bytes.length() }));
        Ok(())
    }

    /// The pictures of samples `run` of `video` (in decode order from a key frame), decoded by the page's
    /// WebCodecs `VideoDecoder`, keeping those of `wanted`.
    async fn decode_run(
        &self,
        files: &MemoryFiles,
        video: &VideoFile,
        run: std::ops::Range<usize>,
        wanted: &BTreeSet<usize>,
        pictures: &mut BTreeMap<usize, RgbImage>,
    ) -> Result<(), BoxError> {
        let track = video.track();
        let codec = track.codec.codec_string().ok_or_else(|| {
            format!("{}: a video codec this page cannot name to the browser's decoder", video.path().display())
        })?;
        let (samples, keys) = (Array::new(), Array::new());
        for sample in run.clone() {
            samples.push(&Uint8Array::from(track.read_sample(files, sample)?.as_slice()));
            keys.push(&JsValue::from_bool(track.is_sync[sample]));
        }
        let request = js_sys::Object::new();
        for (name, value) in [
            ("codec", JsValue::from_str(&codec)),
            ("description", Uint8Array::from(track.codec.configuration()).into()),
            ("width", JsValue::from(track.width)),
            ("height", JsValue::from(track.height)),
            ("first", JsValue::from(run.start as f64)),
            ("samples", samples.into()),
            ("keys", keys.into()),
        ] {
            Reflect::set(&request, &name.into(), &value).map_err(js_message)?;
        }
        let promise = self.decode.call1(&JsValue::NULL, &request).map_err(js_message)?;
        let decoded = JsFuture::from(js_sys::Promise::from(promise))
            .await
            .map_err(|e| format!("{}: {}", video.path().display(), js_message(e)))?;
        for picture in Array::from(&decoded).iter() {
            let number = |name: &str| field(&picture, name).ok().and_then(|v| v.as_f64()).unwrap_or(-1.0);
            let sample = number("timestamp") as usize;
            if !wanted.contains(&sample) {
                continue;
            }
            let rgba = Uint8Array::new(&field(&picture, "rgba")?).to_vec();
            let rgb: Vec<u8> = rgba.chunks_exact(4).flat_map(|p| [p[0], p[1], p[2]]).collect();
            pictures.insert(sample, RgbImage::new(number("width") as u32, number("height") as u32, rgb)?);
        }
        Ok(())
    }
}

/// Packs the picked folder for the run of `setup` (the shared packing over the shared reader): refuses a dataset
/// that does not fit before reading anything but `meta/info.json`, reads only what the policy needs, and trains on
/// the first episodes that fit [`OWN_DATASET_BUDGET_BYTES`].
pub async fn pack_picked_folder(
    folder: &PickedFolder,
    fetch: &impl Fetch,
    setup: &VolunteerSetup,
    name: &str,
    status: &StatusSink,
) -> Result<OwnShard, BoxError> {
    let named = |e: &dyn std::fmt::Display| format!("own dataset {}: {e}", folder.name);
    let run = setup.dataset_signature.as_ref().ok_or("the server takes no own datasets")?;
    let mut files = MemoryFiles::new(&folder.name, folder.listing.clone());
    status.send("stage", json!({ "stage": "reading your dataset's meta/info.json" }));
    folder.read_into(&mut files, Path::new("meta/info.json"), status).await?;
    let (info, version) = DatasetMeta::read_info(&files)?;
    let signature = check_fits_run(&info, run).map_err(|e| named(&e))?;
    let cfg = policy_config(setup)?;
    let tokenizer = fetch_tokenizer(fetch, setup).await?;

    for path in DatasetMeta::files_to_read(version, &files)? {
        folder.read_into(&mut files, &path, status).await?;
    }
    let meta = DatasetMeta::read(&files).map_err(|e| named(&e))?;
    for path in meta.data_files.clone() {
        folder.read_into(&mut files, &path, status).await?;
    }
    let per_frame = bytes_per_frame(&meta.info, &cfg);
    let episodes = episodes_within(&meta.episodes, per_frame, OWN_DATASET_BUDGET_BYTES);
    let frames: usize = meta.episodes.iter().filter(|e| episodes.contains(&e.episode_index)).map(|e| e.length).sum();
    status.send(
        "dataset_plan",
        json!({ "episodes": episodes.len(), "of": meta.episodes.len(), "frames": frames,
                "bytes": frames as u64 * per_frame, "budget_bytes": OWN_DATASET_BUDGET_BYTES }),
    );
    let dataset = LeRobotDataset::from_meta(meta, &files, Box::new(DecodedFrames::default())).map_err(|e| named(&e))?;

    // The frames of every chosen episode and camera, by video file.
    let mut wanted: BTreeMap<PathBuf, Vec<f64>> = BTreeMap::new();
    for episode in dataset.episodes().iter().filter(|e| episodes.contains(&e.episode_index)) {
        let indices: Vec<usize> = (episode.dataset_from_index..episode.dataset_to_index).collect();
        for camera in dataset.camera_keys() {
            let (path, times) = dataset.frame_times(&camera, episode, &indices).map_err(|e| named(&e))?;
            wanted.entry(path.to_path_buf()).or_default().extend(times);
        }
    }
    let mut decoded = DecodedFrames::default();
    for (path, times) in &wanted {
        folder.read_into(&mut files, path, status).await?;
        let video = VideoFile::open(&files, path)?;
        let samples = video.samples_at(times, TOLERANCE_S)?;
        let needed: BTreeSet<usize> = samples.iter().copied().collect();
        let mut pictures = BTreeMap::new();
        status.send("stage", json!({ "stage": format!("decoding {} (WebCodecs)", path.display()) }));
        for run in video.decode_runs(&samples) {
            folder.decode_run(&files, &video, run, &needed, &mut pictures).await?;
        }
        status.send("dataset_decoded", json!({ "path": path.display().to_string(), "frames": pictures.len() }));
        decoded.insert(path, video, pictures);
        yield_to_page().await;
    }
    let dataset = dataset.with_frames(Box::new(decoded));
    status.send("stage", json!({ "stage": "building your examples" }));
    yield_to_page().await;
    pack_own_dataset(&dataset, &episodes, signature, &cfg, &tokenizer, volunteer_seed(name), &mut |_| {})
}
