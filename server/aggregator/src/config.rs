//! Run configuration: `configs/default.toml` plus `--run-config "key=value ..."` overrides.

use std::path::Path;

use fedvla_federation::UpdateEncoding;
use fedvla_sim::TaskKind;
use serde::{Deserialize, Serialize};

#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    #[error("reading {path}: {source}")]
    Read { path: String, source: std::io::Error },
    #[error("parsing {path}: {source}")]
    Parse { path: String, source: Box<toml::de::Error> },
    #[error("override `{0}` is not of the form key=value")]
    NotKeyValue(String),
    #[error("unknown config key `{key}`; known keys: {known}")]
    UnknownKey { key: String, known: String },
    #[error("bad value for `{key}`: {message}")]
    BadValue { key: String, message: String },
    #[error("invalid configuration: {0}")]
    Invalid(String),
}

/// How the learning rate moves over a run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum LrScheduleKind {
    Constant,
    /// LeRobot's: linear warmup, then cosine decay to `lr-final-fraction` of `lr`, over the run's steps.
    Cosine,
}

/// Aggregation strategy.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum StrategyKind {
    Fedavg,
    /// FedAvg with the clients' proximal term (`proximal-mu`).
    Fedprox,
    /// FedAvg plus server momentum (`server-lr`, `server-momentum`).
    Fedavgm,
    /// Adaptive server optimizers of Reddi et al. 2021 (`server-lr`, `server-beta1`, `server-beta2`, `server-tau`).
    Fedadagrad,
    Fedyogi,
    Fedadam,
    /// Coordinate-wise median of the clients' models.
    Median,
    /// Coordinate-wise mean without the `trim-beta` fraction of largest and of smallest values.
    TrimmedMean,
    /// The update nearest its neighbours, tolerating `krum-f` attackers (needs min-fit >= 2 krum-f + 3).
    Krum,
    /// The mean of the `krum-keep` updates Krum ranks best.
    MultiKrum,
    /// Krum's `n - 2 krum-f` best, then per coordinate the mean of the `n - 4 krum-f` nearest their median
    /// (needs min-fit >= 4 krum-f + 3).
    Bulyan,
    /// SCAFFOLD (Karimireddy et al. 2020, option II): control variates per client, kept by the server; `server-lr`.
    Scaffold,
    /// q-FedAvg (Li et al. 2020): clients weighed by their reported loss to the power `qfedavg-q`, step size
    /// `qfedavg-lr`.
    Qfedavg,
}

pub use fedvla_federation::WorkloadKind;

/// The dataset path that means "record the SO-100 sim's expert episodes here on first use".
pub const EMBEDDED_DATASET: &str = "data/so100-sim";

/// How the dataset is split across clients.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Partitioning {
    /// Every client draws from the same distribution.
    Iid,
    /// Each client holds whole episodes, so its data is skewed towards its own states.
    ByEpisode,
    /// Each client holds the episodes of one region of the workspace (sim datasets: episodes ordered by where
    /// the cube starts, around the arm, then cut into contiguous runs): a volunteer whose table is always set
    /// up the same way.
    ByLayout,
    /// Each task of a multi-task dataset goes whole to one client (tasks dealt round-robin in a seeded order): a
    /// volunteer who records only its own task.
    ByTask,
    /// Per task, the clients' shares drawn from Dirichlet(`partition-alpha`): small alpha, each task mostly on
    /// few clients; large alpha, every client near the same mix of tasks.
    Dirichlet,
}

/// How `simulate`'s attackers corrupt their updates (see `fedvla_server::attack`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum AttackKind {
    /// `global + strength * (update - global)`.
    Scale,
    /// `global - strength * (update - global)`.
    SignFlip,
    /// `global + strength * N(0, 1)` in every value, the honest update thrown away.
    Noise,
    /// Data poisoning: the client trains on its shard with the labels (actions; linreg's targets) of its training
    /// rows shuffled among them, and sends that update as is (`attack-strength` does not apply).
    LabelShuffle,
}

/// One of LeRobot's switches of what is trained (`freeze-vision-encoder`, `train-expert-only`): `true`,
/// `false`, or `"auto"`: on (LeRobot's default) for a run from an `init-policy` checkpoint, whose backbone is
/// pretrained and worth keeping, off from random initialisation, where there is nothing pretrained to keep
/// frozen (server/LEARNING.md, E13: 14% success with the backbone frozen against 38% trained).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TrainSwitch {
    Auto,
    On,
    Off,
}

impl TrainSwitch {
    /// The switch's value for a run that starts from a checkpoint (`from_checkpoint`) or from random weights.
    pub fn resolve(self, from_checkpoint: bool) -> bool {
        match self {
            Self::Auto => from_checkpoint,
            Self::On => true,
            Self::Off => false,
        }
    }
}

