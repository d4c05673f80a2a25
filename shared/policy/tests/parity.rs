//! Runs the LeRobot parity check on every fixture folder in ../shared/fixtures and in the folder of fixtures
//! tests/run.sh makes with LeRobot itself (`FEDVLA_LEROBOT_FIXTURES`: one, two and three cameras of non-square
//! sizes, see tests/lerobot-fixtures). With `FEDVLA_REQUIRE_FIXTURES=1` (tests/run.sh) a missing folder fails
//! instead of skipping.

use std::path::{Path, PathBuf};

use burn::tensor::Device;

fn required() -> bool {
    std::env::var("FEDVLA_REQUIRE_FIXTURES").is_ok_and(|v| v == "1")
}

fn fixtures_dir() -> Option<PathBuf> {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../../shared/fixtures");
    if !dir.is_dir() && required() {
        panic!("FEDVLA_REQUIRE_FIXTURES=1 but {} is not there", dir.display());
    }
    dir.is_dir().then_some(dir)
}

/// Checks every fixture folder in `dir`; returns the camera count of each.
fn check_all(dir: &Path) -> Vec<usize> {
    let mut cameras = Vec::new();
    for entry in std::fs::read_dir(dir).unwrap() {
        let path = entry.unwrap().path();
        if !path.join("outputs.safetensors").exists() {
            continue;
        }
        let report = fedvla_policy::parity::run(&path, &Device::flex().autodiff(), 1e-4).unwrap();
        for row in &report.rows {
            println!("{:<70} {:?} {:?} {}", row.name, row.shape, row.max_abs_diff, row.note);
        }
        assert!(report.passed(), "{}: parity failed, worst diff {:e}", path.display(), report.worst());
        cameras.push(fedvla_policy::PolicyDir::load(&path).unwrap().cfg.camera_keys().len());
    }
    cameras
}

#[test]
fn every_fixture_matches_lerobot_within_1e_4() {
    let Some(dir) = fixtures_dir() else {
        eprintln!("SKIPPED: ../shared/fixtures not found next to the checkout; parity not checked");
        return;
    };
    assert!(!check_all(&dir).is_empty(), "no fixture with outputs.safetensors in {}", dir.display());
}

/// LeRobot's own fixtures with 1, 2 and 3 cameras of non-square sizes, listed in an order that is not
/// alphabetical: resize-with-pad and camera order as LeRobot does them.
#[test]
fn generated_multi_camera_fixtures_match_lerobot_within_1e_4() {
    let dir = std::env::var_os("FEDVLA_LEROBOT_FIXTURES").map(PathBuf::from);
    let Some(dir) = dir.filter(|d| d.is_dir()) else {
        assert!(!required(), "FEDVLA_REQUIRE_FIXTURES=1 but FEDVLA_LEROBOT_FIXTURES names no folder");
        eprintln!("SKIPPED: FEDVLA_LEROBOT_FIXTURES not set (tests/run.sh makes them with LeRobot)");
        return;
    };
    let mut cameras = check_all(&dir);
    cameras.sort_unstable();
    cameras.dedup();
    for n in [1, 2, 3] {
        assert!(cameras.contains(&n), "no generated fixture with {n} cameras in {} ({cameras:?})", dir.display());
    }
}

#[test]
fn fixture_tokenizer_reproduces_lerobot_token_ids() {
    let Some(dir) = fixtures_dir() else {
        eprintln!("SKIPPED: ../shared/fixtures not found next to the checkout; tokenizer not checked");
        return;
    };
    let fixture = dir.join("smolvla-tiny-a");
    let policy = fedvla_policy::PolicyDir::load(&fixture).unwrap();
    let tokenizer = policy.tokenizer().unwrap().expect("fixture ships vlm/tokenizer.json");
    let meta: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(fixture.join("meta.json")).unwrap()).unwrap();
    let tasks: Vec<&str> = meta["tasks"].as_array().unwrap().iter().map(|t| t.as_str().unwrap()).collect();
    let (ids, mask, len) = tokenizer
        .encode_batch(&tasks, policy.cfg.tokenizer_max_length, policy.cfg.pad_language_to == "max_length")
        .unwrap();
    let inputs = fedvla_policy::parity::read_any(&fixture.join("inputs.safetensors")).unwrap();
    let expected = &inputs["observation.language.tokens"];
    assert_eq!(len, expected.shape[1]);
    assert_eq!(ids.iter().map(|&i| i as f64).collect::<Vec<_>>(), expected.values);
    let expected_mask = &inputs["observation.language.attention_mask"];
    assert_eq!(mask.iter().map(|&m| m as u8 as f64).collect::<Vec<_>>(), expected_mask.values);
}
