//! The crate's one error type: every failure names the file (or the item) it is about.

use std::path::{Path, PathBuf};

/// Everything that can go wrong while writing, reading, partitioning or sharding a dataset.
#[derive(Debug, thiserror::Error)]
pub enum DataError {
    #[error("{path}: file not found")]
    MissingFile { path: PathBuf },
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error("{path}: corrupt or truncated parquet: {reason}")]
    CorruptParquet { path: PathBuf, reason: String },
    #[error("{path}: invalid JSON: {reason}")]
    InvalidJson { path: PathBuf, reason: String },
    #[error("{path}: unknown codebase_version {found:?} (this reader knows v3.0 and v2.1)")]
    UnknownVersion { path: PathBuf, found: String },
    #[error("{path}: column {column:?}: {reason}")]
    BadColumn { path: PathBuf, column: String, reason: String },
    #[error("{path}: corrupt or unsupported mp4: {reason}")]
    BadMp4 { path: PathBuf, reason: String },
    #[error("{path}: video codec {codec:?} is not supported{hint}")]
    UnsupportedCodec { path: PathBuf, codec: String, hint: &'static str },
    #[error("{path}: video decoding failed: {reason}")]
    Decode { path: PathBuf, reason: String },
    #[error("video encoding failed: {0}")]
    Encode(String),
    #[error("{path}: no frame within {tolerance_s} s of timestamp {timestamp_s} s")]
    FrameTimestamp { path: PathBuf, timestamp_s: f64, tolerance_s: f64 },
    #[error("invalid input: {0}")]
    InvalidInput(String),
    #[error("frame index {index} out of range (dataset has {len} frames)")]
    IndexOutOfRange { index: usize, len: usize },
    #[error("{path}: shard checksum mismatch: manifest says {expected}, content hashes to {actual}")]
    ChecksumMismatch { path: PathBuf, expected: String, actual: String },
    #[error("{path}: invalid shard: {reason}")]
    BadShard { path: PathBuf, reason: String },
}

pub type Result<T> = std::result::Result<T, DataError>;

impl DataError {
    /// An I/O error on `path`, turned into [`DataError::MissingFile`] when the file does not exist.
    pub(crate) fn io(path: &Path, source: std::io::Error) -> Self {
        if source.kind() == std::io::ErrorKind::NotFound {
            DataError::MissingFile { path: path.to_path_buf() }
        } else {
            DataError::Io { path: path.to_path_buf(), source }
        }
    }

    #[cfg(feature = "read")]
    pub(crate) fn parquet(path: &Path, reason: impl std::fmt::Display) -> Self {
        DataError::CorruptParquet { path: path.to_path_buf(), reason: reason.to_string() }
    }

    #[cfg(feature = "read")]
    pub(crate) fn column(path: &Path, column: &str, reason: impl Into<String>) -> Self {
        DataError::BadColumn { path: path.to_path_buf(), column: column.to_string(), reason: reason.into() }
    }

    #[cfg(feature = "read")]
    pub(crate) fn mp4(path: &Path, reason: impl Into<String>) -> Self {
        DataError::BadMp4 { path: path.to_path_buf(), reason: reason.into() }
    }
}
