//! A full-size rehearsal that needs no download: a LeRobot policy directory shaped exactly as
//! `lerobot/smolvla_base` (its 500 tensors and their shapes, stored in bf16 as that checkpoint stores them) holding
//! seeded random weights, whose backbone folder carries a given tokenizer; and a small procedural SO-100 dataset
//! to run it on. A run from these exercises every byte a run from the real checkpoint holds, at its cost.

use std::path::Path;

use anyhow::Context;
use fedvla_data::{CameraSpec, DatasetSpec, DatasetWriter, synthetic};
use fedvla_policy::policy_dir::{Backbone, export};
use fedvla_policy::weights::{host_refs, init_random};
use fedvla_policy::{FeatureStats, NormStats, SmolVlaConfig, StoredDtype};

/// The rehearsal dataset's one task (a string the smolvla-tiny-a fixture's tokenizer was trained on).
pub const REHEARSAL_TASK: &str = "pick up the red cube";

/// Writes `dir` as a LeRobot policy directory of the `base` model size: `config.json`, `model.safetensors` of
/// seeded random weights ([`init_random`] of `seed`) in bf16, the processor files with unit statistics (mean 0,
/// std 1: a run normalises with its dataset's), and `vlm/` with the base backbone's configuration and the
/// tokenizer of the backbone folder `tokenizer_of`.
pub fn write_checkpoint(dir: &Path, seed: u64, tokenizer_of: &Path) -> anyhow::Result<()> {
    for name in ["tokenizer.json", "tokenizer_config.json"] {
        let path = tokenizer_of.join(name);
        anyhow::ensure!(path.is_file(), "{}: no {name} (a backbone folder such as a fixture's vlm/)", path.display());
    }
    let cfg = SmolVlaConfig::base();
    let weights = init_random(&cfg.param_specs(), seed);
    let unit = |f: &fedvla_policy::config::Feature| {
        let dim = f.shape.first().copied().unwrap_or(0);
        (f.name.clone(), FeatureStats { mean: vec![0.0; dim], std: vec![1.0; dim] })
    };
    let normalised = cfg.input_features.iter().filter(|f| f.kind == "STATE").chain(&cfg.output_features);
    let stats = NormStats { features: normalised.map(unit).collect() };
    export(dir, &cfg, host_refs(&weights), &stats, Backbone::GeneratedWithTokenizerOf(tokenizer_of), StoredDtype::Bf16)
        .with_context(|| format!("writing the rehearsal checkpoint to {}", dir.display()))
}

/// Writes `dir` as a LeRobot v3.0 SO-100 dataset of `episodes` procedural episodes ([`synthetic::episode`]) of
/// `frames` frames, two 64x64 cameras (`top`, `wrist`), all of [`REHEARSAL_TASK`]: few frames, so that a base-size
/// run's held-out evaluations stay minutes long.
pub fn write_dataset(dir: &Path, episodes: usize, frames: usize) -> anyhow::Result<()> {
    let cameras: Vec<CameraSpec> = ["top", "wrist"].map(|name| CameraSpec::new(name, 64, 64)).to_vec();
    let mut writer = DatasetWriter::create(dir, DatasetSpec::so100(cameras.clone()))
        .with_context(|| format!("creating the rehearsal dataset {}", dir.display()))?;
    for episode in 0..episodes {
        writer.add_episode(&synthetic::episode(episode, frames, &cameras, REHEARSAL_TASK))?;
    }
    writer.finish()?;
    Ok(())
}
