//! SmolVLA on SO-100 data as the federation's workload: the dataset (the embedded default is
//! recorded by the sim's scripted expert on first use), its partition into client shards and the
//! server's held-out shard, the initial checkpoint; what each round's global model is exported as ([`export`]);
//! the run's tokenizer ([`tokenizer`]).

mod export;
mod tokenizer;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::RwLock;

use anyhow::Context;
use burn::tensor::Device;
use fedvla_data::{
    ClientShard, ClientSplit, EpisodeTask, LeRobotDataset, Partition, PartitionConfig, PartitionStrategy, build_shard,
    episode_tasks, partition,
};
use fedvla_federation::data_report::NORMALISED_FEATURES;
use fedvla_federation::{
    BoxError, DatasetSignature, Evaluator, FeatureSummary, NamedTensors, NormalizationStats, StatsSource,
};
use fedvla_learner::examples::{dataset_signature, norm_stats, shard_spec, task_token_ids};
use fedvla_learner::rollout::SimTasks;
use fedvla_learner::tensors::to_named;
use fedvla_learner::{HeldOutEvaluator, ShardExamples, SmolVlaTrainer};
use fedvla_policy::config::Feature;
use fedvla_policy::weights::{ParamStore, init_random, safetensors_bytes_as};
use fedvla_policy::{NormStats, PolicyDir, SmolVlaConfig, StoredDtype, WeightMap};
use fedvla_sim::TaskKind;

use fedvla_aggregator::config::{ComputeDevice, EMBEDDED_DATASET, ExportDtype, Partitioning, RunConfig, WorkloadKind};
use fedvla_aggregator::registry::{ShardOffer, VolunteerOffer};
use fedvla_aggregator::run_dir::ModelExporter;

use self::export::{LeRobotExport, SimRollouts};
use self::tokenizer::RunTokenizer;
use crate::datagen::{GenDataOptions, GenProgress, SEEDS_FILE, generate_dataset, recorded_seeds};
use crate::device::training_device;
use crate::workload::Workload;

/// Share of each client's episodes it never trains on, and of all episodes only the server sees.
const CLIENT_HELD_OUT: f64 = 0.2;
const SERVER_HELD_OUT: f64 = 0.15;

/// Everything the server and the clients of one SmolVLA run share.
pub struct SmolVlaWorkload {
    cfg: SmolVlaConfig,
    /// The initial checkpoint, split, on the CPU once and shared, not copied: the backbone tensors no client trains
    /// (1.4 GB of f32 at the base size), by the server's evaluator, the exporters and the volunteers' download;
    /// and the trainable ones, the round-0 global model, by the evaluator's resident model.
    frozen: ParamStore,
    trainable: ParamStore,
    /// The dataset's normalisation statistics, and the policy's view of them.
    dataset_stats: NormalizationStats,
    stats: NormStats,
    /// What a volunteer's own dataset must match.
    signature: DatasetSignature,
    tokenizer: RunTokenizer,
    /// What every round's export stores its tensors in.
    export_dtype: StoredDtype,
    /// What the init checkpoint stored its tensors in (f32 from random weights): volunteers download the frozen
    /// tensors in it, which loses nothing and halves the bytes of a bf16 `smolvla_base`.
    checkpoint_dtype: StoredDtype,
    /// What the policy is fed, in words (see [`SmolVlaWorkload::inputs`]).
    inputs: String,
    client_shards: Vec<ShardOffer>,
    server_shard: PathBuf,
    /// Every client's training episodes in one shard: what the centralized baseline trains on.
    pooled_shard: PathBuf,
    /// The sim tasks the dataset records, which every rollout of the run cycles through.
    rollout_tasks: Vec<TaskKind>,
    seed: u64,
}

