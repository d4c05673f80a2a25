//! JSON control messages (text WebSocket frames). Updates travel as binary frames, see [`crate::codec`].

use serde::{Deserialize, Serialize};

use crate::data_report::{DataReport, DatasetSignature, NormalizationStats};

/// Bumped on any incompatible change to the control messages or the binary update format.
/// 2: volunteer setup, sessions for uploads, rollout requests and results.
/// 3: the join names the shard the client trains on; the server weighs updates by that shard, not by the claim;
/// the setup's workload is a [`WorkloadKind`].
/// 4: the task names the update's encoding; the payload starts with it (compressed deltas, see [`UpdateEncoding`]).
/// 5: the join reports the client's data ([`DataReport`]: an own dataset's signature, moments for federated
/// statistics); the server sends the run's normalisation statistics ([`ServerMessage::NormStats`]).
/// 6: identities. The server opens every connection with a [`ServerMessage::Challenge`]; the client proves its key
/// ([`ClientMessage::Identify`]) and is admitted with its session and setup ([`ServerMessage::Admitted`], which
/// replaces `GET /api/volunteer`), downloads with the session, then joins with its data.
pub const PROTOCOL_VERSION: u16 = 6;

/// Longest volunteer name, in bytes, the server accepts.
pub const MAX_NAME_BYTES: usize = 64;

/// The server's HTTP paths, spelled once for the server's router and every client. Every route but the WebSocket
/// answers only requests with `Authorization: Bearer <session>`, the session of an admitted connection
/// ([`ServerMessage::Admitted`]); a shard's, only the session of a volunteer bound to that shard.
pub mod routes {

    /// The federation WebSocket.
    pub const WS: &str = "/ws";
    /// The router's pattern of [`model`].
    pub const MODEL: &str = "/model/{version}";
    /// The router's pattern of [`model_deltas`].
    pub const MODEL_DELTAS: &str = "/model/{version}/deltas/{from}";
    pub const SHARD: &str = "/shard/{index}";
    pub const SHARD_MANIFEST: &str = "/shard/{index}/manifest";
    pub const FROZEN: &str = "/policy/frozen/{tag}";
    pub const ROLLOUT_VIDEO: &str = "/rollout/{round}/{file}";
    pub const CORRECTION: &str = "/scaffold/{round}";
    /// The run's tokenizer (`tokenizer.json`), for volunteers that tokenize their own dataset's tasks.
    pub const TOKENIZER: &str = "/api/tokenizer";

    /// The global trainable tensors of `version` (safetensors).
    pub fn model(version: u64) -> String {
        format!("/model/{version}")
    }

    /// The global model of `version` as the chain of the rounds' deltas from version `from`, which the client
    /// holds ([`crate::codec::encode_model_deltas`]).
    pub fn model_deltas(version: u64, from: u64) -> String {
        format!("/model/{version}/deltas/{from}")
    }

    /// Shard `index` as stored.
    pub fn shard(index: u32) -> String {
        format!("/shard/{index}")
    }

    /// Shard `index`'s manifest: its size and SHA-256.
    pub fn shard_manifest(index: u32) -> String {
        format!("/shard/{index}/manifest")
    }

    /// The frozen tensors, named by their content tag.
    pub fn frozen(tag: &str) -> String {
        format!("/policy/frozen/{tag}")
    }

    /// Where a client uploads the rollout video `file` of `round` (authorised by its session).
    pub fn rollout_video(round: u64, file: &str) -> String {
        format!("/rollout/{round}/{file}")
    }

    /// SCAFFOLD's correction for the client whose session asks, in `round` (safetensors).
    pub fn correction(round: u64) -> String {
        format!("/scaffold/{round}")
    }
}

/// What a federation trains.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum WorkloadKind {
    /// SmolVLA's trainable tensors on SO-100 episodes.
    Smolvla,
    /// Least-squares linear regression on synthetic data: exercises the federation machinery in milliseconds.
    Linreg,
}

/// What a client runs on, so the server can plan tasks.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Capabilities {
    /// e.g. "ndarray", "wgpu", "webgpu".
    pub backend: String,
    pub memory_bytes: u64,
}

