//! What a dataset is made of, as LeRobot v3.0 lays it out: its spec (cameras, joints, files), where each
//! episode's rows and video frames live and their per-episode statistics, `features` in LeRobot's order, and the
//! metadata tables `meta/tasks.parquet` and `meta/episodes/chunk-XXX/file-XXX.parquet`.

use std::path::Path;

use serde_json::json;

use crate::error::Result;
use crate::info::{
    self, CHUNKS_SIZE, DATA_FILES_SIZE_IN_MB, EPISODES_PATH_V30, Feature, Features, VIDEO_FILES_SIZE_IN_MB,
};
use crate::stats::{FeatureStats, QUANTILES};
use crate::table;
use crate::video::VideoEncoding;

/// SO-100 joint order (LeRobot's `so100_follower` names).
pub const SO100_JOINTS: [&str; 6] =
    ["shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll", "gripper"];

/// The per-frame bookkeeping columns every LeRobot dataset has, with their dtypes.
pub(super) const INDEX_FEATURES: [(&str, &str); 5] = [
    ("timestamp", "float32"),
    ("frame_index", "int64"),
    ("episode_index", "int64"),
    ("index", "int64"),
    ("task_index", "int64"),
];

/// A camera: `name` becomes the feature `observation.images.<name>`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct CameraSpec {
    pub name: String,
    pub height: u32,
    pub width: u32,
}

impl CameraSpec {
    pub fn new(name: &str, height: u32, width: u32) -> Self {
        Self { name: name.into(), height, width }
    }

    pub fn key(&self) -> String {
        format!("observation.images.{}", self.name)
    }
}

/// What a dataset holds; fixed when it is created.
#[derive(Debug, Clone, PartialEq)]
pub struct DatasetSpec {
    pub fps: u32,
    pub robot_type: String,
    /// Names of the state and action entries (the same joints, e.g. `shoulder_pan.pos`).
    pub joint_names: Vec<String>,
    pub cameras: Vec<CameraSpec>,
    pub video: VideoEncoding,
    /// A new data parquet file is started after an episode once the current one reaches this size.
    pub data_files_size_in_mb: u64,
    /// A new mp4 per camera is started after an episode once the current one reaches this size.
    pub video_files_size_in_mb: u64,
}

impl DatasetSpec {
    /// SO-100 at 30 fps with LeRobot's default file sizes.
    pub fn so100(cameras: Vec<CameraSpec>) -> Self {
        Self {
            fps: 30,
            robot_type: "so100".into(),
            joint_names: SO100_JOINTS.iter().map(|j| format!("{j}.pos")).collect(),
            cameras,
            video: VideoEncoding::default(),
            data_files_size_in_mb: DATA_FILES_SIZE_IN_MB,
            video_files_size_in_mb: VIDEO_FILES_SIZE_IN_MB,
        }
    }
}

/// A (chunk, file) position in LeRobot's `chunk-XXX/file-XXX` naming.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub(super) struct FilePosition {
    pub(super) chunk: u64,
    pub(super) file: u64,
}

impl FilePosition {
    pub(super) fn next(self) -> Self {
        if self.file + 1 >= CHUNKS_SIZE {
            FilePosition { chunk: self.chunk + 1, file: 0 }
        } else {
            FilePosition { chunk: self.chunk, file: self.file + 1 }
        }
    }
}

/// An episode as the per-episode table records it.
#[derive(Debug, Clone)]
pub(super) struct EpisodeRecord {
    pub(super) index: usize,
    pub(super) task: String,
    pub(super) length: usize,
    pub(super) data_position: FilePosition,
    pub(super) dataset_from_index: u64,
    /// Per camera: file position and from/to timestamps inside that file.
    pub(super) videos: Vec<(FilePosition, f64, f64)>,
    /// Per feature (in `features` order): this episode's stats.
    pub(super) stats: Vec<FeatureStats>,
}

pub(super) fn write_tasks(root: &Path, tasks: &[String]) -> Result<()> {
    let path = root.join("meta/tasks.parquet");
    let columns: Vec<(&str, arrow_array::ArrayRef)> = vec![
        ("task_index", std::sync::Arc::new(arrow_array::Int64Array::from_iter_values(0..tasks.len() as i64))),
        ("task", std::sync::Arc::new(arrow_array::StringArray::from(tasks.to_vec()))),
    ];
    // LeRobot reads this with pandas and expects `task` to come back as the index.
    let pandas = json!({
        "index_columns": ["task"],
        "column_indexes": [{"name": null, "field_name": null, "pandas_type": "unicode", "numpy_type": "object", "metadata": {"encoding": "UTF-8"}}],
        "columns": [
            {"name": "task_index", "field_name": "task_index", "pandas_type": "int64", "numpy_type": "int64", "metadata": null},
            {"name": "task", "field_name": "task", "pandas_type": "unicode", "numpy_type": "object", "metadata": null}
        ],
        "attributes": {},
        "creator": {"library": "fedvla-data", "version": env!("CARGO_PKG_VERSION")},
        "pandas_version": "2.3.3"
    });
    table::write_parquet(&path, columns, vec![("pandas", pandas.to_string())])
}