impl Serialize for TrainSwitch {
    fn serialize<S: serde::Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        match self {
            Self::Auto => serializer.serialize_str("auto"),
            Self::On => serializer.serialize_bool(true),
            Self::Off => serializer.serialize_bool(false),
        }
    }
}

impl<'de> Deserialize<'de> for TrainSwitch {
    /// `true`, `false` or `"auto"`; a command-line override arrives as the text `true`/`false` (the default's
    /// value is a string), so those spellings are accepted as strings too.
    fn deserialize<D: serde::Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        #[derive(Deserialize)]
        #[serde(untagged)]
        enum Repr {
            Bool(bool),
            Text(String),
        }
        match Repr::deserialize(deserializer)? {
            Repr::Bool(true) => Ok(Self::On),
            Repr::Bool(false) => Ok(Self::Off),
            Repr::Text(t) => match t.as_str() {
                "auto" => Ok(Self::Auto),
                "true" => Ok(Self::On),
                "false" => Ok(Self::Off),
                other => Err(serde::de::Error::custom(format!("expected true, false or \"auto\", got {other:?}"))),
            },
        }
    }
}

/// The dtype of each round's exported `model.safetensors`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ExportDtype {
    /// That of the `init-policy` checkpoint (bf16 for LeRobot's `smolvla_base`), f32 from random weights.
    Auto,
    F32,
    Bf16,
}

/// Which rounds' global models a run keeps in `global_model/round_N/` once later rounds have completed.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum KeepModels {
    /// Every round's.
    All,
    /// Round 0's, those of the rounds that evaluated the global model (its held-out figures or rollouts in their
    /// metrics line), and the last completed round's, which a resumed run starts from: a run of hundreds of short
    /// rounds keeps a handful of models, not hundreds.
    Evaluated,
}

/// Where the training steps of `simulate`'s volunteers and of `train`'s centralized baseline run (a volunteer
/// that joins chooses its own: `fedvla join --device`). The server's held-out evaluation and rollouts stay on
/// the CPU either way.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ComputeDevice {
    /// burn's flex backend on the CPU, in every build.
    #[default]
    Cpu,
    /// burn's wgpu backend (WGSL: Vulkan, Metal or DX12, whichever the machine has), in builds with the `gpu`
    /// feature; every simulated volunteer shares the one GPU.
    Wgpu,
}

impl std::str::FromStr for ComputeDevice {
    type Err = String;

    /// The spellings of the configuration (`--device` on the command line).
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "cpu" => Ok(Self::Cpu),
            "wgpu" => Ok(Self::Wgpu),
            other => Err(format!("unknown device {other:?}: expected \"cpu\" or \"wgpu\"")),
        }
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case", deny_unknown_fields)]
pub struct RunConfig {
    pub num_server_rounds: u64,
    pub fraction_fit: f64,
    pub min_clients: usize,
    pub min_fit: usize,
    pub local_steps: u32,
    pub batch_size: u32,
    pub lr: f64,
    pub lr_schedule: LrScheduleKind,
    pub lr_warmup_fraction: f64,
    pub lr_final_fraction: f64,
    pub keep_optimizer_state: bool,
    pub opening_frames: u32,
    pub opening_frames_repeat: u32,
    pub seed: u64,
    pub strategy: StrategyKind,
    pub proximal_mu: f64,
    pub server_lr: f64,
    pub server_momentum: f64,
    pub server_beta1: f64,
    pub server_beta2: f64,
    pub server_tau: f64,
    pub trim_beta: f64,
    pub qfedavg_q: f64,
    pub qfedavg_lr: f64,
    pub krum_f: usize,
    pub krum_keep: usize,
    pub clip_update_norm: f64,
    pub clip_update_quantile: f64,
    pub update_norm_factor: f64,
    pub dp_noise_multiplier: f64,
    pub dp_clip_norm: f64,
    pub dp_clip_quantile: f64,
    pub dp_clip_lr: f64,
    pub dp_clip_count_stddev: f64,
    pub dp_delta: f64,
    pub attackers: usize,
    pub attack: AttackKind,
    pub attack_strength: f64,
    pub update_encoding: String,
    pub topk_fraction: f64,
    pub workload: WorkloadKind,
    pub dataset: String,
    pub dataset_episodes: usize,
    pub dataset_action_noise: f64,
    pub dataset_seed: u64,
    #[serde(with = "task_names")]
    pub dataset_tasks: Vec<TaskKind>,
    /// Absent from run directories written before it existed, whose recordings drew one goal a layout.
    #[serde(default)]
    pub dataset_every_goal: bool,
    pub num_clients: usize,
    pub partitioning: Partitioning,
    pub partition_alpha: f64,
    pub federated_stats: bool,
    pub own_data_max_examples: u64,
    pub own_datasets: Vec<String>,
    pub model_size: String,
    pub init_policy: String,
    pub export_dtype: ExportDtype,
    pub freeze_vision_encoder: TrainSwitch,
    pub train_expert_only: TrainSwitch,
    pub image_size: usize,
    pub patch_size: usize,
    pub chunk_size: usize,
    pub n_action_steps: usize,
    /// Absent from run directories written before it existed, which trained on the CPU.
    #[serde(default)]
    pub device: ComputeDevice,
    pub eval_every: u64,
    pub keep_models: KeepModels,
    pub rollout_episodes: usize,
    pub client_rollout_episodes: u32,
    pub rollout_max_frames: u32,
    pub round_deadline_ms: u64,
    pub listen: String,
    pub tls_cert: String,
    pub tls_key: String,
    pub max_frame_bytes: usize,
    pub auth_token: String,
    pub allowed_keys: String,
    pub operator_token: String,
    pub max_connections: usize,
    pub header_read_timeout_ms: u64,
    pub idle_timeout_ms: u64,
    pub max_volunteer_names: usize,
    pub joins_per_address_per_minute: u32,
    pub max_messages_per_second: u32,
    pub max_rollout_videos: u32,
    pub max_video_bytes: u64,
    pub max_upload_memory_bytes: u64,
    pub auto_start: bool,
    pub www_dir: String,
    pub output_dir: String,
}

