//! What volunteers download and upload over HTTP, beside the WebSocket: the setup (`GET /api/volunteer`: which
//! shard to train on, the policy configuration, where the frozen weights are), the shard and its manifest, the
//! frozen weights (named by content hash so browsers cache them forever), and rollout videos
//! (`POST /rollout/{round}/{file}`, authorised by the connection's session token).

use std::collections::HashMap;
use std::path::PathBuf;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};

use axum::Json;
use axum::Router;
use axum::body::Bytes;
use axum::extract::{DefaultBodyLimit, Path, Query, State};
use axum::http::header::{AUTHORIZATION, CACHE_CONTROL, CONTENT_TYPE};
use axum::http::{HeaderMap, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use fedvla_federation::{PROTOCOL_VERSION, VolunteerSetup};
use serde::Deserialize;
use sha2::{Digest, Sha256};

use crate::app::AppState;
use crate::error::ServerError;

/// Largest rollout video accepted.
const MAX_VIDEO_BYTES: usize = 64 << 20;

/// What a workload offers volunteers.
#[derive(Debug, Clone, Default)]
pub struct VolunteerOffer {
    /// "smolvla" or "linreg".
    pub workload: String,
    /// Client shard files by shard index (each with its `.manifest.json` sidecar).
    pub shards: Vec<PathBuf>,
    /// `{"policy": <LeRobot config.json>, "vlm": <vlm/config.json>}`, null when there is no policy.
    pub policy: serde_json::Value,
    /// The frozen tensors as safetensors, when the workload has any.
    pub frozen: Option<Bytes>,
    /// The sim task's token ids and mask.
    pub rollout_task_tokens: Vec<u32>,
    pub rollout_task_mask: Vec<bool>,
}

impl VolunteerOffer {
    /// An offer of nothing but the round loop (tests and the linreg workload without shards).
    pub fn bare(workload: &str) -> Self {
        Self { workload: workload.into(), ..Self::default() }
    }
}

/// The offer as served: the frozen weights' content tag and the shard assignment (round-robin, sticky by name).
pub struct Volunteers {
    offer: VolunteerOffer,
    /// Hex SHA-256 prefix of the frozen safetensors; part of their URL.
    frozen_tag: Option<String>,
    next_shard: AtomicUsize,
    /// The shard each named volunteer was given, so a reload or a reconnect keeps its data (and its cache).
    assigned: Mutex<HashMap<String, usize>>,
}

impl Volunteers {
    pub fn new(offer: VolunteerOffer) -> Self {
        let frozen_tag = offer.frozen.as_ref().map(|bytes| {
            let digest = Sha256::digest(bytes);
            digest[..8].iter().map(|b| format!("{b:02x}")).collect()
        });
        Self { offer, frozen_tag, next_shard: AtomicUsize::new(0), assigned: Mutex::default() }
    }

    /// The shard of volunteer `name` (the next one round-robin for a new or unnamed volunteer).
    fn assign(&self, name: Option<&str>) -> usize {
        let count = self.offer.shards.len().max(1);
        let next = || self.next_shard.fetch_add(1, Ordering::Relaxed) % count;
        match name {
            Some(name) => *self.assigned.lock().expect("assignments lock").entry(name.to_owned()).or_insert_with(next),
            None => next(),
        }
    }

    fn shard_path(&self, index: usize) -> Result<&PathBuf, ServerError> {
        self.offer.shards.get(index).ok_or(ServerError::NoShard { index, count: self.offer.shards.len() })
    }
}

/// Session tokens of the connected clients, for their HTTP uploads.
#[derive(Clone, Default)]
pub struct Sessions {
    by_token: Arc<Mutex<HashMap<String, u64>>>,
}

impl Sessions {
    /// A fresh unguessable token for `client_id`.
    pub fn open(&self, client_id: u64) -> String {
        let token = crate::console::random_token();
        self.by_token.lock().expect("sessions lock").insert(token.clone(), client_id);
        token
    }

    pub fn close(&self, client_id: u64) {
        self.by_token.lock().expect("sessions lock").retain(|_, id| *id != client_id);
    }

    fn client(&self, token: &str) -> Option<u64> {
        self.by_token.lock().expect("sessions lock").get(token).copied()
    }
}

pub fn routes() -> Router<AppState> {
    Router::new()
        .route("/api/volunteer", get(get_setup))
        .route("/policy/frozen/{tag}", get(get_frozen))
        .route("/shard/{index}", get(get_shard))
        .route("/shard/{index}/manifest", get(get_shard_manifest))
        .route("/rollout/{round}/{file}", post(post_video).layer(DefaultBodyLimit::max(MAX_VIDEO_BYTES)))
}

/// Who asks for a setup.
#[derive(Deserialize)]
struct SetupQuery {
    name: Option<String>,
}

/// The setup of a volunteer (`?name=` keeps a returning one on its shard).
async fn get_setup(State(state): State<AppState>, Query(query): Query<SetupQuery>) -> Json<VolunteerSetup> {
    let v = &state.volunteers;
    let count = v.offer.shards.len();
    let index = v.assign(query.name.as_deref());
    Json(VolunteerSetup {
        protocol_version: PROTOCOL_VERSION,
        workload: v.offer.workload.clone(),
        shard_index: index as u32,
        shard_count: count as u32,
        shard_url: format!("/shard/{index}"),
        shard_manifest_url: format!("/shard/{index}/manifest"),
        policy: v.offer.policy.clone(),
        frozen_url: v.frozen_tag.as_ref().map(|tag| format!("/policy/frozen/{tag}")),
        frozen_bytes: v.offer.frozen.as_ref().map_or(0, |b| b.len() as u64),
        rollout_task_tokens: v.offer.rollout_task_tokens.clone(),
        rollout_task_mask: v.offer.rollout_task_mask.clone(),
        model_version: state.model.borrow().version,
    })
}

async fn get_frozen(Path(tag): Path<String>, State(state): State<AppState>) -> Result<Response, ServerError> {
    let v = &state.volunteers;
    match (&v.offer.frozen, &v.frozen_tag) {
        (Some(bytes), Some(current)) if *current == tag => Ok((
            [(CONTENT_TYPE, "application/octet-stream"), (CACHE_CONTROL, "public, max-age=31536000, immutable")],
            bytes.clone(),
        )
            .into_response()),
        _ => Err(ServerError::NotFound(format!("frozen weights {tag}: this run serves {:?}", v.frozen_tag))),
    }
}

/// The shard file as stored; clients check it against the manifest's size and SHA-256.
async fn get_shard(Path(index): Path<usize>, State(state): State<AppState>) -> Result<Response, ServerError> {
    let path = state.volunteers.shard_path(index)?;
    let bytes = tokio::fs::read(path).await.map_err(|e| ServerError::ShardIo(format!("{}: {e}", path.display())))?;
    Ok(([(CONTENT_TYPE, "application/octet-stream")], bytes).into_response())
}

async fn get_shard_manifest(Path(index): Path<usize>, State(state): State<AppState>) -> Result<Response, ServerError> {
    let path = fedvla_data::shard::sidecar_path(state.volunteers.shard_path(index)?);
    let json = tokio::fs::read(&path).await.map_err(|e| ServerError::ShardIo(format!("{}: {e}", path.display())))?;
    Ok(([(CONTENT_TYPE, "application/json")], json).into_response())
}

/// Stores a rollout video as `evaluate/round_N/client_K/<file>`.
async fn post_video(
    Path((round, file)): Path<(u64, String)>,
    State(state): State<AppState>,
    headers: HeaderMap,
    body: Bytes,
) -> Result<Response, ServerError> {
    let token = headers
        .get(AUTHORIZATION)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.strip_prefix("Bearer "))
        .ok_or_else(|| ServerError::Unauthorized("no `Authorization: Bearer <session>` header".into()))?;
    let client_id = state
        .sessions
        .client(token)
        .ok_or_else(|| ServerError::Unauthorized("unknown session (is the client still connected?)".into()))?;
    let safe_name = !file.is_empty()
        && file.len() <= 64
        && file.chars().all(|c| c.is_ascii_alphanumeric() || matches!(c, '_' | '-' | '.'))
        && !file.starts_with('.')
        && (file.ends_with(".webm") || file.ends_with(".mp4"));
    if !safe_name {
        return Err(ServerError::BadRequest(format!("video name {file:?}: use [A-Za-z0-9_.-], ending .webm or .mp4")));
    }
    if body.is_empty() {
        return Err(ServerError::BadRequest(format!("video {file} is empty")));
    }
    let dir = state.run_dir.client_eval_dir(round, client_id);
    let path = dir.join(&file);
    let len = body.len();
    tokio::fs::create_dir_all(&dir).await.map_err(|e| ServerError::Storage(format!("{}: {e}", dir.display())))?;
    tokio::fs::write(&path, &body).await.map_err(|e| ServerError::Storage(format!("{}: {e}", path.display())))?;
    tracing::info!(client_id, round, file = %path.display(), bytes = len, "rollout video stored");
    state
        .console
        .publish(serde_json::json!({ "type": "video_stored", "round": round, "client_id": client_id, "file": file }));
    Ok((StatusCode::CREATED, format!("stored {len} bytes")).into_response())
}