/// What a client reports after a round.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RoundMetrics {
    pub round: u64,
    pub examples: u64,
    pub train_loss: f64,
    /// Seconds spent on the round: model fetch, training and upload.
    pub seconds: f64,
    /// Bytes this client has sent since it joined (control and update frames).
    pub bytes_up: u64,
    /// Bytes this client has received since it joined (control messages and model downloads).
    pub bytes_down: u64,
    /// Bytes of this round's download of the global model: the whole model, the chain of deltas from the version
    /// the client held ([`RoundTask::model_deltas`]), or 0 when it held the task's version already.
    #[serde(default)]
    pub download_bytes: u64,
}

/// Client -> server.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum ClientMessage {
    /// First message on every connection, the answer to its [`ServerMessage::Challenge`]: who the volunteer is and
    /// the proof that it holds the key (see [`crate::identity`]).
    Identify {
        protocol_version: u16,
        auth_token: Option<String>,
        /// Display name chosen by the volunteer (at most [`MAX_NAME_BYTES`]), owned by the first key that uses it;
        /// sampling and aggregation order follow it.
        name: String,
        /// The volunteer's Ed25519 public key, hex: what the server binds its shard and state to.
        public_key: String,
        /// Hex Ed25519 signature of the challenge's nonce, the name and the protocol version.
        signature: String,
        /// A shard the volunteer asks for (`fedvla join --shard`): granted when no other key holds it. `None`:
        /// the key's shard, or a new key's next one round-robin.
        #[serde(default)]
        shard: Option<u32>,
        /// The volunteer trains on its own dataset: it is given no shard.
        #[serde(default)]
        own_dataset: bool,
    },
    /// After the admission's downloads: the client is ready for rounds.
    Join {
        capabilities: Capabilities,
        /// The client's data: its own dataset's signature and claimed size when it brings one (the server checks
        /// it fits the run), and the moments of its state and action (for federated statistics).
        #[serde(default)]
        data: Option<DataReport>,
    },
    /// Keep-alive for idle connections (e.g. behind proxies); the server only notes it.
    Heartbeat,
    /// Announces the binary update frames that follow.
    UpdateHeader {
        round: u64,
        examples: u64,
        train_loss: f64,
        payload_bytes: u64,
    },
    Metrics(RoundMetrics),
    /// Sim rollouts of the global model the task started from, when the task asked for them. Each episode's
    /// video was uploaded over HTTP before this message.
    RolloutResult {
        round: u64,
        model_version: u64,
        episodes: Vec<RolloutEpisode>,
    },
    /// Loss on the client's own held-out split, when the task asked for it.
    EvalResult {
        round: u64,
        examples: u64,
        loss: f64,
    },
}

/// One seeded sim episode rolled out by a client.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RolloutEpisode {
    pub episode: u32,
    pub seed: u64,
    pub success: bool,
    /// Frames executed (30 fps) until success or the budget.
    pub length: u32,
    /// File name the video was uploaded under (`POST /rollout/{round}/{file}`), if one was recorded.
    pub video: Option<String>,
    /// The sim task of the episode (its name, `fedvla tasks`), told its own instruction.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub task: Option<String>,
}

/// Sim rollouts a task asks for: `episodes` episodes from seeds `first_seed..`, each at most `max_frames`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RolloutRequest {
    pub episodes: u32,
    pub first_seed: u64,
    pub max_frames: u32,
}

/// Parameters the strategy hands to clients (e.g. FedProx's proximal term).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StrategyParams {
    pub name: String,
    /// Weight of the proximal term `mu/2 * ||w - w_global||^2`; 0 for FedAvg.
    pub proximal_mu: f64,
    /// SCAFFOLD: the client fetches its correction `c - c_i` for the round ([`routes::correction`], with its
    /// session) and adds it to the direction of every local step.
    #[serde(default)]
    pub control_variates: bool,
}

impl StrategyParams {
    /// A strategy whose clients train as FedAvg's do.
    pub fn plain(name: &str) -> Self {
        Self { name: name.into(), proximal_mu: 0.0, control_variates: false }
    }
}

/// How clients encode their updates, chosen by the server for the run and announced in every task. Every encoding
/// but `F32` sends the delta from the round's global model rather than the trained tensors.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "lowercase")]
pub enum UpdateEncoding {
    /// The trained tensors in f32: exact, 4 bytes a value.
    #[default]
    F32,
    /// The delta rounded to the nearest (ties to even) IEEE half: 2 bytes a value.
    F16,
    /// The delta rounded to the nearest (ties to even) bfloat16: 2 bytes a value, f32's range.
    Bf16,
    /// The delta in blocks of [`INT8_BLOCK`] values, each an f32 scale (its block's absmax / 127) and one signed
    /// byte a value: every value within its block's absmax / 254.
    Int8,
    /// The `fraction` of each tensor's delta values largest in magnitude, as (index, f32 value) pairs; the client
    /// adds what it left out to its next update (error feedback).
    Topk { fraction: f64 },
}