/// A list of sim tasks as configurations and records spell it: their names ([`TaskKind::name`]); an unknown
/// name is refused with the known ones.
pub mod task_names {
    use fedvla_sim::TaskKind;
    use serde::{Deserialize, Deserializer, Serializer};

    pub fn serialize<S: Serializer>(tasks: &[TaskKind], serializer: S) -> Result<S::Ok, S::Error> {
        serializer.collect_seq(tasks.iter().map(|task| task.name()))
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(deserializer: D) -> Result<Vec<TaskKind>, D::Error> {
        let names = Vec::<String>::deserialize(deserializer)?;
        names.iter().map(|name| TaskKind::from_name(name).map_err(serde::de::Error::custom)).collect()
    }
}

/// `configs/default.toml`, built in so the binary runs from anywhere.
pub const DEFAULT_CONFIG: &str = include_str!("../../../configs/default.toml");

impl Default for RunConfig {
    fn default() -> Self {
        Self::from_toml(DEFAULT_CONFIG, "configs/default.toml").expect("configs/default.toml is valid")
    }
}

impl RunConfig {
    /// Parses a configuration; keys it does not set take configs/default.toml's values (so a run directory written
    /// before a key existed still resumes), unknown keys are refused.
    pub fn from_toml(text: &str, path: &str) -> Result<Self, ConfigError> {
        let parse_error = |e| ConfigError::Parse { path: path.into(), source: Box::new(e) };
        let mut table: toml::Table = toml::from_str(text).map_err(parse_error)?;
        let defaults: toml::Table = toml::from_str(DEFAULT_CONFIG).expect("configs/default.toml is TOML");
        for (key, value) in defaults {
            table.entry(key).or_insert(value);
        }
        let cfg: Self = table.try_into().map_err(parse_error)?;
        cfg.validate()?;
        Ok(cfg)
    }

    pub fn load(path: &Path) -> Result<Self, ConfigError> {
        let text = std::fs::read_to_string(path)
            .map_err(|source| ConfigError::Read { path: path.display().to_string(), source })?;
        Self::from_toml(&text, &path.display().to_string())
    }

    pub fn to_toml(&self) -> String {
        toml::to_string(self).expect("config serializes")
    }

    /// Applies space-separated `key=value` overrides (kebab-case keys, TOML values; bare words are strings, and
    /// for a list key a comma-separated run of bare words is a list of strings).
    pub fn with_overrides(&self, overrides: &str) -> Result<Self, ConfigError> {
        let mut table = toml::Table::try_from(self).expect("config serializes to a table");
        for pair in overrides.split_whitespace() {
            let (key, raw) = pair.split_once('=').ok_or_else(|| ConfigError::NotKeyValue(pair.into()))?;
            let Some(current) = table.get(key) else {
                return Err(ConfigError::UnknownKey {
                    key: key.into(),
                    known: table.keys().cloned().collect::<Vec<_>>().join(", "),
                });
            };
            let value =
                parse_value(raw, current).map_err(|message| ConfigError::BadValue { key: key.into(), message })?;
            // A value of the right TOML type can still be refused by the key's own type (an unknown strategy name):
            // tried alone on this configuration, so the error names the key.
            let mut alone = toml::Table::try_from(self).expect("config serializes to a table");
            alone.insert(key.into(), value.clone());
            alone
                .try_into::<Self>()
                .map_err(|e| ConfigError::BadValue { key: key.into(), message: e.message().to_owned() })?;
            table.insert(key.into(), value);
        }
        let cfg: Self = table.try_into().map_err(|e: toml::de::Error| ConfigError::BadValue {
            key: "run-config".into(),
            message: e.message().to_owned(),
        })?;
        cfg.validate()?;
        Ok(cfg)
    }