/// The sim tasks `dataset` records, in the order their instructions first appear in its task list; a dataset
/// of no sim task (a real robot's) is rolled out on the first task, as every run was before there were others.
pub fn rollout_tasks(dataset: &LeRobotDataset) -> Vec<TaskKind> {
    let mut tasks: Vec<TaskKind> = Vec::new();
    for task in dataset.tasks().iter().filter_map(|instruction| TaskKind::of_instruction(instruction)) {
        if !tasks.contains(&task) {
            tasks.push(task);
        }
    }
    if tasks.is_empty() {
        tasks.push(TaskKind::CubeInBowl);
    }
    tasks
}

/// The dataset a run trains on: the configured path, or for the embedded default its recording of
/// `dataset-episodes` episodes of `dataset-tasks` at the policy's image size
/// (`data/so100-sim/<N>ep_<S>px[_noise<D>][_<task>+<task>...][_seed<F>]`, recorded by the sim's expert from seed
/// `dataset-seed` on first use, whatever the run's seed, so every run of that size shares it). Runs started in
/// parallel call this first, once: two runs recording the same dataset at once would write over each other.
pub fn ensure_dataset(config: &RunConfig) -> anyhow::Result<PathBuf> {
    let root = dataset_root(config)?;
    if config.dataset != EMBEDDED_DATASET {
        anyhow::ensure!(
            root.join("meta/info.json").exists(),
            "dataset {} not found (no meta/info.json); point `dataset` at a LeRobot dataset or use the embedded default {:?}",
            root.display(),
            EMBEDDED_DATASET
        );
        return Ok(root);
    }
    if root.join("meta/info.json").exists() {
        return Ok(root);
    }
    if root.exists() {
        // Left by a recording that was killed: it never finished, so it is no dataset.
        std::fs::remove_dir_all(&root).with_context(|| format!("removing the unfinished {}", root.display()))?;
    }
    let bar = indicatif::ProgressBar::new(config.dataset_episodes as u64);
    bar.set_style(indicatif::ProgressStyle::with_template(
        "recording the embedded SO-100 dataset [{bar:30}] {pos}/{len} expert episodes {msg} ({elapsed})",
    )?);
    let tasks: Vec<&str> = config.dataset_tasks.iter().map(|task| task.name()).collect();
    bar.println(format!(
        "recording {} expert episodes of {} into {}",
        config.dataset_episodes,
        tasks.join(", "),
        root.display()
    ));
    let options = GenDataOptions {
        episodes: config.dataset_episodes,
        seed: config.dataset_seed,
        tasks: config.dataset_tasks.clone(),
        image_size: model_config(config)?.resize_imgs_with_padding.1 as u32,
        action_noise_degrees: config.dataset_action_noise as f32,
        every_goal: config.dataset_every_goal,
    };
    generate_dataset(&root, &options, |event| match event {
        GenProgress::Frame { total_frames, .. } => bar.set_message(format!("{total_frames} frames")),
        GenProgress::EpisodeWritten { .. } => bar.inc(1),
        GenProgress::Skipped { .. } => {}
    })?;
    bar.finish_and_clear();
    Ok(root)
}

/// The dataset a run trains on, recorded or not yet: `dataset`, or the embedded default's recording for
/// the run's episodes, image size, perturbation, tasks and first seed.
pub fn dataset_root(config: &RunConfig) -> anyhow::Result<PathBuf> {
    if config.dataset != EMBEDDED_DATASET {
        return Ok(PathBuf::from(&config.dataset));
    }
    Ok(embedded_dataset(config, model_config(config)?.resize_imgs_with_padding.1))
}