/// Values per scale of [`UpdateEncoding::Int8`].
pub const INT8_BLOCK: usize = 256;

impl UpdateEncoding {
    /// The config and report name ("f32", "f16", "bf16", "int8", "topk").
    pub fn name(self) -> &'static str {
        match self {
            Self::F32 => "f32",
            Self::F16 => "f16",
            Self::Bf16 => "bf16",
            Self::Int8 => "int8",
            Self::Topk { .. } => "topk",
        }
    }

    /// The encoding called `name`, with `topk_fraction` for top-k (in (0, 1]).
    pub fn parse(name: &str, topk_fraction: f64) -> Result<Self, String> {
        match name {
            "f32" => Ok(Self::F32),
            "f16" => Ok(Self::F16),
            "bf16" => Ok(Self::Bf16),
            "int8" => Ok(Self::Int8),
            "topk" if topk_fraction > 0.0 && topk_fraction <= 1.0 => Ok(Self::Topk { fraction: topk_fraction }),
            "topk" => Err(format!("topk-fraction must be in (0, 1], got {topk_fraction}")),
            other => Err(format!("unknown update encoding `{other}` (expected f32, f16, bf16, int8 or topk)")),
        }
    }

    /// How many of a tensor's `numel` values top-k sends: `ceil(fraction * numel)`, at least 1.
    pub fn topk_count(fraction: f64, numel: usize) -> usize {
        ((fraction * numel as f64).ceil() as usize).clamp(numel.min(1), numel)
    }
}

/// One round of local work for one client.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RoundTask {
    pub round: u64,
    /// Version of the global trainable tensors to start from (`GET /model/{version}`).
    pub model_version: u64,
    pub local_steps: u32,
    pub batch_size: u32,
    /// The learning rate, or its peak when `lr_schedule` is given.
    pub lr: f64,
    /// The learning rate over the whole run's local steps, when it is not constant.
    #[serde(default)]
    pub lr_schedule: Option<LrSchedule>,
    /// Seed for this client's local shuffling in this round.
    pub seed: u64,
    pub strategy: StrategyParams,
    /// Whether the client's optimizer keeps its moments from the rounds it trained before (on the global model
    /// it is given) rather than starting afresh each round, as FedAvg's clients classically do. A task that does
    /// not keep them also drops its own when its training ends (at full size 0.8 GB not held until the next
    /// round), so moments carry over only between tasks that both keep them.
    #[serde(default)]
    pub keep_optimizer_state: bool,
    /// Draws the opening frames of episodes whose instruction decides the goal more often; `None`: every
    /// training frame as often.
    #[serde(default)]
    pub opening_frames: Option<OpeningFrames>,
    /// Milliseconds from the task until the server closes the round.
    pub deadline_ms: u64,
    /// Whether the client should also report [`ClientMessage::EvalResult`].
    pub eval_request: bool,
    /// Sim rollouts of the task's starting model to report with [`ClientMessage::RolloutResult`].
    pub rollout: Option<RolloutRequest>,
    /// How to encode the update.
    #[serde(default)]
    pub update_encoding: UpdateEncoding,
    /// Whether a client holding an earlier global model may download this one as deltas; `None`: only whole.
    #[serde(default)]
    pub model_deltas: Option<ModelDeltas>,
}

/// The global model of a task offered as the chain of the rounds' deltas (`GET /model/{version}/deltas/{from}`)
/// to a client that holds an earlier version: the run's update encoding of each round's change, which the server
/// made its global model exactly as the client rebuilds it (see [`crate::codec::encode_model_delta`]). Offered only
/// where the chain is shorter than the whole model.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct ModelDeltas {
    /// The oldest version the chain starts from: a client holding a version in `since..model_version` may ask.
    pub since: u64,
    /// CRC32 of the task's model ([`crate::NamedTensors::checksum`]): what the client checks the model it rebuilt
    /// against.
    pub checksum: u32,
}