    /// The learning rate schedule of a run whose trainer takes `steps_per_round` steps a round, as of round
    /// `round`; `None` when the rate is constant.
    pub fn lr_schedule(&self, round: u64, steps_per_round: u64) -> Option<fedvla_federation::LrSchedule> {
        let total = self.num_server_rounds * steps_per_round;
        (self.lr_schedule == LrScheduleKind::Cosine).then(|| fedvla_federation::LrSchedule {
            warmup_steps: (total as f64 * self.lr_warmup_fraction) as u64,
            total_steps: total,
            final_lr: self.lr * self.lr_final_fraction,
            first_step: round.saturating_sub(1) * steps_per_round,
        })
    }

    /// How often clients draw the opening frames of episodes whose instruction decides the goal
    /// (`opening-frames`, `opening-frames-repeat`); `None` where every frame is drawn as often.
    pub fn opening_frames(&self) -> Option<fedvla_federation::OpeningFrames> {
        (self.opening_frames > 0 && self.opening_frames_repeat > 1).then_some(fedvla_federation::OpeningFrames {
            frames: self.opening_frames,
            repeat: self.opening_frames_repeat,
        })
    }

    /// How clients encode their updates (`update-encoding`, `topk-fraction`).
    pub fn encoding(&self) -> UpdateEncoding {
        UpdateEncoding::parse(&self.update_encoding, self.topk_fraction).expect("validated with the config")
    }

    /// The token clients must present (`auth-token`), or `None` for a public run.
    pub fn auth_token(&self) -> Option<&str> {
        Some(self.auth_token.as_str()).filter(|t| !t.is_empty())
    }

    /// The allow-list of a closed federation's volunteer keys (`allowed-keys`), or `None` to admit any key.
    pub fn allowed_keys_file(&self) -> Option<&Path> {
        (!self.allowed_keys.is_empty()).then(|| Path::new(&self.allowed_keys))
    }

    /// The certificate chain and private key files the server presents over TLS (`tls-cert`, `tls-key`), or
    /// `None` to listen in plain HTTP.
    pub fn tls_files(&self) -> Option<(&Path, &Path)> {
        (!self.tls_cert.is_empty()).then(|| (Path::new(&self.tls_cert), Path::new(&self.tls_key)))
    }

    /// Whether client-level DP-FedAvg wraps the strategy.
    pub fn dp_enabled(&self) -> bool {
        self.dp_noise_multiplier > 0.0
    }

    /// The rate at which a round samples clients from all `num-clients` (what the privacy accountant needs).
    pub fn dp_sampling_rate(&self) -> f64 {
        self.sampled_clients(self.num_clients) as f64 / self.num_clients as f64
    }

    /// The noise on the adaptive clipping norm's count of clipped clients: as configured, or (0) Andrew et al.'s
    /// choice of the expected sampled clients / 20.
    pub fn dp_count_stddev(&self) -> f64 {
        match self.dp_clip_count_stddev {
            0.0 => self.sampled_clients(self.num_clients) as f64 / 20.0,
            s => s,
        }
    }

    fn validate_dp(&self) -> Result<(), ConfigError> {
        let fail = |m: String| Err(ConfigError::Invalid(m));
        let finite_at_least_0 = |v: f64| v.is_finite() && v >= 0.0;
        if !finite_at_least_0(self.dp_noise_multiplier) || !finite_at_least_0(self.dp_clip_count_stddev) {
            return fail(format!(
                "dp-noise-multiplier and dp-clip-count-stddev must be 0 or positive, got {} and {}",
                self.dp_noise_multiplier, self.dp_clip_count_stddev
            ));
        }
        if !self.dp_enabled() {
            return Ok(());
        }
        if !(self.dp_clip_norm.is_finite() && self.dp_clip_norm > 0.0) {
            return fail(format!("dp-clip-norm must be positive, got {}", self.dp_clip_norm));
        }
        let delta_ok = self.dp_delta > 0.0 && self.dp_delta < 1.0;
        if !delta_ok || !(0.0..1.0).contains(&self.dp_clip_quantile) {
            return fail(format!(
                "dp-delta must be in (0, 1) and dp-clip-quantile in [0, 1), got {} and {}",
                self.dp_delta, self.dp_clip_quantile
            ));
        }
        let mean_based = [
            StrategyKind::Fedavg,
            StrategyKind::Fedprox,
            StrategyKind::Fedavgm,
            StrategyKind::Fedadagrad,
            StrategyKind::Fedyogi,
            StrategyKind::Fedadam,
        ];
        if !mean_based.contains(&self.strategy) {
            return fail(format!(
                "dp-noise-multiplier needs a strategy that averages (fedavg, fedprox or a server optimizer): the \
                 noise is sized to what one client can move a mean, not a {:?}",
                self.strategy
            ));
        }
        if self.clip_update_norm > 0.0 {
            return fail("clip-update-norm and dp-noise-multiplier both clip: DP-FedAvg clips to dp-clip-norm".into());
        }
        if self.dp_clip_quantile > 0.0 {
            if !(self.dp_clip_lr.is_finite() && self.dp_clip_lr > 0.0) {
                return fail(format!("dp-clip-lr must be positive, got {}", self.dp_clip_lr));
            }
            let count = self.dp_count_stddev();
            if self.dp_noise_multiplier >= 2.0 * count {
                return fail(format!(
                    "adaptive clipping spends part of the noise on its count: dp-noise-multiplier ({}) must be below \
                     2 x the count's standard deviation ({count}); raise dp-clip-count-stddev",
                    self.dp_noise_multiplier
                ));
            }
        }
        Ok(())
    }

