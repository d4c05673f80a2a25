//! The policy crate's error type: every failure names the file, key or field that was wrong.

use std::path::PathBuf;

#[derive(Debug, thiserror::Error)]
pub enum PolicyError {
    #[error("invalid SmolVLA configuration: {0}")]
    Config(String),
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error("{path}: not valid JSON: {source}")]
    Json { path: PathBuf, source: serde_json::Error },
    #[error("{path}: not a readable safetensors file: {message}")]
    Safetensors { path: PathBuf, message: String },
    #[error("{path}: tensor {key:?} has unsupported dtype {dtype} (expected F32, BF16 or F16)")]
    Dtype { path: PathBuf, key: String, dtype: String },
    #[error("{source_name}: the weights do not match the SmolVLA configuration:\n{report}")]
    KeyMismatch { source_name: String, report: String },
    #[error("input {0}")]
    Input(String),
    #[error("tokenizer: {0}")]
    Tokenizer(String),
}

impl PolicyError {
    pub fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        Self::Io { path: path.into(), source }
    }
}