impl RoundTask {
    /// The learning rate of local step `step` (from 0): constant, or on its schedule over the client's steps of
    /// the whole run (LeRobot's `CosineDecayWithWarmupSchedulerConfig`: linear warmup from `lr / (warmup + 1)`,
    /// then cosine decay to `final_lr`).
    pub fn lr_at(&self, step: u32) -> f64 {
        let Some(s) = self.lr_schedule else { return self.lr };
        let (step, warmup, total) = (s.first_step + u64::from(step), s.warmup_steps, s.total_steps.max(1));
        let w = warmup as f64;
        let factor = if step < warmup {
            if step == 0 { 1.0 / (w + 1.0) } else { (1.0 / (w + 1.0) - 1.0) * (1.0 - step as f64 / w) + 1.0 }
        } else {
            let cosine = 0.5 * (1.0 + (std::f64::consts::PI * step.min(total) as f64 / total as f64).cos());
            let alpha = s.final_lr / self.lr;
            (1.0 - alpha) * cosine + alpha
        };
        self.lr * factor
    }

    /// The sum of the round's learning rates: how far the round moves the model along a unit direction.
    pub fn lr_sum(&self) -> f64 {
        (0..self.local_steps).map(|k| self.lr_at(k)).sum()
    }
}

/// LeRobot's cosine decay with linear warmup, over a client's steps of the whole run: this round's local steps
/// are steps `first_step..first_step + local_steps` of `total_steps`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct LrSchedule {
    pub warmup_steps: u64,
    pub total_steps: u64,
    /// The learning rate the decay ends at.
    pub final_lr: f64,
    pub first_step: u64,
}

/// The first `frames` frames of each training episode whose instruction decides its goal (the sim's
/// `pick-colour`), drawn `repeat` times as often as the other frames. Only there does the instruction, not the
/// arm's motion towards its cube, tell the goal: a demonstration heads for its cube from its first frames.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct OpeningFrames {
    pub frames: u32,
    pub repeat: u32,
}

/// What a volunteer is offered on admission ([`ServerMessage::Admitted`]): its shard, the policy and the frozen
/// weights. Everything is versioned so browsers can cache it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct VolunteerSetup {
    pub protocol_version: u16,
    pub workload: WorkloadKind,
    /// The shard bound to this volunteer's key, of `shard_count` (0, and unused, for a volunteer that brings its
    /// own dataset).
    pub shard_index: u32,
    pub shard_count: u32,
    /// `GET` paths of the shard and its manifest (size and SHA-256).
    pub shard_url: String,
    pub shard_manifest_url: String,
    /// The workload's configuration: SmolVLA's policy (`{"policy": <LeRobot config.json>, "vlm":
    /// <vlm/config.json>}`), linreg's `{"partitioning": ...}`.
    pub policy: serde_json::Value,
    /// `GET` path of the frozen tensors (safetensors), named by their content hash so caches never go stale.
    pub frozen_url: Option<String>,
    pub frozen_bytes: u64,
    /// The sim tasks rollouts cycle through and their instructions' token ids (the shard carries the training
    /// tasks' ids).
    #[serde(default)]
    pub rollout_tasks: RolloutTasks,
    /// The global model version at the time of the request.
    pub model_version: u64,
    /// `GET` path of the run's tokenizer, for volunteers that bring their own dataset.
    #[serde(default)]
    pub tokenizer_url: Option<String>,
    /// What an own dataset must match (the server checks it again on join); `None`: the run takes none.
    #[serde(default)]
    pub dataset_signature: Option<DatasetSignature>,
}

/// What a run's sim rollouts ask of a policy: the tasks its episodes cycle through (episode k of a rollout on
/// task `k mod n`, on its seed's layout), and every instruction those tasks give, tokenised by the run's
/// tokenizer (a client need not have it). A run of one task lists that one.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct RolloutTasks {
    /// Task names, as `fedvla tasks` prints them.
    pub tasks: Vec<String>,
    pub instructions: Vec<InstructionTokens>,
}

/// One instruction as the policy reads it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct InstructionTokens {
    pub instruction: String,
    pub ids: Vec<u32>,
    pub mask: Vec<bool>,
}

