//! HTTP routes: `GET /ws` (the federation WebSocket) and `GET /model/{version}` (global trainable tensors), plus
//! the volunteers' downloads and uploads ([`crate::volunteer`]), the operator console's API ([`crate::console`])
//! and, for every other path, the pages under `www-dir` ([`crate::static_files`]).

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use axum::Router;
use axum::body::Bytes;
use axum::extract::ws::WebSocketUpgrade;
use axum::extract::{Path, State};
use axum::http::header::CONTENT_TYPE;
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use fedvla_federation::{TensorSpec, UpdateLimits};
use futures_util::StreamExt;
use tokio::sync::{mpsc, watch};
use tokio_util::sync::CancellationToken;

use crate::connection::handle_socket;
use crate::console::{self, ConsoleHub};
use crate::coordinator::Event;
use crate::error::ServerError;
use crate::run_dir::RunDir;
use crate::static_files;
use crate::volunteer::{self, Sessions, Volunteers};

/// The global model as served: its version and safetensors bytes.
#[derive(Debug, Clone)]
pub struct PublishedModel {
    pub version: u64,
    pub safetensors: Bytes,
}

/// Shared by every request: channels to the coordinator, no locks.
#[derive(Clone)]
pub struct AppState {
    pub events: mpsc::Sender<Event>,
    pub model: watch::Receiver<Arc<PublishedModel>>,
    pub cancel: CancellationToken,
    pub spec: Arc<TensorSpec>,
    pub limits: UpdateLimits,
    /// How often an idle WebSocket is pinged (well within the listener's idle timeout).
    pub keepalive: Duration,
    /// Token clients must present on join; `None` means no authentication.
    pub auth_token: Option<Arc<str>>,
    /// What volunteers download (setup, shards, frozen weights), and who trains on which shard.
    pub volunteers: Arc<Volunteers>,
    /// Session tokens of connected clients, for their uploads.
    pub sessions: Sessions,
    /// Where uploads are filed.
    pub run_dir: RunDir,
    /// The operator console's live state and controls.
    pub console: ConsoleHub,
    /// The pages served to browsers (`www-dir`).
    pub www_dir: Arc<PathBuf>,
}

pub fn app(state: AppState) -> Router {
    Router::new()
        .route("/ws", get(ws_upgrade))
        .route("/model/{version}", get(get_model))
        .merge(volunteer::routes())
        .merge(console::routes(&state.console))
        .fallback(static_files::serve)
        .with_state(state)
}

async fn ws_upgrade(ws: WebSocketUpgrade, State(state): State<AppState>) -> Response {
    // Twice our frame limit at the WebSocket layer, so a moderately oversized frame still reaches the codec and
    // gets a clear error, while an absurd one is cut off before it is buffered.
    let limit = state.limits.max_frame_bytes * 2 + 64 * 1024;
    ws.max_frame_size(limit).max_message_size(limit).on_upgrade(move |socket| {
        let (sink, stream) = socket.split();
        handle_socket(sink, stream, state)
    })
}

async fn get_model(Path(version): Path<u64>, State(state): State<AppState>) -> Result<Response, ServerError> {
    let model = state.model.borrow().clone();
    if model.version != version {
        return Err(ServerError::ModelVersion { requested: version, current: model.version });
    }
    Ok(([(CONTENT_TYPE, "application/octet-stream")], model.safetensors.clone()).into_response())
}
