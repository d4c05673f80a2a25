//! Write -> read round trip: exact state/action, frames within codec tolerance, stats that match the
//! data, and LeRobot's delta_timestamps/padding semantics.

mod common;

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};

use fedvla_data::stats::FeatureStats;
use fedvla_data::{CodebaseVersion, DatasetSpec, DatasetWriter, LeRobotDataset, WriteProgress};

#[test]
fn written_dataset_reads_back() {
    let dir = common::temp_dir("roundtrip");
    let episodes = common::episodes(3, 20, 64);
    let root = common::write_dataset(&dir, "ds", &episodes, 64);
    let ds = LeRobotDataset::open(&root).expect("open");

    assert_eq!(ds.version(), CodebaseVersion::V30);
    assert_eq!(ds.len(), 60);
    assert_eq!(ds.tasks(), &common::TASKS.map(String::from)[..]);
    assert_eq!(ds.episodes().len(), 3);
    assert_eq!(ds.camera_keys(), vec!["observation.images.top", "observation.images.wrist"]);

    let no_deltas = BTreeMap::new();
    let mut worst_mean_abs_error = 0f64;
    for (e, episode) in episodes.iter().enumerate() {
        let meta = &ds.episodes()[e];
        assert_eq!(
            (meta.dataset_from_index, meta.length, meta.tasks.clone()),
            (e * 20, 20, vec![episode.task.clone()])
        );
        for (f, frame) in episode.frames.iter().enumerate() {
            let sample = ds.get(e * 20 + f, &no_deltas).expect("get");
            assert_eq!((sample.episode_index, sample.frame_index, sample.task.as_str()), (e, f, episode.task.as_str()));
            assert_eq!(sample.vectors["observation.state"], vec![frame.state.clone()], "state bit-exact");
            assert_eq!(sample.vectors["action"], vec![frame.action.clone()], "action bit-exact");
            for (c, key) in ds.camera_keys().iter().enumerate() {
                let decoded = &sample.images[key][0];
                assert_eq!((decoded.width, decoded.height), (64, 64));
                worst_mean_abs_error = worst_mean_abs_error.max(decoded.mean_abs_diff(&frame.images[c]));
            }
        }
    }
    assert!(worst_mean_abs_error < 8.0, "decoded frames differ by {worst_mean_abs_error}/255 on average");

    // stats.json equals stats recomputed from the frames.
    let stats = ds.stats().expect("stats.json");
    for (key, pick) in [("observation.state", 0usize), ("action", 1)] {
        let rows: Vec<Vec<f64>> = episodes
            .iter()
            .flat_map(|e| &e.frames)
            .map(|f| if pick == 0 { &f.state } else { &f.action }.iter().map(|&v| f64::from(v)).collect())
            .collect();
        let expected = FeatureStats::from_rows(&rows, 6);
        let stored = &stats[key];
        assert_eq!(stored.count, 60);
        for d in 0..6 {
            assert!((stored.mean[d] - expected.mean[d]).abs() < 1e-9, "{key} mean");
            assert!((stored.std[d] - expected.std[d]).abs() < 1e-9, "{key} std");
            assert_eq!((stored.min[d], stored.max[d]), (expected.min[d], expected.max[d]), "{key} min/max");
        }
    }
    assert_eq!(stats["observation.images.top"].shape, vec![3, 1, 1]);

    // Each episode's own stats (the episodes parquet's stats/<feature>/<stat> columns) equal its recomputed ones.
    for (e, episode) in episodes.iter().enumerate() {
        let own = &ds.episodes()[e].stats;
        let rows: Vec<Vec<f64>> =
            episode.frames.iter().map(|f| f.state.iter().map(|&v| f64::from(v)).collect()).collect();
        let expected = FeatureStats::from_rows(&rows, 6);
        let stored = &own["observation.state"];
        assert_eq!((stored.count, stored.shape.clone()), (20, vec![6]), "episode {e}");
        for d in 0..6 {
            assert!((stored.mean[d] - expected.mean[d]).abs() < 1e-9, "episode {e} state mean");
            assert_eq!((stored.min[d], stored.max[d]), (expected.min[d], expected.max[d]), "episode {e} state min/max");
        }
        assert_eq!(own["observation.images.wrist"].shape, vec![3, 1, 1], "episode {e}");
        assert!(own.contains_key("action"), "episode {e}");
    }
    std::fs::remove_dir_all(&dir).expect("cleanup");
}

#[test]
fn delta_timestamps_pad_past_episode_bounds() {
    let dir = common::temp_dir("deltas");
    let episodes = common::episodes(2, 20, 32);
    let root = common::write_dataset(&dir, "ds", &episodes, 32);
    let ds = LeRobotDataset::open(&root).expect("open");
    let fps = 30.0;
    let deltas = BTreeMap::from([
        ("action".to_string(), (0..10).map(|i| i as f64 / fps).collect::<Vec<_>>()),
        ("observation.images.top".to_string(), vec![-1.0 / fps, 0.0]),
    ]);

    // Frame 15 of episode 1: actions 15..19 are real, 20..24 repeat frame 19 and are padded.
    let sample = ds.get(20 + 15, &deltas).expect("get");
    let pad = &sample.is_pad["action_is_pad"];
    assert_eq!(pad, &(0..10).map(|i| 15 + i >= 20).collect::<Vec<_>>());
    let actions = &sample.vectors["action"];
    for (i, row) in actions.iter().enumerate() {
        assert_eq!(row, &episodes[1].frames[(15 + i).min(19)].action);
    }
    assert_eq!(sample.is_pad["observation.images.top_is_pad"], vec![false, false]);
    // The -1 frame is the previous frame, decoded from the same file.
    let previous = ds.get(20 + 14, &BTreeMap::new()).expect("get");
    assert_eq!(sample.images["observation.images.top"][0], previous.images["observation.images.top"][0]);
    assert!(!sample.is_pad.contains_key("observation.state_is_pad"));
    let typo = BTreeMap::from([("actions".to_string(), vec![0.0])]);
    assert!(ds.get(0, &typo).is_err(), "an unknown delta_timestamps key is an error, not ignored");

    // First frame of episode 1: the -1 camera frame is padded with the episode's own first frame.
    let first = ds.get(20, &deltas).expect("get");
    assert_eq!(first.is_pad["observation.images.top_is_pad"], vec![true, false]);
    assert_eq!(first.images["observation.images.top"][0], first.images["observation.images.top"][1]);
    std::fs::remove_dir_all(&dir).expect("cleanup");
}

#[test]
fn progress_reports_every_frame() {
    let dir = common::temp_dir("progress");
    let episodes = common::episodes(2, 5, 32);
    let seen: Arc<Mutex<Vec<WriteProgress>>> = Arc::default();
    let sink = seen.clone();
    let mut writer = DatasetWriter::create(dir.join("ds"), DatasetSpec::so100(common::cameras(32)))
        .expect("create")
        .with_progress(move |p| sink.lock().expect("lock").push(*p));
    for ep in &episodes {
        writer.add_episode(ep).expect("add");
    }
    writer.finish().expect("finish");
    let seen = seen.lock().expect("lock");
    assert_eq!(seen.len(), 10);
    assert_eq!(
        seen.last().map(|p| (p.episode_index, p.episode_frames_done, p.episode_length, p.total_frames_written)),
        Some((1, 5, 5, 10))
    );
    std::fs::remove_dir_all(&dir).expect("cleanup");
}