/// Why the server refused something.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ErrorCode {
    ProtocolVersion,
    Unauthorized,
    MalformedMessage,
    MalformedFrame,
    ChecksumMismatch,
    Oversized,
    MissingTensor,
    UnexpectedTensor,
    ShapeMismatch,
    NonFinite,
    UnexpectedMessage,
    /// A join from an address that has already joined `joins-per-address-per-minute` times this minute.
    JoinRateLimited,
    /// More messages a second on one connection than `max-messages-per-second`.
    MessageRateLimited,
    /// An upload that does not fit, while others are in flight, in the memory the server holds for them
    /// (`max-upload-memory-bytes`): an update is refused for its round, a video may be sent again.
    UploadBudget,
    /// A rollout video larger than `max-video-bytes` (HTTP 413).
    VideoTooLarge,
    /// A rollout video beyond those the round asked the client for (HTTP 403).
    TooManyVideos,
    /// A rollout video for a round that asked the client for none (HTTP 403).
    UnrequestedVideo,
    /// An update for another round than the one running (late, or sent when none runs).
    StaleRound,
    /// A second update from a client in the same round.
    DuplicateUpdate,
    /// An update for the running round from a client the round did not sample.
    UnrequestedUpdate,
    ShuttingDown,
    /// A volunteer name that is empty or longer than [`MAX_NAME_BYTES`].
    InvalidName,
    /// A join naming a shard the run does not have.
    UnknownShard,
    /// A name another key holds: names belong to the first key that uses them.
    NameTaken,
    /// A shard asked for that another key holds.
    ShardTaken,
    /// An update dropped after aggregation: the aggregate or its evaluation failed and this update was the one
    /// farthest from the global model.
    DroppedUpdate,
    /// An update left out of the aggregate because its change from the global model is far beyond the norms seen
    /// (`update-norm-factor`).
    UpdateNormOutlier,
    /// A join with an own dataset that does not fit the run (state or action dimensions or names, cameras, fps,
    /// robot type), or one the run's workload cannot take.
    IncompatibleDataset,
}

impl ErrorCode {
    /// Errors after which the server closes the connection.
    pub fn is_fatal(self) -> bool {
        matches!(
            self,
            Self::ProtocolVersion
                | Self::Unauthorized
                | Self::ShuttingDown
                | Self::InvalidName
                | Self::UnknownShard
                | Self::NameTaken
                | Self::ShardTaken
                | Self::IncompatibleDataset
                | Self::JoinRateLimited
                | Self::MessageRateLimited
        )
    }

    pub fn as_str(self) -> &'static str {
        match self {
            Self::ProtocolVersion => "protocol_version",
            Self::Unauthorized => "unauthorized",
            Self::MalformedMessage => "malformed_message",
            Self::MalformedFrame => "malformed_frame",
            Self::ChecksumMismatch => "checksum_mismatch",
            Self::Oversized => "oversized",
            Self::MissingTensor => "missing_tensor",
            Self::UnexpectedTensor => "unexpected_tensor",
            Self::ShapeMismatch => "shape_mismatch",
            Self::NonFinite => "non_finite",
            Self::UnexpectedMessage => "unexpected_message",
            Self::JoinRateLimited => "join_rate_limited",
            Self::MessageRateLimited => "message_rate_limited",
            Self::UploadBudget => "upload_budget",
            Self::VideoTooLarge => "video_too_large",
            Self::TooManyVideos => "too_many_videos",
            Self::UnrequestedVideo => "unrequested_video",
            Self::StaleRound => "stale_round",
            Self::DuplicateUpdate => "duplicate_update",
            Self::UnrequestedUpdate => "unrequested_update",
            Self::ShuttingDown => "shutting_down",
            Self::InvalidName => "invalid_name",
            Self::UnknownShard => "unknown_shard",
            Self::NameTaken => "name_taken",
            Self::ShardTaken => "shard_taken",
            Self::DroppedUpdate => "dropped_update",
            Self::UpdateNormOutlier => "update_norm_outlier",
            Self::IncompatibleDataset => "incompatible_dataset",
        }
    }
}

/// Server -> client.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum ServerMessage {
    /// First message on every connection: a fresh random nonce (hex) the client signs to prove its key.
    Challenge {
        nonce: String,
    },
    /// The answer to a proven [`ClientMessage::Identify`]: the client's id, its session (the bearer token of every
    /// download and upload of this connection) and what it is offered.
    Admitted {
        client_id: u64,
        session: String,
        /// Boxed: the setup is large, and the other messages are many.
        setup: Box<VolunteerSetup>,
    },
    /// The answer to [`ClientMessage::Join`]: rounds may come.
    Welcome {
        client_id: u64,
        protocol_version: u16,
        /// Largest binary frame the server accepts; updates are chunked to fit.
        max_frame_bytes: u32,
    },
    RoundTask(RoundTask),
    /// The statistics the client normalises state and action with, sent before its first task (once agreed,
    /// when the run agrees them by federated statistics).
    NormStats(NormalizationStats),
    Error {
        code: ErrorCode,
        message: String,
    },
    /// The round ended; `accepted` is false when it had too few updates and will be retried.
    RoundClosed {
        round: u64,
        accepted: bool,
        model_version: u64,
        updates: u32,
    },
    /// The run is over; the client may disconnect.
    Finished {
        rounds: u64,
    },
}

