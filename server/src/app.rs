//! HTTP routes: `GET /ws` (the federation WebSocket), `GET /model/{version}` (global trainable tensors)
//! and `GET /shard/{index}` with `GET /shard/{index}/manifest` (a client's data shard, its size and checksum).

use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::AtomicU64;

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
use crate::coordinator::Event;
use crate::error::ServerError;

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
    /// Token clients must present on join; `None` means no authentication.
    pub auth_token: Option<Arc<str>>,
    pub next_client_id: Arc<AtomicU64>,
    /// Client shard files by shard index (each with its `.manifest.json` sidecar).
    pub shards: Arc<Vec<PathBuf>>,
}

pub fn app(state: AppState) -> Router {
    Router::new()
        .route("/ws", get(ws_upgrade))
        .route("/model/{version}", get(get_model))
        .route("/shard/{index}", get(get_shard))
        .route("/shard/{index}/manifest", get(get_shard_manifest))
        .with_state(state)
}

async fn ws_upgrade(ws: WebSocketUpgrade, State(state): State<AppState>) -> Response {
    // Twice our frame limit at the WebSocket layer, so a moderately oversized frame still reaches the codec and
    // gets a clear error, while an absurd one is cut off before it is buffered.
    let limit = state.limits.max_frame_bytes * 2 + 64 * 1024;
    ws.max_frame_size(limit)
        .max_message_size(limit)
        .on_upgrade(move |socket| {
            let (sink, stream) = socket.split();
            handle_socket(sink, stream, state)
        })
}

async fn get_model(
    Path(version): Path<u64>,
    State(state): State<AppState>,
) -> Result<Response, ServerError> {
    let model = state.model.borrow().clone();
    if model.version != version {
        return Err(ServerError::ModelVersion {
            requested: version,
            current: model.version,
        });
    }
    Ok((
        [(CONTENT_TYPE, "application/octet-stream")],
        model.safetensors.clone(),
    )
        .into_response())
}

fn shard_path(state: &AppState, index: usize) -> Result<&PathBuf, ServerError> {
    state.shards.get(index).ok_or(ServerError::NoShard { index, count: state.shards.len() })
}

/// The shard file as stored; clients check it against the manifest's size and SHA-256.
async fn get_shard(Path(index): Path<usize>, State(state): State<AppState>) -> Result<Response, ServerError> {
    let path = shard_path(&state, index)?;
    let bytes = tokio::fs::read(path).await.map_err(|e| ServerError::ShardIo(format!("{}: {e}", path.display())))?;
    Ok(([(CONTENT_TYPE, "application/octet-stream")], bytes).into_response())
}

async fn get_shard_manifest(Path(index): Path<usize>, State(state): State<AppState>) -> Result<Response, ServerError> {
    let path = fedvla_data::shard::sidecar_path(shard_path(&state, index)?);
    let json = tokio::fs::read(&path).await.map_err(|e| ServerError::ShardIo(format!("{}: {e}", path.display())))?;
    Ok(([(CONTENT_TYPE, "application/json")], json).into_response())
}