/// Where the embedded default dataset of this many episodes at this image size (and perturbation, tasks and first
/// seed) lives. The cube-in-bowl task alone and seed 0 add nothing to the name: their recordings predate the others.
fn embedded_dataset(config: &RunConfig, image_size: usize) -> PathBuf {
    let noise = match config.dataset_action_noise {
        0.0 => String::new(),
        degrees => format!("_noise{degrees}"),
    };
    let tasks = match config.dataset_tasks.as_slice() {
        [TaskKind::CubeInBowl] => String::new(),
        tasks => format!("_{}", tasks.iter().map(|task| task.name()).collect::<Vec<_>>().join("+")),
    };
    let first_seed = match config.dataset_seed {
        0 => String::new(),
        seed => format!("_seed{seed}"),
    };
    let every_goal = if config.dataset_every_goal { "_every-goal" } else { "" };
    Path::new(EMBEDDED_DATASET)
        .join(format!("{}ep_{image_size}px{noise}{tasks}{first_seed}{every_goal}", config.dataset_episodes))
}

/// The partitioner's strategy for the configuration's `partitioning` (and `partition-alpha`).
fn partition_strategy(config: &RunConfig) -> PartitionStrategy {
    match config.partitioning {
        Partitioning::Iid => PartitionStrategy::EpisodeModulo,
        Partitioning::ByEpisode => PartitionStrategy::Contiguous,
        Partitioning::ByLayout => PartitionStrategy::ContiguousInGivenOrder,
        Partitioning::ByTask => PartitionStrategy::ByTask,
        Partitioning::Dirichlet => PartitionStrategy::Dirichlet { alpha: config.partition_alpha },
    }
}

/// The dataset's episodes as the partitioner gets them: in index order, or for `by-layout` in the order of where
/// the sim put the cube each episode's task moves (its azimuth around the arm's base, from the recorded seed and
/// task).
pub fn episodes_to_partition(
    config: &RunConfig,
    root: &Path,
    dataset: &LeRobotDataset,
) -> anyhow::Result<Vec<EpisodeTask>> {
    let mut episodes = episode_tasks(dataset);
    if config.partitioning == Partitioning::ByLayout {
        let recorded = recorded_seeds(root)?.with_context(|| {
            format!(
                "partitioning = \"by-layout\" needs a dataset the sim recorded ({} in {})",
                SEEDS_FILE,
                root.display()
            )
        })?;
        let azimuth = |e: &EpisodeTask| -> anyhow::Result<f32> {
            let arrangement = recorded.arrangement_of(e.episode_index).with_context(|| {
                format!("{} lists no seed for episode {} of {}", SEEDS_FILE, e.episode_index, root.display())
            })?;
            let cube = arrangement.subject().position;
            Ok(cube.x.atan2(-cube.y))
        };
        let mut keyed = episodes.iter().map(|e| Ok((azimuth(e)?, *e))).collect::<anyhow::Result<Vec<_>>>()?;
        keyed.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.episode_index.cmp(&b.1.episode_index)));
        episodes = keyed.into_iter().map(|(_, e)| e).collect();
    }
    Ok(episodes)
}

/// How a run splits its dataset's episodes among its clients and the server.
fn partition_config(config: &RunConfig) -> PartitionConfig {
    PartitionConfig {
        num_clients: config.num_clients,
        strategy: partition_strategy(config),
        client_held_out_fraction: CLIENT_HELD_OUT,
        server_held_out_fraction: SERVER_HELD_OUT,
        seed: config.seed,
    }
}

/// `model-size` with the run configuration's changes to it (what is trained, image and patch size, action chunk).
fn model_config(config: &RunConfig) -> anyhow::Result<SmolVlaConfig> {
    let from_checkpoint = !config.init_policy.is_empty();
    let mut cfg = SmolVlaConfig::preset(&config.model_size)?.with_trained_parts(
        config.freeze_vision_encoder.resolve(from_checkpoint),
        config.train_expert_only.resolve(from_checkpoint),
    );
    if config.image_size > 0 || config.patch_size > 0 {
        let v = &cfg.vlm.vision_config;
        let size = if config.image_size > 0 { config.image_size } else { v.image_size };
        let patch = if config.patch_size > 0 { config.patch_size } else { v.patch_size };
        cfg = cfg.with_image_size(size, patch);
    }
    if config.chunk_size > 0 || config.n_action_steps > 0 {
        let chunk = if config.chunk_size > 0 { config.chunk_size } else { cfg.chunk_size };
        let steps = if config.n_action_steps > 0 { config.n_action_steps } else { chunk.min(cfg.n_action_steps) };
        cfg = cfg.with_action_chunk(chunk, steps);
    }
    cfg.validate()?;
    Ok(cfg)
}

