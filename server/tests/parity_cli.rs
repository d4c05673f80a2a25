//! `fedvla parity` on the LeRobot golden fixture: passes as shipped, fails once a weight is changed.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn fixture() -> Option<PathBuf> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/fixtures/smolvla-tiny-a");
    dir.join("outputs.safetensors").exists().then_some(dir)
}

fn parity(dir: &Path) -> Output {
    Command::new(env!("CARGO_BIN_EXE_fedvla")).arg("parity").arg("--fixture").arg(dir).output().expect("fedvla runs")
}

/// Copies `from` into `to` by content, so the copies are writable even though the fixture is not.
fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for entry in std::fs::read_dir(from).unwrap() {
        let path = entry.unwrap().path();
        let target = to.join(path.file_name().unwrap());
        if path.is_dir() {
            copy_dir(&path, &target);
        } else {
            std::fs::write(&target, std::fs::read(&path).unwrap()).unwrap();
        }
    }
}

#[test]
fn fixture_passes_and_every_tensor_is_listed() {
    let Some(dir) = fixture() else {
        eprintln!("SKIPPED: ../shared/fixtures/smolvla-tiny-a not found next to the checkout; parity CLI not checked");
        return;
    };
    let out = parity(&dir);
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{stdout}\n{}", String::from_utf8_lossy(&out.stderr));
    assert!(stdout.lines().any(|l| l.starts_with("policy.loss ")), "{stdout}");
    assert!(stdout.contains("parity passed"), "{stdout}");
}

#[test]
fn a_perturbed_weight_fails_and_names_the_tensors() {
    let Some(dir) = fixture() else {
        eprintln!("SKIPPED: ../shared/fixtures/smolvla-tiny-a not found next to the checkout; parity CLI not checked");
        return;
    };
    let tmp = tempfile::tempdir().unwrap();
    copy_dir(&dir, tmp.path());
    let model = tmp.path().join("model.safetensors");
    let mut weights = fedvla_policy::weights::read_safetensors(&model).unwrap();
    // The action head: changes the loss, the predicted actions and their gradients.
    weights.get_mut("model.action_out_proj.weight").expect("fixture has the action head").data[0] += 0.5;
    fedvla_policy::weights::write_safetensors(&model, &weights).unwrap();

    let out = parity(tmp.path());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{}", String::from_utf8_lossy(&out.stdout));
    assert!(stderr.contains("parity failed") && stderr.contains("policy.loss"), "{stderr}");
}
