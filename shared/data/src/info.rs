//! `meta/info.json`: the dataset's schema and layout (features, fps, path templates), for LeRobot v3.0
//! (written and read) and v2.1 (read), plus the path helpers both layouts need.

use std::path::{Path, PathBuf};

use serde::de::{MapAccess, Visitor};
use serde::ser::SerializeMap;
use serde::{Deserialize, Deserializer, Serialize, Serializer};

use crate::error::{DataError, Result};

pub const CODEBASE_VERSION_V30: &str = "v3.0";
pub const CODEBASE_VERSION_V21: &str = "v2.1";
/// Files per chunk directory (LeRobot's default).
pub const CHUNKS_SIZE: u64 = 1000;
/// LeRobot's default rollover sizes for data parquet and video files.
pub const DATA_FILES_SIZE_IN_MB: u64 = 100;
pub const VIDEO_FILES_SIZE_IN_MB: u64 = 200;
pub const DATA_PATH_V30: &str = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet";
pub const VIDEO_PATH_V30: &str = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4";
pub const EPISODES_PATH_V30: &str = "meta/episodes/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet";

/// The on-disk layout generation.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CodebaseVersion {
    V30,
    V21,
}

/// `meta/info.json`. Field order follows LeRobot 0.6.1's output; v2.1-only fields are optional.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct DatasetInfo {
    pub codebase_version: String,
    pub fps: u32,
    pub features: Features,
    pub total_episodes: u64,
    pub total_frames: u64,
    pub total_tasks: u64,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub total_videos: Option<u64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub total_chunks: Option<u64>,
    pub chunks_size: u64,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub data_files_size_in_mb: Option<u64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub video_files_size_in_mb: Option<u64>,
    pub data_path: String,
    pub video_path: Option<String>,
    pub robot_type: Option<String>,
    #[serde(default)]
    pub splits: std::collections::BTreeMap<String, String>,
}

/// Features in document order (camera order and column order follow it).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Features(pub Vec<(String, Feature)>);

impl Features {
    pub fn get(&self, key: &str) -> Option<&Feature> {
        self.0.iter().find(|(k, _)| k == key).map(|(_, f)| f)
    }

    /// Keys of features stored as video, in order.
    pub fn video_keys(&self) -> Vec<String> {
        self.0.iter().filter(|(_, f)| f.dtype == "video").map(|(k, _)| k.clone()).collect()
    }
}

impl Serialize for Features {
    fn serialize<S: Serializer>(&self, s: S) -> std::result::Result<S::Ok, S::Error> {
        let mut map = s.serialize_map(Some(self.0.len()))?;
        for (k, v) in &self.0 {
            map.serialize_entry(k, v)?;
        }
        map.end()
    }
}

impl<'de> Deserialize<'de> for Features {
    fn deserialize<D: Deserializer<'de>>(d: D) -> std::result::Result<Self, D::Error> {
        struct OrderedVisitor;
        impl<'de> Visitor<'de> for OrderedVisitor {
            type Value = Features;
            fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                f.write_str("a map of feature name to feature")
            }
            fn visit_map<A: MapAccess<'de>>(self, mut map: A) -> std::result::Result<Features, A::Error> {
                let mut out = Vec::new();
                while let Some((k, v)) = map.next_entry::<String, Feature>()? {
                    out.push((k, v));
                }
                Ok(Features(out))
            }
        }
        d.deserialize_map(OrderedVisitor)
    }
}

/// One entry of `features`.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct Feature {
    pub dtype: String,
    pub shape: Vec<usize>,
    /// A list of names, `null`, or (older datasets) a map such as `{"motors": [...]}`.
    pub names: serde_json::Value,
    /// Video encoding facts (v3.0 `info`; v2.x wrote the same under `video_info` or `info`).
    #[serde(default, alias = "video_info", skip_serializing_if = "Option::is_none")]
    pub info: Option<VideoInfo>,
}

/// A video feature's `info`, with LeRobot 0.6.1's keys in its order.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct VideoInfo {
    #[serde(rename = "video.height", default)]
    pub height: Option<u32>,
    #[serde(rename = "video.width", default)]
    pub width: Option<u32>,
    #[serde(rename = "video.codec", default)]
    pub codec: Option<String>,
    #[serde(rename = "video.pix_fmt", default)]
    pub pix_fmt: Option<String>,
    /// A number as written (LeRobot writes an integer; some datasets a float).
    #[serde(rename = "video.fps", default)]
    pub fps: Option<serde_json::Number>,
    #[serde(rename = "video.channels", default)]
    pub channels: Option<u32>,
    #[serde(default)]
    pub has_audio: Option<bool>,
    #[serde(rename = "video.g", default)]
    pub gop: Option<u32>,
    #[serde(rename = "video.crf", default)]
    pub crf: Option<u32>,
    #[serde(rename = "video.preset", default)]
    pub preset: Option<serde_json::Value>,
    #[serde(rename = "video.fast_decode", default)]
    pub fast_decode: Option<u32>,
    #[serde(rename = "video.video_backend", default)]
    pub video_backend: Option<String>,
    #[serde(rename = "video.extra_options", default)]
    pub extra_options: Option<serde_json::Value>,
    #[serde(default)]
    pub is_depth_map: Option<bool>,
}

