//! Shared fixtures: small synthetic datasets written into fresh temporary directories.
// Each test binary compiles this module and uses only part of it.
#![allow(dead_code)]

use std::path::PathBuf;

use fedvla_data::{CameraSpec, DatasetSpec, DatasetWriter, Episode, synthetic};

pub const TASKS: [&str; 2] = ["put the cube in the bowl", "push the cube to the left"];

/// A fresh, empty directory under the system temp dir, unique to this test process and `name`.
pub fn temp_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("fedvla-data-test-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).expect("create temp dir");
    dir
}

pub fn cameras(size: u32) -> Vec<CameraSpec> {
    vec![CameraSpec::new("top", size, size), CameraSpec::new("wrist", size, size)]
}

pub fn episodes(count: usize, frames: usize, size: u32) -> Vec<Episode> {
    let cams = cameras(size);
    (0..count).map(|e| synthetic::episode(e, frames, &cams, TASKS[e % TASKS.len()])).collect()
}

/// Writes `episodes` (two `size`x`size` cameras) to `dir/name` and returns the dataset root.
pub fn write_dataset(dir: &std::path::Path, name: &str, episodes: &[Episode], size: u32) -> PathBuf {
    let root = dir.join(name);
    let mut writer = DatasetWriter::create(&root, DatasetSpec::so100(cameras(size))).expect("create writer");
    for ep in episodes {
        writer.add_episode(ep).expect("add episode");
    }
    writer.finish().expect("finish");
    root
}