pub(super) fn write_episodes(
    root: &Path,
    episodes: &[EpisodeRecord],
    cameras: &[&CameraSpec],
    features: &Features,
) -> Result<()> {
    let path = info::v30_path(root, EPISODES_PATH_V30, 0, 0, None);
    let eps = &episodes;
    let i64_col = |f: &dyn Fn(&EpisodeRecord) -> i64| -> arrow_array::ArrayRef {
        std::sync::Arc::new(arrow_array::Int64Array::from(eps.iter().map(f).collect::<Vec<_>>()))
    };
    let f64_col = |f: &dyn Fn(&EpisodeRecord) -> f64| -> arrow_array::ArrayRef {
        std::sync::Arc::new(arrow_array::Float64Array::from(eps.iter().map(f).collect::<Vec<_>>()))
    };
    let mut names: Vec<String> = Vec::new();
    let mut arrays: Vec<arrow_array::ArrayRef> = Vec::new();
    let mut push = |name: String, array: arrow_array::ArrayRef| {
        names.push(name);
        arrays.push(array);
    };
    push("episode_index".into(), i64_col(&|e| e.index as i64));
    push("tasks".into(), table::string_lists(&eps.iter().map(|e| vec![e.task.clone()]).collect::<Vec<_>>()));
    push("length".into(), i64_col(&|e| e.length as i64));
    push("data/chunk_index".into(), i64_col(&|e| e.data_position.chunk as i64));
    push("data/file_index".into(), i64_col(&|e| e.data_position.file as i64));
    push("dataset_from_index".into(), i64_col(&|e| e.dataset_from_index as i64));
    push("dataset_to_index".into(), i64_col(&|e| (e.dataset_from_index + e.length as u64) as i64));
    for (ci, cam) in cameras.iter().enumerate() {
        let key = cam.key();
        push(format!("videos/{key}/chunk_index"), i64_col(&|e| e.videos[ci].0.chunk as i64));
        push(format!("videos/{key}/file_index"), i64_col(&|e| e.videos[ci].0.file as i64));
        push(format!("videos/{key}/from_timestamp"), f64_col(&|e| e.videos[ci].1));
        push(format!("videos/{key}/to_timestamp"), f64_col(&|e| e.videos[ci].2));
    }
    for (fi, (key, _)) in features.0.iter().enumerate() {
        let shape = eps[0].stats[fi].shape.clone();
        let stat_rows = |name: &str| -> Vec<&[f64]> {
            eps.iter()
                .map(|e| e.stats[fi].named_values().into_iter().find(|(n, _)| *n == name).map_or(&[][..], |(_, v)| v))
                .collect()
        };
        for name in ["min", "max", "mean", "std"] {
            push(format!("stats/{key}/{name}"), table::nested_f64_list(&stat_rows(name), &shape));
        }
        push(
            format!("stats/{key}/count"),
            table::count_list(&eps.iter().map(|e| e.stats[fi].count as i64).collect::<Vec<_>>()),
        );
        for (name, _) in QUANTILES {
            push(format!("stats/{key}/{name}"), table::nested_f64_list(&stat_rows(name), &shape));
        }
    }
    push("meta/episodes/chunk_index".into(), i64_col(&|_| 0));
    push("meta/episodes/file_index".into(), i64_col(&|_| 0));
    let columns = names.iter().map(String::as_str).zip(arrays).collect();
    table::write_parquet(&path, columns, Vec::new())
}

/// `features` in LeRobot's order: action, observation.state, cameras, then the bookkeeping columns.
pub(super) fn build_features(spec: &DatasetSpec) -> Features {
    let mut features = vec![
        ("action".to_string(), Feature::vector(&spec.joint_names)),
        ("observation.state".to_string(), Feature::vector(&spec.joint_names)),
    ];
    for cam in &spec.cameras {
        features.push((cam.key(), Feature::video(cam.height, cam.width, spec.fps, "h264", spec.video.gop)));
    }
    for (name, dtype) in INDEX_FEATURES {
        features.push((name.to_string(), Feature::scalar(dtype)));
    }
    Features(features)
}

/// The `huggingface` schema metadata `datasets` writes into LeRobot's data files.
pub(super) fn huggingface_metadata(dim: usize) -> String {
    let vector = json!({"feature": {"dtype": "float32", "_type": "Value"}, "length": dim, "_type": "List"});
    let value = |dtype: &str| json!({"dtype": dtype, "_type": "Value"});
    let mut features = serde_json::Map::new();
    features.insert("action".into(), vector.clone());
    features.insert("observation.state".into(), vector);
    for (name, dtype) in INDEX_FEATURES {
        features.insert(name.into(), value(dtype));
    }
    json!({"info": {"features": features}}).to_string()
}
