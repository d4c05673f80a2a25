//! Our output matches LeRobot v3.0 field for field. The expected values below were taken from the
//! dataset LeRobot 0.6.1 itself writes (`make_sample_dataset.py` of tools/lerobot-check, inspected
//! with pyarrow 26): info.json keys and feature entries, parquet column names and arrow types
//! (spelled the way pyarrow prints them), and the schema metadata LeRobot's loaders rely on.

mod common;

use std::fs::File;
use std::path::Path;

use arrow_schema::{DataType, Schema};
use parquet::arrow::arrow_reader::ParquetRecordBatchReaderBuilder;
use serde_json::Value;

const INFO_KEYS: [&str; 13] = [
    "codebase_version",
    "fps",
    "features",
    "total_episodes",
    "total_frames",
    "total_tasks",
    "chunks_size",
    "data_files_size_in_mb",
    "video_files_size_in_mb",
    "data_path",
    "video_path",
    "robot_type",
    "splits",
];

const VIDEO_INFO_KEYS: [&str; 14] = [
    "video.height",
    "video.width",
    "video.codec",
    "video.pix_fmt",
    "video.fps",
    "video.channels",
    "has_audio",
    "video.g",
    "video.crf",
    "video.preset",
    "video.fast_decode",
    "video.video_backend",
    "video.extra_options",
    "is_depth_map",
];

const DATA_COLUMNS: [(&str, &str); 7] = [
    ("action", "fixed_size_list<element: float>[6]"),
    ("observation.state", "fixed_size_list<element: float>[6]"),
    ("timestamp", "float"),
    ("frame_index", "int64"),
    ("episode_index", "int64"),
    ("index", "int64"),
    ("task_index", "int64"),
];

const TASKS_COLUMNS: [(&str, &str); 2] = [("task_index", "int64"), ("task", "string")];

const EPISODE_COLUMNS_HEAD: [(&str, &str); 15] = [
    ("episode_index", "int64"),
    ("tasks", "list<element: string>"),
    ("length", "int64"),
    ("data/chunk_index", "int64"),
    ("data/file_index", "int64"),
    ("dataset_from_index", "int64"),
    ("dataset_to_index", "int64"),
    ("videos/observation.images.top/chunk_index", "int64"),
    ("videos/observation.images.top/file_index", "int64"),
    ("videos/observation.images.top/from_timestamp", "double"),
    ("videos/observation.images.top/to_timestamp", "double"),
    ("videos/observation.images.wrist/chunk_index", "int64"),
    ("videos/observation.images.wrist/file_index", "int64"),
    ("videos/observation.images.wrist/from_timestamp", "double"),
    ("videos/observation.images.wrist/to_timestamp", "double"),
];

/// Per-episode stats columns `stats/<feature>/<stat>`: features in this order, each stat's type.
const STATS_FEATURES: [(&str, &str); 9] = [
    ("action", "list<element: double>"),
    ("observation.state", "list<element: double>"),
    ("observation.images.top", "list<element: list<element: list<element: double>>>"),
    ("observation.images.wrist", "list<element: list<element: list<element: double>>>"),
    ("timestamp", "list<element: double>"),
    ("frame_index", "list<element: double>"),
    ("episode_index", "list<element: double>"),
    ("index", "list<element: double>"),
    ("task_index", "list<element: double>"),
];
const STATS_NAMES: [&str; 10] = ["min", "max", "mean", "std", "count", "q01", "q10", "q50", "q90", "q99"];

/// An arrow type as pyarrow prints it.
fn pyarrow_type(t: &DataType) -> String {
    match t {
        DataType::Int64 => "int64".into(),
        DataType::Float32 => "float".into(),
        DataType::Float64 => "double".into(),
        DataType::Utf8 => "string".into(),
        DataType::List(f) => format!("list<{}: {}>", f.name(), pyarrow_type(f.data_type())),
        DataType::FixedSizeList(f, n) => format!("fixed_size_list<{}: {}>[{n}]", f.name(), pyarrow_type(f.data_type())),
        other => format!("{other:?}"),
    }
}

fn schema(path: &Path) -> Schema {
    let file = File::open(path).expect("open parquet");
    ParquetRecordBatchReaderBuilder::try_new(file).expect("parquet").schema().as_ref().clone()
}

fn columns(schema: &Schema) -> Vec<(String, String)> {
    schema.fields().iter().map(|f| (f.name().clone(), pyarrow_type(f.data_type()))).collect()
}

fn owned(cols: &[(&str, &str)]) -> Vec<(String, String)> {
    cols.iter().map(|(n, t)| (n.to_string(), t.to_string())).collect()
}

