//! A volunteer's trainer assembled from what it downloaded (`GET /api/volunteer`, the frozen weights, the global
//! trainable tensors and its shard), the same way natively and in the browser.

use std::path::Path;

use burn::tensor::Device;
use fedvla_data::{ClientShard, ShardFileManifest};
use fedvla_federation::{BoxError, VolunteerSetup};
use fedvla_policy::SmolVlaConfig;
use fedvla_policy::weights::parse_safetensors;

use crate::examples::ShardExamples;
use crate::trainer::SmolVlaTrainer;

/// The downloaded bytes a volunteer starts from.
pub struct Downloads<'a> {
    pub setup: &'a VolunteerSetup,
    /// Safetensors of the frozen tensors.
    pub frozen: &'a [u8],
    /// Safetensors of the global trainable tensors (any version: the first task replaces them).
    pub global: &'a [u8],
    /// The shard file, already checked against its manifest.
    pub shard: &'a [u8],
    pub manifest: &'a ShardFileManifest,
}

/// The policy configuration the server runs.
pub fn policy_config(setup: &VolunteerSetup) -> Result<SmolVlaConfig, BoxError> {
    let policy = setup.policy.get("policy").ok_or("the volunteer setup has no policy (is this a smolvla run?)")?;
    let vlm = serde_json::from_value(setup.policy.get("vlm").cloned().ok_or("the volunteer setup has no vlm config")?)
        .map_err(|e| format!("the volunteer setup's vlm config: {e}"))?;
    Ok(SmolVlaConfig::from_lerobot_json(policy, vlm)?)
}

/// A seed of this volunteer's own for its noise and times, from its name.
pub fn volunteer_seed(name: &str) -> u64 {
    name.bytes().fold(0xcbf2_9ce4_8422_2325, |h, b| (h ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3))
}

/// The trainer of `name` on `device` (autodiff enabled), able to roll out the sim task.
pub fn volunteer_trainer(
    downloads: &Downloads,
    name: &str,
    device: &Device,
    backend: &str,
) -> Result<SmolVlaTrainer, BoxError> {
    let cfg = policy_config(downloads.setup)?;
    let mut weights = parse_safetensors(downloads.frozen, Path::new("frozen weights"))?;
    weights.extend(parse_safetensors(downloads.global, Path::new("global model"))?);
    let shard = ClientShard::from_bytes(Path::new(&downloads.manifest.file), downloads.shard)?;
    let examples = ShardExamples::new(shard, &cfg)?;
    let setup = downloads.setup;
    let tokens = (
        setup.rollout_task_tokens.iter().map(|&i| i64::from(i)).collect(),
        setup.rollout_task_mask.clone(),
        setup.rollout_task_tokens.len(),
    );
    Ok(SmolVlaTrainer::new(&cfg, &weights, examples, volunteer_seed(name), device, backend)?.with_rollouts(tokens))
}
