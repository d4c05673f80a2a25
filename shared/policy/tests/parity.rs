//! Runs the LeRobot parity check on every fixture folder in ../shared/fixtures.

use std::path::PathBuf;

use burn::tensor::Device;

fn fixtures_dir() -> Option<PathBuf> {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../../shared/fixtures");
    dir.is_dir().then_some(dir)
}

#[test]
fn every_fixture_matches_lerobot_within_1e_4() {
    let Some(dir) = fixtures_dir() else {
        eprintln!("SKIPPED: ../shared/fixtures not found next to the checkout; parity not checked");
        return;
    };
    let mut checked = 0;
    for entry in std::fs::read_dir(&dir).unwrap() {
        let path = entry.unwrap().path();
        if !path.join("outputs.safetensors").exists() {
            continue;
        }
        let report = fedvla_policy::parity::run(&path, &Device::flex().autodiff(), 1e-4).unwrap();
        for row in &report.rows {
            println!("{:<70} {:?} {:?} {}", row.name, row.shape, row.max_abs_diff, row.note);
        }
        assert!(report.passed(), "{}: parity failed, worst diff {:e}", path.display(), report.worst());
        checked += 1;
    }
    assert!(checked > 0, "no fixture with outputs.safetensors in {}", dir.display());
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
