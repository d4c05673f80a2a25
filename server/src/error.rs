//! The HTTP error type.

use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};

#[derive(Debug, thiserror::Error)]
pub enum ServerError {
    #[error("model version {requested} is not served; the current version is {current}")]
    ModelVersion { requested: u64, current: u64 },
}

impl IntoResponse for ServerError {
    fn into_response(self) -> Response {
        let status = match self {
            Self::ModelVersion { .. } => StatusCode::NOT_FOUND,
        };
        (status, self.to_string()).into_response()
    }
}
