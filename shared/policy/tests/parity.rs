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
