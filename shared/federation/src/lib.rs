//! The federation spine shared by the server and the clients (native and wasm): the exchanged tensors, the
//! versioned protocol and binary update codec, aggregation strategies and the client round loop.
//!
//! No tokio, axum or wasm-bindgen: this crate compiles for `wasm32-unknown-unknown`.

pub mod accountant;
pub mod client;
pub mod codec;
pub mod data_report;
pub mod error;
pub mod evaluate;
pub mod identity;
pub mod protocol;
mod quantize;
mod reader;
pub mod seed;
pub mod strategy;
pub mod tensors;

pub use client::{
    Admission, ClientError, ClientEvent, ClientOptions, ClientSummary, ClientTransport, EvalOutput, Introduction,
    LocalTrainer, RolloutOutput, TrainOutput, Video, identify, run_client,
};
pub use codec::{Reassembler, UpdateLimits, UpdateValues};
pub use data_report::{
    DataReport, DatasetSignature, FeatureMoments, FeatureSummary, NormalizationStats, OwnDataset, StatsSource,
};
pub use error::{AggregateError, BoxError, CodecError, TensorError};
pub use evaluate::{EvalMetrics, Evaluator, LanguageHeldOut, TaskHeldOut};
pub use identity::Identity;
pub use protocol::{
    Capabilities, ClientMessage, ErrorCode, InstructionTokens, LrSchedule, ModelDeltas, OpeningFrames,
    PROTOCOL_VERSION, RolloutEpisode, RolloutRequest, RolloutTasks, RoundMetrics, RoundTask, ServerMessage,
    StrategyParams, UpdateEncoding, VolunteerSetup, WorkloadKind, routes,
};
pub use seed::{fnv1a, mix};
pub use strategy::{
    Adaptivity, Aggregation, Bulyan, ClipNorm, ClippedUpdates, Contribution, DpFedAvg, FedAdaptive, FedAvg, FedAvgM,
    FedMedian, FedProx, FedTrimmedAvg, Krum, PrivacyReport, QFedAvg, Scaffold, Step, Strategy, WeightedMean, aggregate,
    conclude,
};
pub use tensors::{NamedTensors, Tensor, TensorSpec};