/// The policy configuration of `model-size`, with the dataset's cameras (in its order) as inputs.
fn policy_config(config: &RunConfig, dataset: &LeRobotDataset) -> anyhow::Result<SmolVlaConfig> {
    let mut cfg = model_config(config)?;
    let features = &dataset.info().features;
    let cameras: Vec<Feature> = dataset
        .camera_keys()
        .into_iter()
        .map(|key| {
            let shape = features.get(&key).map(|f| f.shape.clone()).unwrap_or_default();
            // LeRobot declares camera features channels-first; datasets store [H, W, C].
            let (h, w) = (shape.first().copied().unwrap_or(0), shape.get(1).copied().unwrap_or(0));
            Feature { name: key, kind: "VISUAL".into(), shape: vec![3, h, w] }
        })
        .collect();
    cfg.input_features.retain(|f| f.kind != "VISUAL");
    cfg.input_features.extend(cameras);
    cfg.validate()?;
    Ok(cfg)
}

fn describe_inputs(
    root: &Path,
    dataset: &LeRobotDataset,
    cfg: &SmolVlaConfig,
    stats: &NormStats,
    tokenizer: &RunTokenizer,
) -> String {
    use std::fmt::Write;
    let features = &dataset.info().features;
    let (w, h) = cfg.resize_imgs_with_padding;
    let mut out = format!(
        "dataset {}: {} episodes, {} frames at {} fps, tasks {:?}\n",
        root.display(),
        dataset.episodes().len(),
        dataset.len(),
        dataset.fps(),
        dataset.tasks()
    );
    let cameras = cfg.input_features.iter().filter(|f| f.kind == "VISUAL");
    for (i, camera) in cameras.enumerate() {
        let _ = writeln!(
            out,
            "  camera {i}: {} ({}x{}, resized with padding to {w}x{h})",
            camera.name,
            camera.shape.get(2).copied().unwrap_or(0),
            camera.shape.get(1).copied().unwrap_or(0)
        );
    }
    for key in ["observation.state", "action"] {
        let names = features.get(key).map(|f| f.names.to_string()).unwrap_or_default();
        let _ = writeln!(out, "  {key}: {names}");
        if let Ok(s) = stats.get(key) {
            let fmt = |v: &[f32]| v.iter().map(|x| format!("{x:.3}")).collect::<Vec<_>>().join(", ");
            let _ = writeln!(out, "    normalised with mean [{}], std [{}]", fmt(&s.mean), fmt(&s.std));
        }
    }
    let _ = write!(out, "  tokenizer: {}", tokenizer.describe());
    out
}

/// The statistics of `meta/stats.json` the policy normalises with.
fn dataset_stats(dataset: &LeRobotDataset) -> anyhow::Result<NormalizationStats> {
    let stats = dataset.stats().context("the dataset has no meta/stats.json")?;
    let mut features = BTreeMap::new();
    for feature in NORMALISED_FEATURES {
        let s = stats.get(feature).with_context(|| format!("meta/stats.json has no {feature}"))?;
        let summary = FeatureSummary {
            count: s.count,
            mean: s.mean.clone(),
            std: s.std.clone(),
            min: s.min.clone(),
            max: s.max.clone(),
        };
        features.insert(feature.to_owned(), summary);
    }
    Ok(NormalizationStats { source: StatsSource::Dataset, clients: 0, features })
}

