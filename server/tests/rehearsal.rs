//! The full-size rehearsal's inputs (`fedvla rehearsal-inputs`): a checkpoint with exactly `lerobot/smolvla_base`'s
//! tensors, in bf16, with the fixture's tokenizer, and a small dataset; and the flow-matching loss of those
//! base-size weights on one frame of that dataset with fixed noise and time, computed here as training computes it
//! (the run's workload packs the frame, [`ShardExamples::batch`] makes the batch, [`Trainer::forward`] the loss)
//! and by LeRobot 0.6.1 itself from the same two folders (`tests/lerobot/flow_loss.py`: its dataset reader,
//! pre-processor and policy, given the frame's images as our decoder gives them; torch on the CPU in the checker's
//! chroot that FEDVLA_LEROBOT_ENV names, as tests/run.sh sets), equal to 1e-3 relative. Needs `../shared` beside
//! the checkout (with `FEDVLA_REQUIRE_FIXTURES=1` a missing one fails instead of skipping). Each side's base-size
//! forward pass takes a minute or two of CPU and several GB.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use burn::tensor::{Device, Tensor, TensorData};
use fedvla_aggregator::config::RunConfig;
use fedvla_data::{ClientShard, LeRobotDataset, RgbImage};
use fedvla_learner::ShardExamples;
use fedvla_policy::{PolicyDir, SmolVlaConfig, StoredDtype, Trainer};
use fedvla_workloads::smolvla::SmolVlaWorkload;
use rand::SeedableRng;
use rand_distr::{Distribution, StandardNormal};
use safetensors::Dtype;

/// The rehearsal dataset: three episodes (one the server's held-out, two the client's) of 40 frames, and the frame
/// of the loss: 15 steps of its 50-step action chunk lie in its episode, 35 past its end (LeRobot's padding).
const EPISODES: usize = 3;
const FRAMES: usize = 40;
const FRAME: usize = 25;

/// `../shared/<path>` beside the checkout, canonical (the chroot binds host directories at the same paths).
fn shared(path: &str) -> Option<PathBuf> {
    let full = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared").join(path);
    if let Ok(found) = std::fs::canonicalize(&full) {
        return Some(found);
    }
    if std::env::var("FEDVLA_REQUIRE_FIXTURES").is_ok_and(|v| v == "1") {
        panic!("FEDVLA_REQUIRE_FIXTURES=1 but {} is not there", full.display());
    }
    eprintln!("SKIPPED: {} not found next to the checkout", full.display());
    None
}

/// Name, dtype and shape of every tensor of a safetensors file.
fn header(path: &Path) -> BTreeMap<String, (Dtype, Vec<usize>)> {
    let bytes = std::fs::read(path).unwrap();
    let tensors = safetensors::SafeTensors::deserialize(&bytes).unwrap();
    tensors.tensors().into_iter().map(|(name, view)| (name, (view.dtype(), view.shape().to_vec()))).collect()
}

