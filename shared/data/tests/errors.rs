//! Broken datasets fail with errors that name the problem and the file.

mod common;

use fedvla_data::{DataError, LeRobotDataset};

fn broken_copy(name: &str) -> (std::path::PathBuf, std::path::PathBuf) {
    let dir = common::temp_dir(name);
    let root = common::write_dataset(&dir, "ds", &common::episodes(2, 10, 32), 32);
    (dir, root)
}

#[test]
fn truncated_parquet_names_the_file() {
    let (dir, root) = broken_copy("truncated");
    let path = root.join("data/chunk-000/file-000.parquet");
    let bytes = std::fs::read(&path).expect("read");
    std::fs::write(&path, &bytes[..bytes.len() / 2]).expect("truncate");
    let err = LeRobotDataset::open(&root).err().expect("must fail");
    assert!(matches!(&err, DataError::CorruptParquet { path: p, .. } if *p == path), "{err}");
    assert!(err.to_string().contains("file-000.parquet") && err.to_string().contains("corrupt or truncated"), "{err}");
    std::fs::remove_dir_all(&dir).expect("cleanup");
}

#[test]
fn missing_mp4_names_the_file() {
    let (dir, root) = broken_copy("missing-mp4");
    let path = root.join("videos/observation.images.wrist/chunk-000/file-000.mp4");
    std::fs::remove_file(&path).expect("remove");
    let err = LeRobotDataset::open(&root).err().expect("must fail");
    assert!(matches!(&err, DataError::MissingFile { path: p } if *p == path), "{err}");
    assert!(err.to_string().contains("observation.images.wrist") && err.to_string().contains("not found"), "{err}");
    std::fs::remove_dir_all(&dir).expect("cleanup");
}

#[test]
fn unknown_codebase_version_is_rejected() {
    let (dir, root) = broken_copy("version");
    let path = root.join("meta/info.json");
    let text = std::fs::read_to_string(&path).expect("read").replace("\"v3.0\"", "\"v9.9\"");
    std::fs::write(&path, text).expect("write");
    let err = LeRobotDataset::open(&root).err().expect("must fail");
    assert!(matches!(&err, DataError::UnknownVersion { found, .. } if found == "v9.9"), "{err}");
    assert!(err.to_string().contains("info.json") && err.to_string().contains("v9.9"), "{err}");
    std::fs::remove_dir_all(&dir).expect("cleanup");
}

#[test]
fn truncated_mp4_fails_when_decoding() {
    let (dir, root) = broken_copy("truncated-mp4");
    let path = root.join("videos/observation.images.top/chunk-000/file-000.mp4");
    let bytes = std::fs::read(&path).expect("read");
    std::fs::write(&path, &bytes[..bytes.len() - 100]).expect("truncate");
    let ds = LeRobotDataset::open(&root).expect("metadata is intact");
    let err = ds.get(0, &Default::default()).expect_err("must fail");
    assert!(matches!(&err, DataError::BadMp4 { path: p, .. } if *p == path), "{err}");
    std::fs::remove_dir_all(&dir).expect("cleanup");
}

#[test]
fn missing_dataset_reports_info_json() {
    let dir = common::temp_dir("absent");
    let err = LeRobotDataset::open(dir.join("nothing-here")).err().expect("must fail");
    assert!(matches!(&err, DataError::MissingFile { path } if path.ends_with("meta/info.json")), "{err}");
    std::fs::remove_dir_all(&dir).expect("cleanup");
}
