//! Typed errors. Every error a client can cause maps to an [`ErrorCode`] sent back to it.

use crate::protocol::ErrorCode;

/// Errors for use across trait objects (trainers, transports, evaluators).
pub type BoxError = Box<dyn std::error::Error + Send + Sync>;

/// A tensor set that does not match what was expected.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum TensorError {
    #[error("tensor of shape {shape:?} needs {expected} values, got {got}")]
    LengthMismatch { shape: Vec<usize>, expected: usize, got: usize },
    #[error("missing tensor `{0}`")]
    Missing(String),
    #[error("unexpected tensor `{0}` (not in the trainable set)")]
    Unexpected(String),
    #[error("tensor `{name}` has shape {got:?}, expected {expected:?}")]
    ShapeMismatch { name: String, expected: Vec<usize>, got: Vec<usize> },
    #[error("tensor `{name}` holds a NaN or infinite value at index {index}")]
    NonFinite { name: String, index: usize },
    #[error("tensor `{name}` has dtype {dtype}, only F32 is exchanged")]
    Dtype { name: String, dtype: String },
    #[error("safetensors: {0}")]
    Safetensors(String),
}

impl From<safetensors::SafeTensorError> for TensorError {
    fn from(e: safetensors::SafeTensorError) -> Self {
        Self::Safetensors(e.to_string())
    }
}

impl TensorError {
    pub fn code(&self) -> ErrorCode {
        match self {
            Self::Missing(_) => ErrorCode::MissingTensor,
            Self::Unexpected(_) => ErrorCode::UnexpectedTensor,
            Self::ShapeMismatch { .. } | Self::LengthMismatch { .. } | Self::Dtype { .. } => ErrorCode::ShapeMismatch,
            Self::NonFinite { .. } => ErrorCode::NonFinite,
            Self::Safetensors(_) => ErrorCode::MalformedFrame,
        }
    }
}

/// A binary update frame or payload that cannot be accepted.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CodecError {
    #[error("frame does not start with the update magic")]
    BadMagic,
    #[error("frame speaks protocol version {got}, this side speaks {expected}")]
    ProtocolVersion { expected: u16, got: u16 },
    #[error("truncated: needed {needed} bytes, got {got}")]
    Truncated { needed: usize, got: usize },
    #[error("frame of {len} bytes exceeds the {limit}-byte frame limit")]
    FrameTooLarge { len: usize, limit: usize },
    #[error("update of {len} bytes exceeds the {limit}-byte update limit")]
    Oversized { len: u64, limit: u64 },
    #[error("malformed frame: {0}")]
    Malformed(String),
    #[error("payload checksum {got:#010x} does not match {expected:#010x}")]
    ChecksumMismatch { expected: u32, got: u32 },
    #[error("model deltas from version {} to {}, expected from {} to {}", got.0, got.1, expected.0, expected.1)]
    DeltaVersions { expected: (u64, u64), got: (u64, u64) },
    #[error(transparent)]
    Tensor(#[from] TensorError),
}

impl CodecError {
    pub fn code(&self) -> ErrorCode {
        match self {
            Self::ProtocolVersion { .. } => ErrorCode::ProtocolVersion,
            Self::FrameTooLarge { .. } | Self::Oversized { .. } => ErrorCode::Oversized,
            Self::ChecksumMismatch { .. } => ErrorCode::ChecksumMismatch,
            Self::BadMagic | Self::Truncated { .. } | Self::Malformed(_) | Self::DeltaVersions { .. } => {
                ErrorCode::MalformedFrame
            }
            Self::Tensor(e) => e.code(),
        }
    }
}

/// Aggregation that cannot produce a new global model.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum AggregateError {
    #[error("no updates to aggregate")]
    NoUpdates,
    #[error("{rule} needs at least {need} updates a round, got {got}")]
    TooFew { rule: &'static str, need: usize, got: usize },
    #[error("updates carry zero examples in total")]
    ZeroExamples,
    #[error("update {index} does not match the global model: {source}")]
    Mismatch { index: usize, source: TensorError },
    #[error("update {index} reports no usable training loss ({loss:?}): {rule} weighs every client by it")]
    Loss { index: usize, rule: &'static str, loss: Option<f64> },
    #[error("update {index}: {rule} needs {what}, which the server does not know of it")]
    Unknown { index: usize, rule: &'static str, what: &'static str },
    #[error(
        "update {index} holds {value:e}, beyond the {limit:e} in magnitude the exact accumulator sums (a model's \
         values are far smaller)"
    )]
    OutOfRange { index: usize, value: f64, limit: f64 },
    #[error("the round's weighted values sum beyond what the exact accumulator holds")]
    Overflow,
    #[error("the aggregate is not a usable model: {0}")]
    Aggregate(TensorError),
}