#[test]
fn the_rehearsal_checkpoint_is_smolvla_base_and_lerobot_computes_our_loss_from_it() {
    let (Some(reference), Some(tokenizer)) =
        (shared("reference/smolvla_base_shapes.json"), shared("fixtures/smolvla-tiny-a/vlm"))
    else {
        return;
    };
    let tmp = tempfile::tempdir().unwrap();
    let out = std::fs::canonicalize(tmp.path()).unwrap();
    let run = std::process::Command::new(env!("CARGO_BIN_EXE_fedvla"))
        .args(["rehearsal-inputs", "--seed", "3", "--episodes", &EPISODES.to_string(), "--frames"])
        .arg(FRAMES.to_string())
        .arg("--tokenizer")
        .arg(&tokenizer)
        .arg("--out")
        .arg(&out)
        .output()
        .expect("fedvla runs");
    assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));
    let (policy_dir, data) = (out.join("policy"), out.join("data"));

    // Exactly smolvla_base's keys and shapes, every one stored in bf16.
    let expected: BTreeMap<String, Vec<usize>> =
        serde_json::from_str(&std::fs::read_to_string(&reference).unwrap()).unwrap();
    let stored = header(&policy_dir.join("model.safetensors"));
    assert_eq!(stored.len(), 500);
    for (name, (dtype, shape)) in &stored {
        assert_eq!(*dtype, Dtype::BF16, "{name}");
        assert_eq!(Some(shape), expected.get(name), "{name}");
    }
    assert_eq!(stored.keys().collect::<Vec<_>>(), expected.keys().collect::<Vec<_>>());
    // The fixture's tokenizer, byte for byte, beside the base backbone's configuration.
    for name in ["tokenizer.json", "tokenizer_config.json"] {
        assert_eq!(
            std::fs::read(policy_dir.join("vlm").join(name)).unwrap(),
            std::fs::read(tokenizer.join(name)).unwrap(),
            "{name}"
        );
    }
    let policy = PolicyDir::load(&policy_dir).unwrap();
    assert_eq!((policy.dtype, &policy.cfg.vlm), (StoredDtype::Bf16, &SmolVlaConfig::base().vlm));
    assert_eq!(policy.cfg.param_specs(), SmolVlaConfig::base().param_specs());
    assert!(policy.tokenizer().unwrap().is_some(), "the backbone folder's tokenizer reads");
    drop(policy);
    let dataset = LeRobotDataset::open(&data).unwrap();
    assert_eq!((dataset.episodes().len(), dataset.len()), (EPISODES, EPISODES * FRAMES));
    assert_eq!(dataset.camera_keys(), ["observation.images.top", "observation.images.wrist"]);

    // The batch of one frame as a base-size run from the rehearsal's inputs trains on it: its workload packs the
    // client's shard (frames resized with padding, the checkpoint's tokenizer, the dataset's statistics) and fixes
    // the policy's configuration (the dataset's cameras in place of smolvla_base's).
    let run_config = RunConfig::default()
        .with_overrides(&format!(
            "model-size=base num-clients=1 rollout-episodes=0 dataset={} init-policy={}",
            data.display(),
            policy_dir.display()
        ))
        .unwrap();
    let shards = out.join("shards");
    let cfg = SmolVlaWorkload::prepare(&run_config, &shards).unwrap().policy_config().clone();
    let shard = ClientShard::read(&shards.join("client_0.safetensors")).unwrap();
    let episode = &shard.episodes[0];
    let row = episode.start + FRAME;
    assert_eq!(shard.frame_index[row], FRAME as i64);
    let index =
        dataset.episodes().iter().find(|e| e.episode_index == episode.episode_index).unwrap().dataset_from_index
            + FRAME;
    let batch = ShardExamples::new(shard, &cfg).unwrap().batch(&[row], cfg.chunk_size).unwrap();
    let t = cfg.chunk_size;
    assert_eq!(batch.action_is_pad.as_deref().unwrap().iter().filter(|&&p| !p).count(), FRAMES - FRAME);

    // Fixed noise and time; our loss from the bf16 weights, as the trainer computes it.
    let mut rng = rand::rngs::StdRng::seed_from_u64(12);
    let noise: Vec<f32> = (0..t * cfg.max_action_dim).map(|_| StandardNormal.sample(&mut rng)).collect();
    let time = [0.37f32];
    let weights = PolicyDir::load(&policy_dir).unwrap().weights;
    let trainer = Trainer::new(&cfg, &weights, &Device::flex().autodiff(), 0).unwrap();
    drop(weights);
    let noise_tensor =
        Tensor::<3>::from_data(TensorData::new(noise.clone(), [1, t, cfg.max_action_dim]), trainer.device());
    let ours = trainer.forward(&batch, noise_tensor, &time).unwrap().loss.into_scalar::<f32>();
    drop(trainer);
    println!("our flow-matching loss at full size (dataset frame {index}): {ours:.7}");

    let Ok(env) = std::env::var("FEDVLA_LEROBOT_ENV") else {
        eprintln!("SKIPPED: FEDVLA_LEROBOT_ENV not set; LeRobot's loss on the rehearsal's inputs not compared");
        return;
    };
    // The frame's camera images as our decoder gives them: PyAV converts the video's YUV to RGB with its own
    // rounding (a level apart here and there), which is a difference of decoders, not of the policy.
    let episode_meta = dataset.episode_of(index).unwrap();
    let images: Vec<(String, RgbImage)> = dataset
        .camera_keys()
        .into_iter()
        .map(|camera| {
            let frame = dataset.camera_frames(&camera, episode_meta, &[index]).unwrap().remove(0);
            (camera, frame)
        })
        .collect();
    let noise_file = out.join("noise.safetensors");
    write_noise(&noise_file, &noise, [1, t, cfg.max_action_dim], &time, &images);
    let scripts = std::fs::canonicalize(Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/lerobot")).unwrap();
    let output = std::process::Command::new("bash")
        .arg(shared("tools/lerobot-check/run.sh").expect("the LeRobot checker beside the checkout"))
        .arg(&env)
        .arg("python3")
        .arg(scripts.join("flow_loss.py"))
        .args([&policy_dir, &data])
        .arg(index.to_string())
        .arg(&noise_file)
        .env("HOSTDIR", format!("{}:{}", out.display(), scripts.display()))
        .output()
        .expect("running LeRobot");
    let log = format!("{}{}", String::from_utf8_lossy(&output.stdout), String::from_utf8_lossy(&output.stderr));
    assert!(output.status.success(), "LeRobot did not compute the loss:\n{log}");
    let theirs: f64 = log
        .lines()
        .find_map(|line| line.strip_prefix("FLOW_LOSS "))
        .and_then(|v| v.trim().parse().ok())
        .unwrap_or_else(|| panic!("no FLOW_LOSS line in:\n{log}"));
    let relative = (f64::from(ours) - theirs).abs() / theirs.abs();
    println!("LeRobot's: {theirs:.7}; relative difference {relative:.2e}");
    assert!(relative <= 1e-3, "ours {ours} against LeRobot's {theirs}: relative difference {relative:.2e}\n{log}");
}

/// The flow-matching `noise` (of `shape`) and `time`, and the frame's camera `images` (RGB, height x width x 3,
/// named by their feature), as `flow_loss.py` reads them.
fn write_noise(path: &Path, noise: &[f32], shape: [usize; 3], time: &[f32], images: &[(String, RgbImage)]) {
    let f32s = |v: &[f32]| v.iter().flat_map(|x| x.to_le_bytes()).collect::<Vec<u8>>();
    let (noise, time) = (f32s(noise), f32s(time));
    let mut views = vec![
        ("noise".to_owned(), safetensors::tensor::TensorView::new(Dtype::F32, shape.to_vec(), &noise).unwrap()),
        ("time".to_owned(), safetensors::tensor::TensorView::new(Dtype::F32, vec![shape[0]], &time).unwrap()),
    ];
    for (camera, image) in images {
        let shape = vec![image.height as usize, image.width as usize, 3];
        views.push((camera.clone(), safetensors::tensor::TensorView::new(Dtype::U8, shape, &image.data).unwrap()));
    }
    std::fs::write(path, safetensors::serialize(views, None).unwrap()).unwrap();
}