impl Feature {
    /// A float32 vector feature such as `observation.state`.
    pub fn vector(names: &[String]) -> Self {
        Feature { dtype: "float32".into(), shape: vec![names.len()], names: serde_json::json!(names), info: None }
    }

    /// A scalar bookkeeping column (`timestamp`, `index`, ...).
    pub fn scalar(dtype: &str) -> Self {
        Feature { dtype: dtype.into(), shape: vec![1], names: serde_json::Value::Null, info: None }
    }

    /// An RGB camera stored as video.
    pub fn video(height: u32, width: u32, fps: u32, codec: &str, gop: u32) -> Self {
        Feature {
            dtype: "video".into(),
            shape: vec![height as usize, width as usize, 3],
            names: serde_json::json!(["height", "width", "channels"]),
            info: Some(VideoInfo {
                height: Some(height),
                width: Some(width),
                codec: Some(codec.into()),
                pix_fmt: Some("yuv420p".into()),
                fps: Some(fps.into()),
                channels: Some(3),
                has_audio: Some(false),
                gop: Some(gop),
                crf: None,
                preset: None,
                fast_decode: Some(0),
                video_backend: Some("pyav".into()),
                extra_options: Some(serde_json::json!({})),
                is_depth_map: Some(false),
            }),
        }
    }

    /// Number of values per frame (product of the shape).
    pub fn width(&self) -> usize {
        self.shape.iter().product()
    }
}

impl DatasetInfo {
    /// Reads `root/meta/info.json` and checks that its version is one this crate reads.
    pub fn load(root: &Path) -> Result<(Self, CodebaseVersion)> {
        let path = root.join("meta/info.json");
        let bytes = std::fs::read(&path).map_err(|e| DataError::io(&path, e))?;
        Self::from_json(&path, &bytes)
    }

    /// Parses the `meta/info.json` at `path` (named in errors) and checks that its version is one this crate reads.
    pub fn from_json(path: &Path, bytes: &[u8]) -> Result<(Self, CodebaseVersion)> {
        let invalid = |reason: String| DataError::InvalidJson { path: path.to_path_buf(), reason };
        let raw: serde_json::Value = serde_json::from_slice(bytes).map_err(|e| invalid(e.to_string()))?;
        let found = raw.get("codebase_version").and_then(|v| v.as_str()).unwrap_or("<missing>").to_string();
        let version = match found.as_str() {
            CODEBASE_VERSION_V30 => CodebaseVersion::V30,
            CODEBASE_VERSION_V21 => CodebaseVersion::V21,
            _ => return Err(DataError::UnknownVersion { path: path.to_path_buf(), found }),
        };
        let info = serde_json::from_value(raw).map_err(|e| invalid(e.to_string()))?;
        Ok((info, version))
    }

    pub fn save(&self, root: &Path) -> Result<()> {
        write_json(&root.join("meta/info.json"), self)
    }
}

/// Fills a LeRobot path template such as `data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet`.
/// Integer placeholders may carry a `:0Nd` width; `{video_key}` is a string.
pub fn fill_template(template: &str, ints: &[(&str, u64)], video_key: Option<&str>) -> String {
    let mut out = String::with_capacity(template.len() + 16);
    let mut rest = template;
    while let Some(open) = rest.find('{') {
        out.push_str(&rest[..open]);
        let Some(close) = rest[open..].find('}') else {
            out.push_str(&rest[open..]);
            return out;
        };
        let spec = &rest[open + 1..open + close];
        let (name, format) = spec.split_once(':').unwrap_or((spec, ""));
        if name == "video_key" {
            out.push_str(video_key.unwrap_or_default());
        } else if let Some((_, v)) = ints.iter().find(|(n, _)| *n == name) {
            let width: usize = format.trim_start_matches('0').trim_end_matches('d').parse().unwrap_or(0);
            out.push_str(&format!("{v:0width$}"));
        } else {
            out.push_str(&rest[open..=open + close]);
        }
        rest = &rest[open + close + 1..];
    }
    out.push_str(rest);
    out
}

/// The v3.0 path of a data, video or episodes-metadata file.
pub fn v30_path(root: &Path, template: &str, chunk_index: u64, file_index: u64, video_key: Option<&str>) -> PathBuf {
    root.join(fill_template(template, &[("chunk_index", chunk_index), ("file_index", file_index)], video_key))
}

pub(crate) fn write_json(path: &Path, value: &impl Serialize) -> Result<()> {
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir).map_err(|e| DataError::io(dir, e))?;
    }
    let text = serde_json::to_string_pretty(value)
        .map_err(|e| DataError::InvalidJson { path: path.to_path_buf(), reason: e.to_string() })?;
    fedvla_fs::write_atomic(path, text.as_bytes()).map_err(|e| DataError::io(path, e))
}
