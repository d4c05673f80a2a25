//! The HTTP error type.

use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};

#[derive(Debug, thiserror::Error)]
pub enum ServerError {
    #[error("model version {requested} is not served; the current version is {current}")]
    ModelVersion { requested: u64, current: u64 },
    #[error("no shard {index}: this run has {count}")]
    NoShard { index: usize, count: usize },
    #[error("shard unavailable: {0}")]
    ShardIo(String),
}

impl IntoResponse for ServerError {
    fn into_response(self) -> Response {
        let status = match self {
            Self::ModelVersion { .. } | Self::NoShard { .. } => StatusCode::NOT_FOUND,
            Self::ShardIo(_) => StatusCode::INTERNAL_SERVER_ERROR,
        };
        (status, self.to_string()).into_response()
    }
}
