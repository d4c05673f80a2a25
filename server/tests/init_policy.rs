//! A run from a checkpoint (`init-policy`) tokenizes with the checkpoint's own tokenizer, in its shards, its
//! rollouts and its export, on the public LeRobot fixture (a BPE tokenizer that no word-level one resembles).
//! With `FEDVLA_REQUIRE_FIXTURES=1` (tests/run.sh) a missing `../shared/fixtures` fails instead of skipping.

use std::path::{Path, PathBuf};

use fedvla_aggregator::config::RunConfig;
use fedvla_data::{CameraSpec, ClientShard, DatasetSpec, DatasetWriter, Episode, Frame, RgbImage};
use fedvla_policy::{PolicyDir, StoredDtype, Tokenizer};
use fedvla_workloads::smolvla::SmolVlaWorkload;
use fedvla_workloads::workload::Workload;

/// The fixture's own task string, whose ids LeRobot recorded in `inputs.safetensors`.
const FIXTURE_TASK: &str = "pick up the red cube";

fn fixture() -> Option<PathBuf> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/fixtures/smolvla-tiny-a");
    if dir.join("config.json").exists() {
        return Some(dir);
    }
    if std::env::var("FEDVLA_REQUIRE_FIXTURES").is_ok_and(|v| v == "1") {
        panic!("FEDVLA_REQUIRE_FIXTURES=1 but {} is not there", dir.display());
    }
    eprintln!("SKIPPED: {} not found next to the checkout", dir.display());
    None
}

/// The fixture, and a temporary folder holding [`dataset`] at `data`.
fn fixture_and_dataset() -> Option<(PathBuf, tempfile::TempDir, PathBuf)> {
    let fixture = fixture()?;
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    dataset(&data);
    Some((fixture, tmp, data))
}

/// A small dataset with the fixture's cameras (32x32 top and wrist) and the fixture's task.
fn dataset(root: &Path) {
    let cameras = ["top", "wrist"].map(|name| CameraSpec::new(name, 32, 32)).to_vec();
    let mut writer = DatasetWriter::create(root, DatasetSpec::so100(cameras)).unwrap();
    for episode in 0..4u8 {
        let frames = (0..6u8)
            .map(|t| Frame {
                state: (0..6).map(|j| f32::from(episode + t + j)).collect(),
                action: (0..6).map(|j| f32::from(episode + t + j) + 0.5).collect(),
                images: (0..2).map(|c| RgbImage::new(32, 32, vec![40 * c + 10 * t; 32 * 32 * 3]).unwrap()).collect(),
            })
            .collect();
        writer.add_episode(&Episode { task: FIXTURE_TASK.into(), frames }).unwrap();
    }
    writer.finish().unwrap();
}

#[test]
fn a_run_from_a_checkpoint_uses_the_checkpoints_tokenizer_everywhere() {
    let Some((fixture, tmp, data)) = fixture_and_dataset() else { return };
    let config = RunConfig::default()
        .with_overrides(&format!(
            "model-size=tiny num-clients=2 rollout-episodes=0 dataset={} init-policy={}",
            data.display(),
            fixture.display()
        ))
        .unwrap();
    let workload = SmolVlaWorkload::prepare(&config, &tmp.path().join("shards")).expect("prepare from the fixture");
    // What the run prints first: the cameras in the order the policy reads them, the features, the tokenizer.
    let inputs = workload.inputs();
    for line in [
        "camera 0: observation.images.top (32x32, resized with padding to 32x32)",
        "camera 1: observation.images.wrist",
        "observation.state: [\"shoulder_pan.pos\"",
        "normalised with mean [",
        "tokenizer: the checkpoint's",
    ] {
        assert!(inputs.contains(line), "{line:?} missing from:\n{inputs}");
    }

    // The fixture's tokenizer, and the ids LeRobot itself recorded for this task.
    let checkpoint = Tokenizer::read(&fixture.join("vlm/tokenizer.json")).unwrap();
    let (ids, _, len) = checkpoint.encode_batch(&[FIXTURE_TASK], 48, false).unwrap();
    let inputs = safetensors_i64(&fixture.join("inputs.safetensors"), "observation.language.tokens");
    assert_eq!(ids, inputs[..len], "the fixture's tokenizer gives LeRobot's ids");

    let offer = workload.volunteer_offer().unwrap();
    for shard in &offer.shards {
        let shard = ClientShard::read(shard.file.as_ref().unwrap()).unwrap();
        let (shard_ids, _) = shard.task_tokens.expect("shards carry the task's tokens");
        assert_eq!(shard_ids[..len], ids[..], "shard token ids are the checkpoint tokenizer's");
    }

    // The export carries the checkpoint's backbone folder, tokenizer included, byte for byte.
    let out = tmp.path().join("round_0");
    let global = workload.initial_model().unwrap();
    for exporter in workload.exporters() {
        exporter.export(0, &global, &config, &out).unwrap();
    }
    let exported = out.join("policy/vlm/tokenizer.json");
    assert_eq!(std::fs::read(&exported).unwrap(), std::fs::read(fixture.join("vlm/tokenizer.json")).unwrap());
    let reloaded = PolicyDir::load(&out.join("policy")).unwrap();
    let (again, _, _) = reloaded.tokenizer().unwrap().unwrap().encode_batch(&[FIXTURE_TASK], 48, false).unwrap();
    assert_eq!(again, ids);
}