    /// Clients a round samples when `connected` are connected: `fraction-fit` of them, at least `min-fit`.
    pub fn sampled_clients(&self, connected: usize) -> usize {
        ((self.fraction_fit * connected as f64).ceil() as usize).max(self.min_fit).min(connected)
    }

    pub fn validate(&self) -> Result<(), ConfigError> {
        let fail = |m: String| Err(ConfigError::Invalid(m));
        if !(self.fraction_fit > 0.0 && self.fraction_fit <= 1.0) {
            return fail(format!("fraction-fit must be in (0, 1], got {}", self.fraction_fit));
        }
        if self.min_fit == 0 {
            return fail("min-fit must be at least 1".into());
        }
        if self.min_clients < self.min_fit {
            return fail(format!("min-clients ({}) must be at least min-fit ({})", self.min_clients, self.min_fit));
        }
        if self.num_clients == 0 {
            return fail("num-clients must be at least 1".into());
        }
        if self.local_steps == 0 || self.batch_size == 0 {
            return fail("local-steps and batch-size must be at least 1".into());
        }
        if !(self.lr.is_finite() && self.lr > 0.0) {
            return fail(format!("lr must be positive, got {}", self.lr));
        }
        if !(0.0..1.0).contains(&self.lr_warmup_fraction) || !(0.0..=1.0).contains(&self.lr_final_fraction) {
            return fail(format!(
                "lr-warmup-fraction must be in [0, 1) and lr-final-fraction in [0, 1], got {} and {}",
                self.lr_warmup_fraction, self.lr_final_fraction
            ));
        }
        if self.opening_frames_repeat == 0 {
            return fail(
                "opening-frames-repeat must be at least 1 (1: opening frames drawn as often as the rest)".into(),
            );
        }
        if !(self.proximal_mu.is_finite() && self.proximal_mu >= 0.0) {
            return fail(format!("proximal-mu must be a non-negative number, got {}", self.proximal_mu));
        }
        if !(self.server_lr.is_finite() && self.server_lr > 0.0 && self.server_tau.is_finite() && self.server_tau > 0.0)
        {
            return fail(format!(
                "server-lr and server-tau must be positive, got {} and {}",
                self.server_lr, self.server_tau
            ));
        }
        for (key, value) in [
            ("server-momentum", self.server_momentum),
            ("server-beta1", self.server_beta1),
            ("server-beta2", self.server_beta2),
        ] {
            if !(0.0..1.0).contains(&value) {
                return fail(format!("{key} must be in [0, 1), got {value}"));
            }
        }
        if matches!(self.strategy, StrategyKind::Krum | StrategyKind::MultiKrum) {
            let need = 2 * self.krum_f + 3;
            if self.min_fit < need {
                return fail(format!(
                    "krum with krum-f={} needs at least {need} updates a round (n >= 2f + 3), but min-fit is {}",
                    self.krum_f, self.min_fit
                ));
            }
            if self.strategy == StrategyKind::MultiKrum && !(1..=self.min_fit - self.krum_f).contains(&self.krum_keep) {
                return fail(format!(
                    "krum-keep must be in [1, min-fit - krum-f] = [1, {}], got {}",
                    self.min_fit - self.krum_f,
                    self.krum_keep
                ));
            }
        }
        let bulyan_needs = fedvla_federation::Bulyan::min_updates(self.krum_f);
        if self.strategy == StrategyKind::Bulyan && self.min_fit < bulyan_needs {
            return fail(format!(
                "bulyan with krum-f={} needs at least {bulyan_needs} updates a round (n >= 4f + 3), but min-fit is {}",
                self.krum_f, self.min_fit
            ));
        }
        if self.attackers > self.num_clients || !(self.attack_strength.is_finite() && self.attack_strength > 0.0) {
            return fail(format!(
                "attackers ({}) must be at most num-clients ({}) and attack-strength positive, got {}",
                self.attackers, self.num_clients, self.attack_strength
            ));
        }
        if self.tls_cert.is_empty() != self.tls_key.is_empty() {
            return fail(format!(
                "tls-cert ({:?}) and tls-key ({:?}) go together: set both to serve TLS, neither for plain HTTP",
                self.tls_cert, self.tls_key
            ));
        }
        if !(self.clip_update_norm.is_finite() && self.clip_update_norm >= 0.0) {
            return fail(format!("clip-update-norm must be 0 (off) or positive, got {}", self.clip_update_norm));
        }
        if !(0.0..1.0).contains(&self.clip_update_quantile)
            || self.clip_update_quantile > 0.0
                && (self.clip_update_norm == 0.0 || !(self.dp_clip_lr.is_finite() && self.dp_clip_lr > 0.0))
        {
            return fail(format!(
                "clip-update-quantile must be in [0, 1) and, above 0, needs the norm it starts from, clip-update-norm \
                 > 0, and a positive dp-clip-lr; got {}, {} and {}",
                self.clip_update_quantile, self.clip_update_norm, self.dp_clip_lr
            ));
        }
        if !(self.update_norm_factor == 0.0 || self.update_norm_factor.is_finite() && self.update_norm_factor >= 1.0) {
            return fail(format!("update-norm-factor must be 0 (off) or at least 1, got {}", self.update_norm_factor));
        }
        self.validate_dp()?;
        UpdateEncoding::parse(&self.update_encoding, self.topk_fraction).map_err(ConfigError::Invalid)?;
        if !(self.qfedavg_q.is_finite()
            && self.qfedavg_q >= 0.0
            && self.qfedavg_lr.is_finite()
            && self.qfedavg_lr > 0.0)
        {
            return fail(format!(
                "qfedavg-q must be a number >= 0 and qfedavg-lr a positive one, got {} and {}",
                self.qfedavg_q, self.qfedavg_lr
            ));
        }
        if !(0.0..0.5).contains(&self.trim_beta) {
            return fail(format!("trim-beta must be in [0, 0.5), got {}", self.trim_beta));
        }
        if !(self.dataset_action_noise.is_finite() && (0.0..=20.0).contains(&self.dataset_action_noise)) {
            return fail(format!("dataset-action-noise must be in [0, 20] degrees, got {}", self.dataset_action_noise));
        }
        if !(self.partition_alpha.is_finite() && self.partition_alpha > 0.0) {
            return fail(format!("partition-alpha must be a positive number, got {}", self.partition_alpha));
        }
        if !self.own_datasets.is_empty() && self.workload != WorkloadKind::Smolvla {
            return fail("own-datasets needs the smolvla workload (linreg has no datasets)".into());
        }
        if self.dataset_tasks.is_empty() {
            return fail("dataset-tasks must name at least one task (`fedvla tasks` lists them)".into());
        }
        if self.eval_every == 0 {
            return fail("eval-every must be at least 1".into());
        }
        if self.round_deadline_ms == 0 {
            return fail("round-deadline-ms must be at least 1".into());
        }
        if self.max_connections == 0 || self.max_volunteer_names == 0 {
            return fail("max-connections and max-volunteer-names must be at least 1".into());
        }
        if self.header_read_timeout_ms == 0 || self.idle_timeout_ms < 1000 {
            return fail("header-read-timeout-ms must be at least 1 and idle-timeout-ms at least 1000".into());
        }
        if self.max_frame_bytes <= fedvla_federation::codec::HEADER_LEN {
            return fail(format!("max-frame-bytes must exceed {}", fedvla_federation::codec::HEADER_LEN));
        }
        self.validate_bounds()
    }