#[test]
fn layout_matches_lerobot_v30() {
    let dir = common::temp_dir("layout");
    let root = common::write_dataset(&dir, "ds", &common::episodes(2, 20, 32), 32);

    // meta/info.json
    let info: Value =
        serde_json::from_str(&std::fs::read_to_string(root.join("meta/info.json")).expect("info.json")).expect("json");
    let mut keys: Vec<&str> = info.as_object().expect("object").keys().map(String::as_str).collect();
    keys.sort_unstable();
    let mut expected_keys = INFO_KEYS.to_vec();
    expected_keys.sort();
    assert_eq!(keys, expected_keys, "info.json keys");
    assert_eq!(info["codebase_version"], "v3.0");
    assert_eq!(info["fps"], 30);
    assert_eq!(info["robot_type"], "so100");
    assert_eq!(
        (info["total_episodes"].clone(), info["total_frames"].clone(), info["total_tasks"].clone()),
        (2.into(), 40.into(), 2.into())
    );
    assert_eq!(
        (info["chunks_size"].clone(), info["data_files_size_in_mb"].clone(), info["video_files_size_in_mb"].clone()),
        (1000.into(), 100.into(), 200.into())
    );
    assert_eq!(info["data_path"], "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet");
    assert_eq!(info["video_path"], "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4");
    assert_eq!(info["splits"], serde_json::json!({"train": "0:2"}));

    let joints =
        ["shoulder_pan.pos", "shoulder_lift.pos", "elbow_flex.pos", "wrist_flex.pos", "wrist_roll.pos", "gripper.pos"];
    let features = &info["features"];
    for key in ["action", "observation.state"] {
        assert_eq!(features[key], serde_json::json!({"dtype": "float32", "shape": [6], "names": joints}), "{key}");
    }
    for (key, dtype) in [
        ("timestamp", "float32"),
        ("frame_index", "int64"),
        ("episode_index", "int64"),
        ("index", "int64"),
        ("task_index", "int64"),
    ] {
        assert_eq!(features[key], serde_json::json!({"dtype": dtype, "shape": [1], "names": null}), "{key}");
    }
    for key in ["observation.images.top", "observation.images.wrist"] {
        let cam = &features[key];
        assert_eq!(cam["dtype"], "video");
        assert_eq!(cam["shape"], serde_json::json!([32, 32, 3]));
        assert_eq!(cam["names"], serde_json::json!(["height", "width", "channels"]));
        let mut video_keys: Vec<&str> =
            cam["info"].as_object().expect("video info").keys().map(String::as_str).collect();
        let mut expected = VIDEO_INFO_KEYS.to_vec();
        video_keys.sort();
        expected.sort();
        assert_eq!(video_keys, expected, "{key} info keys");
        assert_eq!((cam["info"]["video.height"].clone(), cam["info"]["video.width"].clone()), (32.into(), 32.into()));
        assert_eq!(cam["info"]["video.pix_fmt"], "yuv420p");
        assert_eq!(cam["info"]["video.codec"], "h264");
        assert_eq!(cam["info"]["video.fps"], 30);
        assert_eq!(cam["info"]["video.channels"], 3);
        assert_eq!(cam["info"]["has_audio"], false);
        assert_eq!(cam["info"]["is_depth_map"], false);
    }
    // LeRobot's order of the features in info.json: the recorded ones, then the five index columns.
    const FEATURE_ORDER: [&str; 9] = [
        "action",
        "observation.state",
        "observation.images.top",
        "observation.images.wrist",
        "timestamp",
        "frame_index",
        "episode_index",
        "index",
        "task_index",
    ];
    let order: Vec<String> = {
        let text = std::fs::read_to_string(root.join("meta/info.json")).expect("info.json");
        let mut found: Vec<(usize, String)> = FEATURE_ORDER
            .iter()
            .map(|n| (text.find(&format!("\"{n}\": {{")).expect("feature present"), n.to_string()))
            .collect();
        found.sort();
        found.into_iter().map(|(_, n)| n).collect()
    };
    assert_eq!(order, FEATURE_ORDER, "feature order");

    // meta/stats.json: every feature, each with the ten statistics; images per channel as [3][1][1].
    let stats: Value =
        serde_json::from_str(&std::fs::read_to_string(root.join("meta/stats.json")).expect("stats.json"))
            .expect("json");
    for (feature, _) in STATS_FEATURES {
        let mut names: Vec<&str> =
            stats[feature].as_object().expect("feature stats").keys().map(String::as_str).collect();
        let mut expected = STATS_NAMES.to_vec();
        names.sort();
        expected.sort();
        assert_eq!(names, expected, "stats.json {feature}");
        assert_eq!(stats[feature]["count"], serde_json::json!([40]));
    }
    assert!(stats["observation.images.top"]["mean"][2][0][0].is_number());
    assert_eq!(stats["action"]["std"].as_array().map(Vec::len), Some(6));

    // Parquet schemas.
    let data = schema(&root.join("data/chunk-000/file-000.parquet"));
    assert_eq!(columns(&data), owned(&DATA_COLUMNS), "data columns");
    let hf: Value =
        serde_json::from_str(data.metadata().get("huggingface").expect("huggingface metadata")).expect("json");
    assert_eq!(
        hf["info"]["features"]["action"],
        serde_json::json!({"feature": {"dtype": "float32", "_type": "Value"}, "length": 6, "_type": "List"})
    );

    let tasks = schema(&root.join("meta/tasks.parquet"));
    assert_eq!(columns(&tasks), owned(&TASKS_COLUMNS), "tasks columns");
    let pandas: Value = serde_json::from_str(tasks.metadata().get("pandas").expect("pandas metadata")).expect("json");
    assert_eq!(pandas["index_columns"], serde_json::json!(["task"]), "pandas must restore `task` as the index");

    let episodes = schema(&root.join("meta/episodes/chunk-000/file-000.parquet"));
    let mut expected = owned(&EPISODE_COLUMNS_HEAD);
    for (feature, list_type) in STATS_FEATURES {
        for stat in STATS_NAMES {
            let t = if stat == "count" { "list<element: int64>" } else { list_type };
            expected.push((format!("stats/{feature}/{stat}"), t.to_string()));
        }
    }
    expected.push(("meta/episodes/chunk_index".into(), "int64".into()));
    expected.push(("meta/episodes/file_index".into(), "int64".into()));
    assert_eq!(columns(&episodes), expected, "episodes columns");

    for cam in ["observation.images.top", "observation.images.wrist"] {
        assert!(root.join(format!("videos/{cam}/chunk-000/file-000.mp4")).is_file(), "{cam} mp4");
    }
    std::fs::remove_dir_all(&dir).expect("cleanup");
}