#[test]
fn a_checkpoint_without_a_tokenizer_is_refused_by_name() {
    let Some((fixture, tmp, data)) = fixture_and_dataset() else { return };
    // The fixture without its backbone's tokenizer.
    let policy = tmp.path().join("policy");
    std::fs::create_dir_all(policy.join("vlm")).unwrap();
    for entry in std::fs::read_dir(&fixture).unwrap() {
        let path = entry.unwrap().path();
        if path.is_file() {
            std::fs::copy(&path, policy.join(path.file_name().unwrap())).unwrap();
        }
    }
    std::fs::copy(fixture.join("vlm/config.json"), policy.join("vlm/config.json")).unwrap();
    let config = RunConfig::default()
        .with_overrides(&format!("model-size=tiny dataset={} init-policy={}", data.display(), policy.display()))
        .unwrap();
    let err = SmolVlaWorkload::prepare(&config, &tmp.path().join("shards")).err().expect("no tokenizer");
    assert!(format!("{err:#}").contains("no tokenizer.json"), "{err:#}");
}

#[test]
fn a_bf16_export_reloads_within_rounding_and_lerobot_loads_it() {
    let Some((fixture, tmp, data)) = fixture_and_dataset() else { return };
    let run = |dtype: &str| {
        let config = RunConfig::default()
            .with_overrides(&format!(
                "model-size=tiny rollout-episodes=0 dataset={} init-policy={} export-dtype={dtype}",
                data.display(),
                fixture.display()
            ))
            .unwrap();
        let workload = SmolVlaWorkload::prepare(&config, &tmp.path().join(format!("shards_{dtype}"))).unwrap();
        let out = tmp.path().join(format!("round_0_{dtype}"));
        let global = workload.initial_model().unwrap();
        for exporter in workload.exporters() {
            exporter.export(0, &global, &config, &out).unwrap();
        }
        PolicyDir::load(&out.join("policy")).unwrap()
    };
    // The fixture is f32, so `auto` keeps f32; `bf16` asks for half the bytes.
    assert_eq!(run("auto").dtype, StoredDtype::F32);
    let bf16 = run("bf16");
    assert_eq!(bf16.dtype, StoredDtype::Bf16);
    let original = PolicyDir::load(&fixture).unwrap();
    for (key, tensor) in &original.weights {
        for (stored, exact) in bf16.weights[key].data.iter().zip(&tensor.data) {
            assert!((stored - exact).abs() <= exact.abs() * 2f32.powi(-8), "{key}: {exact} exported as {stored}");
        }
    }

    // A run from the bf16 export keeps bf16: its own exports (auto), and the frozen tensors volunteers download,
    // exactly the values the server holds, at half the bytes of f32.
    let from_bf16 = RunConfig::default()
        .with_overrides(&format!(
            "model-size=tiny rollout-episodes=0 dataset={} init-policy={}",
            data.display(),
            tmp.path().join("round_0_bf16/policy").display()
        ))
        .unwrap();
    let workload = SmolVlaWorkload::prepare(&from_bf16, &tmp.path().join("shards_from_bf16")).unwrap();
    let frozen = workload.volunteer_offer().unwrap().frozen.expect("frozen tensors offered");
    let downloaded = fedvla_policy::weights::parse_safetensors(&frozen, Path::new("frozen")).unwrap();
    let trainable: std::collections::BTreeSet<String> =
        bf16.cfg.param_specs().into_iter().filter(|s| s.trainable).map(|s| s.name).collect();
    let held: fedvla_policy::WeightMap = bf16.weights.into_iter().filter(|(k, _)| !trainable.contains(k)).collect();
    assert_eq!(downloaded, held, "the download is the frozen tensors, bit for bit");
    let f32_bytes = fedvla_policy::weights::safetensors_bytes(&held).unwrap().len() as f64;
    assert!((frozen.len() as f64) < 0.55 * f32_bytes, "{} bytes in bf16 against {f32_bytes} in f32", frozen.len());

    // LeRobot 0.6.1 itself loads the bf16 export and acts with it (the checker's chroot, as tests/run.sh sets).
    let Ok(env) = std::env::var("FEDVLA_LEROBOT_ENV") else {
        eprintln!("SKIPPED: FEDVLA_LEROBOT_ENV not set; LeRobot's load of the bf16 export not checked");
        return;
    };
    // Canonical: the chroot binds host directories at the same paths.
    let tools = std::fs::canonicalize(Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/tools/lerobot-check"))
        .expect("../shared/tools/lerobot-check beside the checkout");
    let policy = tmp.path().join("round_0_bf16/policy");
    let output = std::process::Command::new("bash")
        .arg(tools.join("run.sh"))
        .arg(&env)
        .args(["python3", &tools.join("check_policy.py").display().to_string(), &policy.display().to_string()])
        .env("HOSTDIR", tmp.path())
        .output()
        .expect("running the LeRobot checker");
    let log = format!("{}{}", String::from_utf8_lossy(&output.stdout), String::from_utf8_lossy(&output.stderr));
    assert!(output.status.success(), "LeRobot did not load the bf16 export:\n{log}");
}

fn safetensors_i64(path: &Path, key: &str) -> Vec<i64> {
    let bytes = std::fs::read(path).unwrap();
    let tensors = safetensors::SafeTensors::deserialize(&bytes).unwrap();
    let view = tensors.tensor(key).unwrap();
    match view.dtype() {
        safetensors::Dtype::I64 => view.data().chunks(8).map(|b| i64::from_le_bytes(b.try_into().unwrap())).collect(),
        safetensors::Dtype::I32 => {
            view.data().chunks(4).map(|b| i64::from(i32::from_le_bytes(b.try_into().unwrap()))).collect()
        }
        other => panic!("{key}: unexpected dtype {other:?}"),
    }
}