    /// The bounds on strangers' input (`joins-per-address-per-minute` and after): each at least 1, and none
    /// that makes what the run asks for impossible.
    fn validate_bounds(&self) -> Result<(), ConfigError> {
        let fail = |m: String| Err(ConfigError::Invalid(m));
        if self.joins_per_address_per_minute == 0
            || self.max_messages_per_second == 0
            || self.max_rollout_videos == 0
            || self.max_video_bytes == 0
        {
            return fail(
                "joins-per-address-per-minute, max-messages-per-second, max-rollout-videos and max-video-bytes \
                 must be at least 1"
                    .into(),
            );
        }
        if self.client_rollout_episodes > self.max_rollout_videos {
            return fail(format!(
                "client-rollout-episodes ({}) asks each client for more videos a round than max-rollout-videos ({})",
                self.client_rollout_episodes, self.max_rollout_videos
            ));
        }
        if self.max_upload_memory_bytes < self.max_video_bytes {
            return fail(format!(
                "max-upload-memory-bytes ({}) must hold at least one video of max-video-bytes ({})",
                self.max_upload_memory_bytes, self.max_video_bytes
            ));
        }
        Ok(())
    }
}

/// Parses `raw` as a TOML value of the same type as `current`.
fn parse_value(raw: &str, current: &toml::Value) -> Result<toml::Value, String> {
    use toml::Value;
    let parsed = toml::from_str::<toml::Table>(&format!("v = {raw}")).ok().and_then(|mut t| t.remove("v"));
    match (current, parsed) {
        (Value::String(_), Some(Value::String(s))) => Ok(Value::String(s)),
        (Value::String(_), _) => Ok(Value::String(raw.to_owned())),
        (Value::Integer(_), Some(Value::Integer(i))) => Ok(Value::Integer(i)),
        (Value::Float(_), Some(Value::Float(f))) => Ok(Value::Float(f)),
        (Value::Float(_), Some(Value::Integer(i))) => Ok(Value::Float(i as f64)),
        (Value::Boolean(_), Some(Value::Boolean(b))) => Ok(Value::Boolean(b)),
        (Value::Array(_), Some(Value::Array(items))) => Ok(Value::Array(items)),
        (Value::Array(_), _) => Ok(Value::Array(raw.split(',').map(|item| Value::String(item.to_owned())).collect())),
        (current, _) => Err(format!("`{raw}` is not of type {}", current.type_str())),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn default_parses_and_round_trips() {
        let cfg = RunConfig::default();
        assert_eq!(cfg.strategy, StrategyKind::Fedavgm);
        assert_eq!(RunConfig::from_toml(&cfg.to_toml(), "resolved").unwrap(), cfg);
    }

    #[test]
    fn the_trained_parts_default_to_lerobots_switches_from_a_checkpoint_and_to_everything_from_random_weights() {
        let cfg = RunConfig::default();
        assert_eq!((cfg.freeze_vision_encoder, cfg.train_expert_only), (TrainSwitch::Auto, TrainSwitch::Auto));
        assert!(cfg.train_expert_only.resolve(true) && !cfg.train_expert_only.resolve(false));
        let set = cfg.with_overrides("train-expert-only=true freeze-vision-encoder=false").unwrap();
        assert_eq!((set.train_expert_only, set.freeze_vision_encoder), (TrainSwitch::On, TrainSwitch::Off));
        assert!(set.train_expert_only.resolve(false) && !set.freeze_vision_encoder.resolve(true));
        assert_eq!(RunConfig::from_toml(&set.to_toml(), "resolved").unwrap(), set);
        let err = RunConfig::default().with_overrides("train-expert-only=yes").unwrap_err().to_string();
        assert!(err.contains("train-expert-only") && err.contains("\"yes\""), "{err}");
    }

    #[test]
    fn a_robust_rule_that_cannot_be_honoured_is_refused_naming_both_numbers() {
        let err = RunConfig::default().with_overrides("strategy=krum krum-f=1 min-fit=3").unwrap_err().to_string();
        assert!(err.contains("needs at least 5 updates") && err.contains("min-fit is 3"), "{err}");
        let err = RunConfig::default()
            .with_overrides("strategy=multi-krum krum-f=1 krum-keep=9 num-clients=5 min-clients=5 min-fit=5")
            .unwrap_err()
            .to_string();
        assert!(err.contains("= [1, 4], got 9"), "{err}");
        let err = RunConfig::default()
            .with_overrides("strategy=bulyan krum-f=1 num-clients=5 min-clients=5 min-fit=5")
            .unwrap_err()
            .to_string();
        assert!(err.contains("needs at least 7 updates") && err.contains("min-fit is 5"), "{err}");
        let ok = RunConfig::default().with_overrides("strategy=krum krum-f=1 num-clients=5 min-clients=5 min-fit=5");
        assert!(ok.is_ok(), "{ok:?}");
    }

    #[test]
    fn an_adaptive_clip_needs_a_norm_to_start_from() {
        let err = RunConfig::default().with_overrides("clip-update-quantile=0.5").unwrap_err().to_string();
        assert!(err.contains("clip-update-quantile") && err.contains("clip-update-norm"), "{err}");
        let err = RunConfig::default().with_overrides("clip-update-norm=1 clip-update-quantile=1").unwrap_err();
        assert!(err.to_string().contains("[0, 1)"), "{err}");
        assert!(RunConfig::default().with_overrides("clip-update-norm=1 clip-update-quantile=0.5").is_ok());
    }

    #[test]
    fn dp_settings_it_cannot_honour_are_refused() {
        let refused = |overrides: &str| RunConfig::default().with_overrides(overrides).unwrap_err().to_string();
        let err = refused("dp-noise-multiplier=1 strategy=median");
        assert!(err.contains("needs a strategy that averages"), "{err}");
        let err = refused("dp-noise-multiplier=1 clip-update-norm=2");
        assert!(err.contains("both clip"), "{err}");
        let err = refused("dp-noise-multiplier=1 dp-clip-norm=0");
        assert!(err.contains("dp-clip-norm must be positive"), "{err}");
        // 3 sampled clients: the count's noise defaults to 3/20, too little to leave a noise multiplier of 1.
        let err = refused("dp-noise-multiplier=1 dp-clip-quantile=0.5");
        assert!(err.contains("dp-noise-multiplier (1) must be below 2 x") && err.contains("(0.15)"), "{err}");
        let cfg = RunConfig::default()
            .with_overrides("dp-noise-multiplier=1 dp-clip-quantile=0.5 dp-clip-count-stddev=1 fraction-fit=0.5")
            .unwrap();
        assert_eq!((cfg.dp_count_stddev(), cfg.dp_sampling_rate()), (1.0, 2.0 / 3.0));
    }

    #[test]
    fn a_file_without_newer_keys_takes_their_defaults_and_unknown_keys_are_refused() {
        let old = "num-server-rounds = 3\nseed = 9\n";
        let cfg = RunConfig::from_toml(old, "old/config.toml").unwrap();
        assert_eq!((cfg.num_server_rounds, cfg.seed), (3, 9));
        assert_eq!(cfg.www_dir, RunConfig::default().www_dir);
        let err = RunConfig::from_toml("num-rounds = 3\n", "typo.toml").unwrap_err().to_string();
        assert!(err.contains("typo.toml") && err.contains("num-rounds"), "{err}");
    }

    #[test]
    fn overrides_apply() {
        let cfg = RunConfig::default()
            .with_overrides("num-server-rounds=5 fraction-fit=0.5 seed=7 lr=1 partitioning=iid dataset=/d/x")
            .unwrap();
        assert_eq!(cfg.num_server_rounds, 5);
        assert_eq!(cfg.fraction_fit, 0.5);
        assert_eq!(cfg.seed, 7);
        assert_eq!(cfg.lr, 1.0);
        assert_eq!(cfg.partitioning, Partitioning::Iid);
        assert_eq!(cfg.dataset, "/d/x");
    }

    #[test]
    fn own_datasets_take_a_list_of_paths_and_need_the_smolvla_workload() {
        assert!(RunConfig::default().own_datasets.is_empty());
        let cfg = RunConfig::default().with_overrides("own-datasets=data/own-a,data/own-b").unwrap();
        assert_eq!(cfg.own_datasets, ["data/own-a", "data/own-b"]);
        let err = RunConfig::default().with_overrides("workload=linreg own-datasets=data/own-a").unwrap_err();
        assert!(err.to_string().contains("own-datasets needs the smolvla workload"), "{err}");
    }

    #[test]
    fn dataset_tasks_default_to_the_first_task_take_a_list_and_refuse_unknown_names() {
        use fedvla_sim::TaskKind;
        assert_eq!(RunConfig::default().dataset_tasks, [TaskKind::CubeInBowl]);
        let both = [TaskKind::Stack, TaskKind::PickColour];
        for list in ["stack,pick-colour", r#"["stack","pick-colour"]"#] {
            let cfg = RunConfig::default().with_overrides(&format!("dataset-tasks={list}")).unwrap();
            assert_eq!(cfg.dataset_tasks, both, "{list}");
            assert_eq!(RunConfig::from_toml(&cfg.to_toml(), "resolved").unwrap(), cfg);
        }
        let one = RunConfig::default().with_overrides("dataset-tasks=push-to-target").unwrap();
        assert_eq!(one.dataset_tasks, [TaskKind::PushToTarget]);

        let err = RunConfig::default().with_overrides("dataset-tasks=stack,juggle").unwrap_err().to_string();
        assert!(err.starts_with("bad value for `dataset-tasks`") && err.contains("\"juggle\""), "{err}");
        for task in TaskKind::ALL {
            assert!(err.contains(task.name()), "{err}");
        }
        let err = RunConfig::from_toml("dataset-tasks = [\"stak\"]\n", "run.toml").unwrap_err().to_string();
        assert!(err.contains("run.toml") && err.contains("\"stak\"") && err.contains("pick-colour"), "{err}");
        let err = RunConfig::default().with_overrides("dataset-tasks=[]").unwrap_err().to_string();
        assert!(err.contains("dataset-tasks must name at least one task"), "{err}");
    }

    #[test]
    fn overrides_fail_clearly() {
        let base = RunConfig::default();
        let err = base.with_overrides("num-rounds=5").unwrap_err().to_string();
        assert!(err.starts_with("unknown config key `num-rounds`; known keys:"), "{err}");
        assert!(err.contains("num-server-rounds"), "{err}");
        let err = base.with_overrides("seed=seven").unwrap_err().to_string();
        assert_eq!(err, "bad value for `seed`: `seven` is not of type integer");
        let err = base.with_overrides("strategy=fedmagic").unwrap_err().to_string();
        assert!(err.contains("fedmagic") && err.contains("fedavg"), "{err}");
        let err = base.with_overrides("fraction-fit=1.5").unwrap_err().to_string();
        assert_eq!(err, "invalid configuration: fraction-fit must be in (0, 1], got 1.5");
        assert!(matches!(base.with_overrides("seed"), Err(ConfigError::NotKeyValue(_))));
    }
}
