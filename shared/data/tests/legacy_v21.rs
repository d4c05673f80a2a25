//! Reading the legacy v2.1 layout: JSON-lines metadata, one parquet and one mp4 per episode, and
//! vector columns stored as variable-length lists (as older `datasets` versions wrote them).

mod common;

use std::collections::BTreeMap;
use std::sync::Arc;

use arrow_array::{ArrayRef, Float32Array, Int64Array, ListArray, RecordBatch};
use arrow_schema::{DataType, Field, Schema};
use fedvla_data::video::CameraVideoWriter;
use fedvla_data::{CodebaseVersion, Episode, LeRobotDataset, VideoEncoding};
use parquet::arrow::ArrowWriter;
use serde_json::json;

const SIZE: u32 = 32;

fn list_f32(rows: Vec<&[f32]>) -> ArrayRef {
    let lengths = rows.iter().map(|r| r.len());
    let offsets = arrow_buffer::OffsetBuffer::from_lengths(lengths);
    let values = Float32Array::from(rows.concat());
    Arc::new(ListArray::new(Arc::new(Field::new("item", DataType::Float32, true)), offsets, Arc::new(values), None))
}

fn write_episode_parquet(
    path: &std::path::Path,
    episode: &Episode,
    episode_index: i64,
    first_index: i64,
    task_index: i64,
) {
    let n = episode.frames.len();
    let columns: Vec<(&str, ArrayRef)> = vec![
        ("observation.state", list_f32(episode.frames.iter().map(|f| f.state.as_slice()).collect())),
        ("action", list_f32(episode.frames.iter().map(|f| f.action.as_slice()).collect())),
        ("timestamp", Arc::new(Float32Array::from((0..n).map(|i| i as f32 / 30.0).collect::<Vec<_>>()))),
        ("frame_index", Arc::new(Int64Array::from((0..n as i64).collect::<Vec<_>>()))),
        ("episode_index", Arc::new(Int64Array::from(vec![episode_index; n]))),
        ("index", Arc::new(Int64Array::from((first_index..first_index + n as i64).collect::<Vec<_>>()))),
        ("task_index", Arc::new(Int64Array::from(vec![task_index; n]))),
    ];
    let schema = Arc::new(Schema::new(
        columns.iter().map(|(name, a)| Field::new(*name, a.data_type().clone(), true)).collect::<Vec<_>>(),
    ));
    let batch = RecordBatch::try_new(schema.clone(), columns.into_iter().map(|(_, a)| a).collect()).expect("batch");
    std::fs::create_dir_all(path.parent().expect("parent")).expect("mkdir");
    let mut writer = ArrowWriter::try_new(std::fs::File::create(path).expect("create"), schema, None).expect("writer");
    writer.write(&batch).expect("write");
    writer.close().expect("close");
}

#[test]
fn reads_v21_layout() {
    let dir = common::temp_dir("v21");
    let root = dir.join("ds");
    let episodes = common::episodes(2, 15, SIZE);
    let names: Vec<String> = ["shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll", "gripper"]
        .iter()
        .map(|j| format!("{j}.pos"))
        .collect();
    let camera = json!({"dtype": "video", "shape": [SIZE, SIZE, 3], "names": ["height", "width", "channels"],
               "info": {"video.fps": 30.0, "video.height": SIZE, "video.width": SIZE, "video.channels": 3, "video.codec": "h264",
                        "video.pix_fmt": "yuv420p", "video.is_depth_map": false, "has_audio": false}});
    let info = json!({
        "codebase_version": "v2.1", "robot_type": "so100", "total_episodes": 2, "total_frames": 30, "total_tasks": 2,
        "total_videos": 4, "total_chunks": 1, "chunks_size": 1000, "fps": 30, "splits": {"train": "0:2"},
        "data_path": "data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet",
        "video_path": "videos/chunk-{episode_chunk:03d}/{video_key}/episode_{episode_index:06d}.mp4",
        "features": {
            "action": {"dtype": "float32", "shape": [6], "names": names},
            "observation.state": {"dtype": "float32", "shape": [6], "names": names},
            "observation.images.top": camera.clone(), "observation.images.wrist": camera,
            "timestamp": {"dtype": "float32", "shape": [1], "names": null},
            "frame_index": {"dtype": "int64", "shape": [1], "names": null},
            "episode_index": {"dtype": "int64", "shape": [1], "names": null},
            "index": {"dtype": "int64", "shape": [1], "names": null},
            "task_index": {"dtype": "int64", "shape": [1], "names": null}
        }
    });
    std::fs::create_dir_all(root.join("meta")).expect("mkdir");
    std::fs::write(root.join("meta/info.json"), serde_json::to_string_pretty(&info).expect("json")).expect("info");
    let tasks: String =
        common::TASKS.iter().enumerate().map(|(i, t)| format!("{}\n", json!({"task_index": i, "task": t}))).collect();
    std::fs::write(root.join("meta/tasks.jsonl"), tasks).expect("tasks");
    let lines: String = episodes
        .iter()
        .enumerate()
        .map(|(i, e)| format!("{}\n", json!({"episode_index": i, "tasks": [e.task], "length": e.frames.len()})))
        .collect();
    std::fs::write(root.join("meta/episodes.jsonl"), lines).expect("episodes");
    for (e, episode) in episodes.iter().enumerate() {
        write_episode_parquet(
            &root.join(format!("data/chunk-000/episode_{e:06}.parquet")),
            episode,
            e as i64,
            (e * 15) as i64,
            (e % 2) as i64,
        );
        for (c, key) in ["observation.images.top", "observation.images.wrist"].iter().enumerate() {
            let path = root.join(format!("videos/chunk-000/{key}/episode_{e:06}.mp4"));
            let mut video = CameraVideoWriter::create(&path, SIZE, SIZE, 30, VideoEncoding::default()).expect("video");
            for frame in &episode.frames {
                video.push_frame(&frame.images[c]).expect("frame");
            }
            video.finish().expect("finish");
        }
    }

    let ds = LeRobotDataset::open(&root).expect("open v2.1");
    assert_eq!(ds.version(), CodebaseVersion::V21);
    assert_eq!((ds.len(), ds.episodes().len()), (30, 2));
    assert_eq!(ds.tasks(), &common::TASKS.map(String::from)[..]);
    assert_eq!((ds.episodes()[1].dataset_from_index, ds.episodes()[1].dataset_to_index), (15, 30));
    assert!(ds.stats().is_none());
    let deltas = BTreeMap::from([("action".to_string(), vec![0.0, 1.0 / 30.0, 2.0 / 30.0])]);
    let sample = ds.get(15 + 13, &deltas).expect("get");
    assert_eq!(sample.task, common::TASKS[1]);
    assert_eq!(sample.vectors["observation.state"], vec![episodes[1].frames[13].state.clone()]);
    assert_eq!(sample.vectors["action"][2], episodes[1].frames[14].action);
    assert_eq!(sample.is_pad["action_is_pad"], vec![false, false, true]);
    let decoded = &sample.images["observation.images.wrist"][0];
    assert!(decoded.mean_abs_diff(&episodes[1].frames[13].images[1]) < 8.0);
    std::fs::remove_dir_all(&dir).expect("cleanup");
}