impl SmolVlaWorkload {
    /// Opens (or records) the dataset, partitions it among `config.num_clients` clients and writes
    /// their shards and the server's held-out shard into `shard_dir`.
    pub fn prepare(config: &RunConfig, shard_dir: &Path) -> anyhow::Result<Self> {
        Self::prepare_with(config, shard_dir, false)
    }

    /// [`SmolVlaWorkload::prepare`] plus the pooled shard of every client's training episodes, for
    /// [`SmolVlaWorkload::centralized_trainer`].
    pub fn prepare_centralized(config: &RunConfig, shard_dir: &Path) -> anyhow::Result<Self> {
        Self::prepare_with(config, shard_dir, true)
    }

    fn prepare_with(config: &RunConfig, shard_dir: &Path, pooled: bool) -> anyhow::Result<Self> {
        let root = ensure_dataset(config)?;
        let dataset = LeRobotDataset::open(&root).with_context(|| format!("opening dataset {}", root.display()))?;
        let cfg = policy_config(config, &dataset)?;
        let init_path = Path::new(&config.init_policy);
        let init = match config.init_policy.as_str() {
            "" => None,
            path => Some(PolicyDir::load(init_path).with_context(|| format!("loading init-policy {path}"))?),
        };
        let tokenizer = RunTokenizer::choose(init.as_ref().map(|p| (init_path, p)), dataset.tasks())?;
        anyhow::ensure!(
            tokenizer.vocab_size() <= cfg.vlm.text_config.vocab_size,
            "the run's tokenizer ({}) has {} tokens, more than the {} of the token embedding of model size {}",
            tokenizer.describe(),
            tokenizer.vocab_size(),
            cfg.vlm.text_config.vocab_size,
            config.model_size
        );
        let parts = partition(&episodes_to_partition(config, &root, &dataset)?, &partition_config(config))?;
        std::fs::create_dir_all(shard_dir).with_context(|| format!("creating {}", shard_dir.display()))?;
        let spec = shard_spec(&cfg);
        let task_ids =
            task_token_ids(&tokenizer.tokenizer(), dataset.tasks(), &cfg).context("tokenizing the dataset's tasks")?;
        let tokenize = |task: &str| -> Vec<u32> { task_ids.get(task).cloned().unwrap_or_default() };
        let length: BTreeMap<usize, usize> = dataset.episodes().iter().map(|e| (e.episode_index, e.length)).collect();
        // Every episode is decoded once per shard it lands in; with hundreds of episodes that takes minutes.
        let pooled_episodes = if pooled { parts.clients.iter().map(|c| c.train.len()).sum::<usize>() } else { 0 };
        let to_pack = parts.clients.iter().map(|c| c.all().count()).sum::<usize>()
            + parts.server_held_out.len()
            + pooled_episodes;
        let bar = indicatif::ProgressBar::new(to_pack as u64);
        bar.set_style(indicatif::ProgressStyle::with_template(
            "building shards [{bar:30}] {pos}/{len} episodes decoded and packed ({elapsed}, eta {eta})",
        )?);
        let mut packed = |_: &fedvla_data::EpisodeMeta| bar.inc(1);
        let client_shards = (0..config.num_clients)
            .map(|k| {
                let path = shard_dir.join(format!("client_{k}.safetensors"));
                build_shard(&dataset, &parts, k, &spec, Some(&tokenize), &path, &mut packed)
                    .with_context(|| format!("building shard {k}"))?;
                let train_examples = parts.clients[k].train.iter().map(|e| length[e] as u64).sum();
                Ok(ShardOffer { file: Some(path), train_examples })
            })
            .collect::<anyhow::Result<Vec<_>>>()?;
        // The server's held-out episodes, packed like a client's held-out split.
        let server_parts = Partition {
            clients: vec![ClientSplit { train: Vec::new(), held_out: parts.server_held_out.clone() }],
            ..parts.clone()
        };
        let server_shard = shard_dir.join("server_heldout.safetensors");
        build_shard(&dataset, &server_parts, 0, &spec, Some(&tokenize), &server_shard, &mut packed)
            .context("building the server's held-out shard")?;
        let pooled_shard = shard_dir.join("pooled_train.safetensors");
        if pooled {
            // The union of the clients' training episodes; their held-out episodes stay out.
            let mut train: Vec<usize> = parts.clients.iter().flat_map(|c| c.train.iter().copied()).collect();
            train.sort_unstable();
            let pooled = Partition { clients: vec![ClientSplit { train, held_out: Vec::new() }], ..parts.clone() };
            build_shard(&dataset, &pooled, 0, &spec, Some(&tokenize), &pooled_shard, &mut packed)
                .context("building the pooled training shard")?;
        }
        bar.finish_and_clear();
        let checkpoint_dtype = init.as_ref().map_or(StoredDtype::F32, |policy| policy.dtype);
        let export_dtype = match config.export_dtype {
            ExportDtype::F32 => StoredDtype::F32,
            ExportDtype::Bf16 => StoredDtype::Bf16,
            ExportDtype::Auto => checkpoint_dtype,
        };
        let weights = match init {
            None => init_random(&cfg.param_specs(), config.seed),
            Some(policy) => {
                anyhow::ensure!(
                    policy.cfg.param_specs() == cfg.param_specs(),
                    "init-policy {} does not have the tensors of model size {} with this dataset's cameras",
                    config.init_policy,
                    config.model_size
                );
                policy.weights
            }
        };
        let trained: std::collections::BTreeSet<String> =
            cfg.param_specs().into_iter().filter(|s| s.trainable).map(|s| s.name).collect();
        let (trainable, frozen): (WeightMap, WeightMap) = weights.into_iter().partition(|(k, _)| trained.contains(k));
        let dataset_stats = dataset_stats(&dataset)?;
        let stats = norm_stats(&dataset_stats)?;
        Ok(Self {
            inputs: describe_inputs(&root, &dataset, &cfg, &stats, &tokenizer),
            signature: dataset_signature(dataset.info()),
            dataset_stats,
            stats,
            cfg,
            frozen: ParamStore::upload_owned(frozen, &Device::flex(), false),
            trainable: ParamStore::upload_owned(trainable, &Device::flex(), false),
            tokenizer,
            export_dtype,
            checkpoint_dtype,
            client_shards,
            server_shard,
            pooled_shard,
            rollout_tasks: rollout_tasks(&dataset),
            seed: config.seed,
        })
    }

