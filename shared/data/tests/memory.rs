//! A dataset read from files in memory (what a browser page picked and read), through the one reader: it loads
//! only the files the reader names, stage by stage, and packs the same shard as the dataset's directory.

mod common;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use fedvla_data::video::{DecodedFrames, FrameSource, Mp4Frames, VideoFile};
use fedvla_data::{
    DatasetFiles, DatasetMeta, LeRobotDataset, MemoryFiles, PartitionConfig, PartitionStrategy, ShardSpec,
    episode_tasks, pack_shard, partition,
};

const SPEC: ShardSpec = ShardSpec { image_width: 16, image_height: 16, tokenizer_max_length: 8, pad_token_id: 0 };

/// Every file under `root`: (path relative to it, size), as a directory picker lists them.
fn listing(root: &Path) -> Vec<(PathBuf, u64)> {
    let mut out = Vec::new();
    let mut stack = vec![root.to_path_buf()];
    while let Some(dir) = stack.pop() {
        for entry in std::fs::read_dir(&dir).unwrap() {
            let path = entry.unwrap().path();
            if path.is_dir() {
                stack.push(path);
            } else {
                let size = std::fs::metadata(&path).unwrap().len();
                out.push((path.strip_prefix(root).unwrap().to_path_buf(), size));
            }
        }
    }
    out
}

fn load(files: &mut MemoryFiles, root: &Path, path: &Path) {
    files.insert(path, std::fs::read(root.join(path)).unwrap()).unwrap();
}

#[test]
fn a_dataset_in_memory_reads_only_what_the_reader_names_and_packs_the_shard_its_directory_packs() {
    let dir = common::temp_dir("memory");
    let root = common::write_dataset(&dir, "ds", &common::episodes(4, 12, 32), 32);
    // What a LeRobot folder may hold besides: none of it is read.
    std::fs::write(root.join("README.md"), "# a dataset card").unwrap();
    std::fs::write(root.join("meta/notes.txt"), "private notes").unwrap();

    let mut files = MemoryFiles::new("ds", listing(&root));
    load(&mut files, &root, Path::new("meta/info.json"));
    let (_, version) = DatasetMeta::read_info(&files).unwrap();
    for path in DatasetMeta::files_to_read(version, &files).unwrap() {
        load(&mut files, &root, &path);
    }
    let meta = DatasetMeta::read(&files).unwrap();
    for path in meta.data_files.clone() {
        load(&mut files, &root, &path);
    }
    let videos: Vec<PathBuf> = meta.episodes.iter().flat_map(|e| e.videos.values().map(|v| v.path.clone())).collect();
    for path in &videos {
        if !files.is_loaded(path) {
            load(&mut files, &root, path);
        }
    }
    let read: Vec<String> = files.loaded().iter().map(|p| p.display().to_string()).collect();
    assert_eq!(
        read,
        [
            "data/chunk-000/file-000.parquet",
            "meta/episodes/chunk-000/file-000.parquet",
            "meta/info.json",
            "meta/stats.json",
            "meta/tasks.parquet",
            "videos/observation.images.top/chunk-000/file-000.mp4",
            "videos/observation.images.wrist/chunk-000/file-000.mp4",
        ]
    );

    // The page's part: decode the samples each episode's frames need (natively here; WebCodecs in a browser).
    let dataset = LeRobotDataset::from_meta(meta, &files, Box::new(DecodedFrames::default())).unwrap();
    let mut wanted: BTreeMap<PathBuf, Vec<f64>> = BTreeMap::new();
    for episode in dataset.episodes() {
        let indices: Vec<usize> = (episode.dataset_from_index..episode.dataset_to_index).collect();
        for camera in dataset.camera_keys() {
            let (path, times) = dataset.frame_times(&camera, episode, &indices).unwrap();
            wanted.entry(path.to_path_buf()).or_default().extend(times);
        }
    }
    let files = Arc::new(files);
    let decoder = Mp4Frames::new(files.clone());
    let mut decoded = DecodedFrames::default();
    for (path, times) in &wanted {
        let video = VideoFile::open(&*files, path).unwrap();
        assert!(video.track().codec.codec_string().is_some_and(|c| c.starts_with("avc1.")));
        let samples = video.samples_at(times, 1e-4).unwrap();
        let runs = video.decode_runs(&samples);
        assert!(runs.iter().all(|run| video.track().is_sync[run.start]), "every run starts at a key frame");
        let needed: Vec<usize> = {
            let mut s = samples.clone();
            s.sort_unstable();
            s.dedup();
            s
        };
        let sample_times: Vec<f64> = needed.iter().map(|&s| video.track().sample_time_s(s)).collect();
        let pictures = decoder.frames_at(path, &sample_times, 1e-4).unwrap();
        decoded.insert(path, video, needed.into_iter().zip(pictures).collect());
    }
    let in_memory = dataset.with_frames(Box::new(decoded));

    let on_disk = LeRobotDataset::open(&root).unwrap();
    let config = PartitionConfig {
        num_clients: 1,
        strategy: PartitionStrategy::EpisodeModulo,
        client_held_out_fraction: 0.25,
        server_held_out_fraction: 0.0,
        seed: 3,
    };
    let parts = partition(&episode_tasks(&on_disk), &config).unwrap();
    let (_, from_disk) = pack_shard(&on_disk, &parts, 0, &SPEC, None, &mut |_| {}).unwrap();
    let (manifest, from_memory) = pack_shard(&in_memory, &parts, 0, &SPEC, None, &mut |_| {}).unwrap();
    assert_eq!(manifest.num_frames, 48);
    assert!(from_memory == from_disk, "the shard packed from memory differs from the directory's");
}

#[test]
fn frames_not_decoded_are_an_error_naming_the_video() {
    let dir = common::temp_dir("memory-undecoded");
    let root = common::write_dataset(&dir, "ds", &common::episodes(1, 6, 32), 32);
    let files = fedvla_data::DirFiles::new(&root);
    let meta = DatasetMeta::read(&files).unwrap();
    let dataset = LeRobotDataset::from_meta(meta, &files, Box::new(DecodedFrames::default())).unwrap();
    let episode = &dataset.episodes()[0];
    let err = dataset.camera_frames("observation.images.top", episode, &[0]).unwrap_err().to_string();
    assert!(err.contains("videos/observation.images.top/chunk-000/file-000.mp4: no frames of this video"), "{err}");
    assert_eq!(files.root(), root);
}