#[cfg(test)]
mod tests {
    use super::*;

    /// LeRobot's schedule by hand: warmup 4 steps of 10 at peak 1, decay to 0.1. Step 0: 1/5; step 2:
    /// (1/5 - 1)(1 - 2/4) + 1 = 0.6; step 4 (warmup over, cosine of 4/10 pi): 0.9 * 0.5 (1 + cos 0.4 pi) + 0.1;
    /// from step 10 on: 0.1. A round of 3 steps from step 1 sums steps 1, 2 and 3.
    #[test]
    fn the_cosine_schedule_with_warmup_and_its_round_sums_by_hand() {
        let schedule = LrSchedule { warmup_steps: 4, total_steps: 10, final_lr: 0.1, first_step: 0 };
        let task = |first_step, local_steps| RoundTask {
            round: 1,
            model_version: 0,
            local_steps,
            batch_size: 1,
            lr: 1.0,
            lr_schedule: Some(LrSchedule { first_step, ..schedule }),
            seed: 0,
            strategy: StrategyParams::plain("fedavg"),
            keep_optimizer_state: false,
            opening_frames: None,
            deadline_ms: 1,
            eval_request: false,
            rollout: None,
            update_encoding: UpdateEncoding::F32,
            model_deltas: None,
        };
        let at = |step| task(0, 20).lr_at(step);
        let close = |a: f64, b: f64| assert!((a - b).abs() < 1e-12, "{a} != {b}");
        close(at(0), 0.2);
        close(at(2), 0.6);
        close(at(4), 0.45 * (1.0 + (0.4 * std::f64::consts::PI).cos()) + 0.1);
        close(at(10), 0.1);
        close(at(15), 0.1);
        close(task(1, 3).lr_sum(), at(1) + at(2) + at(3));
        let constant = RoundTask { lr_schedule: None, lr: 0.5, ..task(0, 4) };
        close(constant.lr_at(3), 0.5);
        close(constant.lr_sum(), 2.0);
    }

    #[test]
    fn messages_are_tagged_snake_case() {
        let identify = ClientMessage::Identify {
            protocol_version: PROTOCOL_VERSION,
            auth_token: None,
            name: "c0".into(),
            public_key: "ab".into(),
            signature: "cd".into(),
            shard: Some(2),
            own_dataset: false,
        };
        let json = serde_json::to_string(&identify).unwrap();
        assert!(json.starts_with(&format!(r#"{{"type":"identify","protocol_version":{PROTOCOL_VERSION}"#)), "{json}");
        assert_eq!(serde_json::from_str::<ClientMessage>(&json).unwrap(), identify);
        let join = ClientMessage::Join {
            capabilities: Capabilities { backend: "ndarray".into(), memory_bytes: 1 << 30 },
            data: None,
        };
        let json = serde_json::to_string(&join).unwrap();
        assert_eq!(serde_json::from_str::<ClientMessage>(&json).unwrap(), join);

        let err = ServerMessage::Error { code: ErrorCode::NonFinite, message: "x".into() };
        let json = serde_json::to_string(&err).unwrap();
        assert_eq!(json, r#"{"type":"error","code":"non_finite","message":"x"}"#);
        assert_eq!(serde_json::from_str::<ServerMessage>(&json).unwrap(), err);
    }

    #[test]
    fn code_strings_match_serde() {
        for code in [
            ErrorCode::ProtocolVersion,
            ErrorCode::StaleRound,
            ErrorCode::DuplicateUpdate,
            ErrorCode::UnrequestedUpdate,
            ErrorCode::MalformedFrame,
            ErrorCode::DroppedUpdate,
            ErrorCode::UpdateNormOutlier,
            ErrorCode::IncompatibleDataset,
            ErrorCode::NameTaken,
            ErrorCode::ShardTaken,
        ] {
            assert_eq!(serde_json::to_string(&code).unwrap(), format!("\"{}\"", code.as_str()));
        }
    }
}