    /// One trainer on every client's training episodes (the shard [`SmolVlaWorkload::prepare_centralized`]
    /// pooled), from the run's initial weights, stepping on `device`: the centralized baseline of a federation.
    pub fn centralized_trainer(&self, device: ComputeDevice) -> Result<SmolVlaTrainer, BoxError> {
        let examples = self.examples(&self.pooled_shard)?;
        let (device, backend) = training_device(device)?;
        let mut weights = self.frozen.to_host();
        weights.extend(self.trainable.to_host());
        SmolVlaTrainer::new(&self.cfg, weights, examples, self.seed, &device, backend)
    }

    fn examples(&self, path: &Path) -> Result<ShardExamples, BoxError> {
        let shard = ClientShard::read(path)?;
        Ok(ShardExamples::new(shard, &self.cfg)?)
    }

    /// What the policy is fed, for a robot owner to check at the start of a run: the dataset, the cameras in
    /// the order the policy reads them, the state and action features with their names, the normalisation
    /// statistics, and the tokenizer.
    pub fn inputs(&self) -> &str {
        &self.inputs
    }

    pub fn policy_config(&self) -> &SmolVlaConfig {
        &self.cfg
    }
}

impl Workload for SmolVlaWorkload {
    fn initial_model(&self) -> Result<NamedTensors, BoxError> {
        Ok(to_named(&self.trainable.to_host())?)
    }

