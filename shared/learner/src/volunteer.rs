//! A volunteer's start-up, the same natively and in the browser: its key pair proves it on a new connection and
//! the server admits it with a session and its setup ([`fedvla_federation::identify`]); with that session it
//! checks the setup is a workload it can serve, downloads the frozen weights, the shard bound to its key (checked
//! against its manifest's size and SHA-256; or, for a volunteer with its own dataset, the run's tokenizer to pack
//! that dataset with) and the global model, builds the trainer, and joins ([`fedvla_federation::run_client`]).
//! Only the I/O differs: the key's storage, and the downloading behind [`Fetch`] (natively a plain HTTP GET, in the
//! browser a fetch with progress that keeps content under a content key in the Cache API), each presenting the
//! admission's session.

use std::future::Future;
use std::path::Path;

use burn::tensor::Device;
use fedvla_data::shard::verify_shard_bytes;
use fedvla_data::{ClientShard, ShardFileManifest};
use fedvla_federation::{BoxError, VolunteerSetup, WorkloadKind, routes};
use fedvla_policy::weights::{ParamStore, parse_safetensors};
use fedvla_policy::{SmolVlaConfig, Tokenizer, WeightMap};

use crate::examples::ShardExamples;
use crate::rollout::SimTasks;
use crate::trainer::SmolVlaTrainer;

/// How a volunteer downloads from its server, with its admission's session.
pub trait Fetch {
    /// `GET path` on the server, presenting the session. `cache_key`, when given, names content that never changes
    /// under that key (it carries a content hash), which a client may keep; `what` names the download for progress.
    fn get(&self, path: &str, what: &str, cache_key: Option<&str>) -> impl Future<Output = Result<Vec<u8>, BoxError>>;
}

/// A shard and its manifest, the shard checked against the manifest's size and SHA-256 before use (and kept
/// under its SHA-256).
pub async fn fetch_shard(
    fetch: &impl Fetch,
    shard_url: &str,
    manifest_url: &str,
) -> Result<(ShardFileManifest, Vec<u8>), BoxError> {
    let manifest: ShardFileManifest = serde_json::from_slice(&fetch.get(manifest_url, "manifest", None).await?)
        .map_err(|e| format!("GET {manifest_url}: {e}"))?;
    let shard = fetch.get(shard_url, "shard", Some(&format!("/shard/sha256/{}", manifest.file_sha256))).await?;
    verify_shard_bytes(Path::new(&manifest.file), &shard, &manifest)?;
    Ok((manifest, shard))
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
    fedvla_federation::fnv1a(name)
}

/// The run's tokenizer, for a volunteer that tokenizes its own dataset's tasks.
pub async fn fetch_tokenizer(fetch: &impl Fetch, setup: &VolunteerSetup) -> Result<Tokenizer, BoxError> {
    let url = setup.tokenizer_url.as_deref().ok_or("the server offers no tokenizer: it takes no own datasets")?;
    let bytes = fetch.get(url, "tokenizer", None).await?;
    Ok(Tokenizer::from_json_bytes(&bytes, Path::new(url))?)
}

/// The SmolVLA volunteer `name` of `setup`, on `device` (autodiff enabled), able to roll out the sim task:
/// downloads the frozen weights, its shard and the global model the setup names.
pub async fn smolvla_volunteer(
    fetch: &impl Fetch,
    setup: &VolunteerSetup,
    name: &str,
    device: &Device,
    backend: &str,
) -> Result<SmolVlaTrainer, BoxError> {
    check_smolvla(setup)?;
    let (manifest, shard) = fetch_shard(fetch, &setup.shard_url, &setup.shard_manifest_url).await?;
    let shard = ClientShard::from_bytes(Path::new(&manifest.file), &shard)?;
    smolvla_volunteer_on(fetch, setup, name, shard, device, backend).await
}

fn check_smolvla(setup: &VolunteerSetup) -> Result<(), BoxError> {
    match setup.workload {
        WorkloadKind::Smolvla => Ok(()),
        other => Err(format!("the server runs the {other:?} workload, not SmolVLA").into()),
    }
}

/// [`smolvla_volunteer`] on `shard`, one the volunteer already holds (packed from its own dataset): downloads the
/// frozen weights and the global model.
pub async fn smolvla_volunteer_on(
    fetch: &impl Fetch,
    setup: &VolunteerSetup,
    name: &str,
    shard: ClientShard,
    device: &Device,
    backend: &str,
) -> Result<SmolVlaTrainer, BoxError> {
    check_smolvla(setup)?;
    let cfg = policy_config(setup)?;
    let frozen_url = setup.frozen_url.as_deref().ok_or("the server offers no frozen weights")?;
    // Each download's bytes go as soon as they are parsed, before the trainer uploads its tensors (at the base
    // size the frozen ones are 0.7 GB in bf16).
    let bytes = fetch.get(frozen_url, "frozen weights", Some(frozen_url)).await?;
    let frozen_name = Path::new("frozen weights");
    // On the CPU the frozen tensors go straight onto the device in the dtype they came in (bf16 for a bf16
    // checkpoint) and are held once; a GPU gets them in f32 (WebGPU has no bf16) and the CPU keeps its own copy.
    let on_cpu = *device == Device::flex();
    let frozen = if on_cpu {
        Frozen::OnDevice(ParamStore::from_safetensors(&bytes, frozen_name, device, true)?)
    } else {
        Frozen::OnHost(parse_safetensors(&bytes, frozen_name)?)
    };
    drop(bytes);
    // Never cached: versions are numbered per run, so a kept version 3 could be another run's.
    let global = fetch.get(&routes::model(setup.model_version), "global model", None).await?;
    let trainable = parse_safetensors(&global, Path::new("global model"))?;
    drop(global);
    let examples = ShardExamples::new(shard, &cfg)?;
    let tasks = SimTasks::from_wire(&setup.rollout_tasks)?;
    let seed = volunteer_seed(name);
    let trainer = match frozen {
        Frozen::OnDevice(frozen) => {
            SmolVlaTrainer::on_cpu_with_frozen(&cfg, frozen, trainable, examples, seed, device, backend)?
        }
        Frozen::OnHost(mut weights) => {
            weights.extend(trainable);
            SmolVlaTrainer::new(&cfg, weights, examples, seed, device, backend)?
        }
    };
    Ok(trainer.with_rollouts(tasks))
}

/// The downloaded frozen tensors, where the volunteer's device wants them.
enum Frozen {
    OnDevice(ParamStore),
    OnHost(WeightMap),
}