    fn evaluator(&self) -> Result<Box<dyn Evaluator + Send>, BoxError> {
        let mut examples = self.examples(&self.server_shard)?;
        examples.add_other_goals(&self.tokenizer.tokenizer(), &self.cfg)?;
        let cpu = Device::flex();
        let store = self.frozen.overlaid(&self.trainable);
        Ok(Box::new(HeldOutEvaluator::new(&self.cfg, &store, examples, &cpu)))
    }

    fn exporters(&self) -> Vec<Box<dyn ModelExporter>> {
        vec![
            Box::new(LeRobotExport {
                cfg: self.cfg.clone(),
                frozen: self.frozen.clone(),
                stats: RwLock::new(self.stats.clone()),
                tokenizer: self.tokenizer.clone(),
                dtype: self.export_dtype,
            }),
            Box::new(SimRollouts {
                cfg: self.cfg.clone(),
                frozen: self.frozen.clone(),
                stats: RwLock::new(self.stats.clone()),
                tokenizer: self.tokenizer.tokenizer(),
                tasks: self.rollout_tasks.clone(),
            }),
        ]
    }

    fn volunteer_offer(&self) -> Result<VolunteerOffer, BoxError> {
        let rollout_tasks = SimTasks::tokenize(&self.rollout_tasks, &self.tokenizer.tokenizer(), &self.cfg)?;
        Ok(VolunteerOffer {
            workload: WorkloadKind::Smolvla,
            shards: self.client_shards.clone(),
            policy: serde_json::json!({ "policy": self.cfg.to_lerobot_json(), "vlm": self.cfg.vlm_config_json() }),
            frozen: Some(safetensors_bytes_as(self.frozen.refs(), self.checkpoint_dtype)?.into()),
            rollout_tasks: rollout_tasks.to_wire(),
            signature: Some(self.signature.clone()),
            norm_stats: Some(self.dataset_stats.clone()),
            tokenizer: Some(self.tokenizer.json().map_err(|e| format!("{e:#}"))?.into()),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn by_task_and_dirichlet_partitionings_are_reachable_from_the_configuration() {
        let config = |overrides: &str| RunConfig::default().with_overrides(overrides).unwrap();
        let episodes: Vec<EpisodeTask> = (0..40).map(|i| EpisodeTask { episode_index: i, task_index: i % 4 }).collect();
        let split = |config: &RunConfig| partition(&episodes, &partition_config(config)).unwrap();

        let by_task = config("partitioning=by-task num-clients=4");
        assert_eq!(partition_strategy(&by_task), PartitionStrategy::ByTask);
        for client in split(&by_task).clients {
            let mut tasks: Vec<usize> = client.all().map(|e| e % 4).collect();
            tasks.dedup();
            assert_eq!(tasks.len(), 1, "one task per client: {client:?}");
        }

        let dirichlet = config("partitioning=dirichlet partition-alpha=0.2 num-clients=4");
        assert_eq!(partition_strategy(&dirichlet), PartitionStrategy::Dirichlet { alpha: 0.2 });
        let uniform = config("partitioning=dirichlet partition-alpha=1000 num-clients=4");
        // Small alpha: some client lacks some task; huge alpha: every client holds every task.
        let tasks_held = |config: &RunConfig| -> Vec<usize> {
            split(config)
                .clients
                .iter()
                .map(|c| c.all().map(|e| e % 4).collect::<std::collections::BTreeSet<_>>().len())
                .collect()
        };
        assert!(tasks_held(&dirichlet).iter().any(|&n| n < 4), "{:?}", tasks_held(&dirichlet));
        assert!(tasks_held(&uniform).iter().all(|&n| n == 4), "{:?}", tasks_held(&uniform));

        let err = RunConfig::default().with_overrides("partition-alpha=0").unwrap_err().to_string();
        assert!(err.contains("partition-alpha"), "{err}");
    }
}
