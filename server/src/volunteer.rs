//! What volunteers download and upload over HTTP, beside the WebSocket: the setup (`GET /api/volunteer`: which
//! shard to train on, the policy configuration, where the frozen weights are), the shard and its manifest, the
//! frozen weights (named by content hash so browsers cache them forever), and rollout videos
//! (`POST /rollout/{round}/{file}`, authorised by the connection's session token).

use std::collections::{BTreeMap, HashMap};
use std::path::PathBuf;
use std::sync::{Arc, Mutex, MutexGuard};

use axum::Json;
use axum::Router;
use axum::body::Bytes;
use axum::extract::{DefaultBodyLimit, Path, Query, State};
use axum::http::header::{AUTHORIZATION, CACHE_CONTROL, CONTENT_TYPE};
use axum::http::{HeaderMap, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use fedvla_federation::protocol::MAX_NAME_BYTES;
use fedvla_federation::{ErrorCode, PROTOCOL_VERSION, VolunteerSetup};
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use crate::app::AppState;
use crate::error::ServerError;
use crate::run_dir::{RunDir, RunDirError};

/// Largest rollout video accepted.
const MAX_VIDEO_BYTES: usize = 64 << 20;
/// Client ids are reserved (and the reservation persisted) this many at a time, so a restarted server never hands
/// out an id it gave before (the `evaluate/round_N/client_K/` directories stay one client's each).
const CLIENT_ID_BLOCK: u64 = 1024;

/// One shard a workload offers: its file (none for shards a client generates from its index, as linreg's) and the
/// training examples in it, which weigh every update of the client training on it.
#[derive(Debug, Clone, PartialEq)]
pub struct ShardOffer {
    pub file: Option<PathBuf>,
    pub train_examples: u64,
}

/// What a workload offers volunteers.
#[derive(Debug, Clone, Default)]
pub struct VolunteerOffer {
    /// "smolvla" or "linreg".
    pub workload: String,
    /// Client shards by shard index (a file's `.manifest.json` sidecar beside it).
    pub shards: Vec<ShardOffer>,
    /// `{"policy": <LeRobot config.json>, "vlm": <vlm/config.json>}`, null when there is no policy.
    pub policy: serde_json::Value,
    /// The frozen tensors as safetensors, when the workload has any.
    pub frozen: Option<Bytes>,
    /// The sim task's token ids and mask.
    pub rollout_task_tokens: Vec<u32>,
    pub rollout_task_mask: Vec<bool>,
}

/// The shard a joined client trains on, as the server knows it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ShardBinding {
    pub index: usize,
    /// The weight of the client's updates.
    pub train_examples: u64,
}

/// Why a volunteer was refused.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum VolunteerError {
    #[error("volunteer name of {len} bytes: names are 1 to {MAX_NAME_BYTES} bytes without control characters")]
    InvalidName { len: usize },
    #[error("no shard {index}: this run has {count}")]
    UnknownShard { index: usize, count: usize },
}

impl VolunteerError {
    pub fn code(&self) -> ErrorCode {
        match self {
            Self::InvalidName { .. } => ErrorCode::InvalidName,
            Self::UnknownShard { .. } => ErrorCode::UnknownShard,
        }
    }
}

/// Checks a volunteer name: it keys the shard registry and appears in logs, metrics and the console.
pub fn check_name(name: &str) -> Result<(), VolunteerError> {
    if name.is_empty() || name.len() > MAX_NAME_BYTES || name.chars().any(char::is_control) {
        return Err(VolunteerError::InvalidName { len: name.len() });
    }
    Ok(())
}

/// Which shard each named volunteer was given and which client ids are spent: `volunteers.json` in the run
/// directory, so a restarted server keeps both.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Registry {
    /// The next shard handed out round-robin.
    pub next_shard: usize,
    /// Client ids below this were (or may have been) handed out.
    pub reserved_client_ids: u64,
    /// Shard by volunteer name, with the order in which names were first bound (the oldest is pruned first).
    pub assignments: BTreeMap<String, Assignment>,
    /// Counter behind `Assignment::order`.
    pub bindings: u64,
    /// The next client id (not persisted: a restart continues after the reservation).
    #[serde(skip)]
    next_client_id: u64,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Assignment {
    pub shard: usize,
    pub order: u64,
}

/// The offer as served: the frozen weights' content tag, and the registry of names, shards and client ids
/// (round-robin, sticky by name, at most `max_names` names).
pub struct Volunteers {
    offer: VolunteerOffer,
    /// Hex SHA-256 prefix of the frozen safetensors; part of their URL.
    frozen_tag: Option<String>,
    registry: Mutex<Registry>,
    max_names: usize,
    run_dir: RunDir,
    /// Held while the registry is written, so the last write is the newest state.
    writing: Mutex<()>,
}

impl Volunteers {
    /// The volunteers of the run in `run_dir`, continuing its saved registry if it has one.
    pub fn new(offer: VolunteerOffer, run_dir: RunDir, max_names: usize) -> Result<Self, RunDirError> {
        let frozen_tag = offer.frozen.as_ref().map(|bytes| {
            let digest = Sha256::digest(bytes);
            digest[..8].iter().map(|b| format!("{b:02x}")).collect()
        });
        let mut registry = run_dir.read_volunteers()?.unwrap_or_default();
        registry.next_client_id = registry.reserved_client_ids.max(1);
        Ok(Self { offer, frozen_tag, registry: Mutex::new(registry), max_names, run_dir, writing: Mutex::default() })
    }

    /// The shard of volunteer `name`: `requested` when given (it becomes the name's shard), else the name's
    /// shard, else the next one round-robin; `None` when the workload offers no shards. Also says whether the
    /// registry changed (and so should be persisted).
    fn assign(
        &self,
        name: Option<&str>,
        requested: Option<usize>,
    ) -> Result<(Option<ShardBinding>, bool), VolunteerError> {
        if let Some(name) = name {
            check_name(name)?;
        }
        let count = self.offer.shards.len();
        if let Some(index) = requested.filter(|&i| i >= count) {
            return Err(VolunteerError::UnknownShard { index, count });
        }
        if count == 0 {
            return Ok((None, false));
        }
        let mut registry = self.registry();
        let (index, changed) = match name {
            Some(name) => {
                let current = registry.assignments.get(name).map(|a| a.shard);
                let index = match (requested, current) {
                    (Some(index), _) | (None, Some(index)) => index,
                    (None, None) => registry.round_robin(count),
                };
                (index, registry.bind(name, index, self.max_names))
            }
            None => (requested.unwrap_or_else(|| registry.round_robin(count)), false),
        };
        Ok((Some(ShardBinding { index, train_examples: self.offer.shards[index].train_examples }), changed))
    }

    /// A joining client: its (never reused) id, the shard it trains on as [`Volunteers::assign`] picks it, and
    /// whether the registry must be persisted before the client is welcomed.
    pub fn join(
        &self,
        name: &str,
        requested: Option<u32>,
    ) -> Result<(u64, Option<ShardBinding>, bool), VolunteerError> {
        let (shard, changed) = self.assign(Some(name), requested.map(|s| s as usize))?;
        let mut registry = self.registry();
        let id = registry.next_client_id;
        registry.next_client_id += 1;
        Ok((id, shard, changed || registry.next_client_id + CLIENT_ID_BLOCK / 2 >= registry.reserved_client_ids))
    }

    /// Writes the registry (`volunteers.json`), reserving the next block of client ids when the current one is
    /// half used. Blocking: call it off the async runtime.
    pub fn persist(&self) -> Result<(), RunDirError> {
        let _writing = self.writing.lock().expect("registry writer lock");
        let snapshot = {
            let mut registry = self.registry();
            if registry.next_client_id + CLIENT_ID_BLOCK / 2 >= registry.reserved_client_ids {
                registry.reserved_client_ids = registry.next_client_id + CLIENT_ID_BLOCK;
            }
            registry.clone()
        };
        self.run_dir.write_volunteers(&snapshot)
    }

    fn registry(&self) -> MutexGuard<'_, Registry> {
        self.registry.lock().expect("volunteer registry lock")
    }

    fn shard_file(&self, index: usize) -> Result<&PathBuf, ServerError> {
        let count = self.offer.shards.len();
        self.offer
            .shards
            .get(index)
            .ok_or(ServerError::NoShard { index, count })?
            .file
            .as_ref()
            .ok_or_else(|| ServerError::NotFound(format!("shard {index} has no file: clients generate it")))
    }
}

impl Registry {
    fn round_robin(&mut self, count: usize) -> usize {
        let index = self.next_shard % count;
        self.next_shard = (index + 1) % count;
        index
    }

    /// Records `name`'s shard, dropping the name bound first when the registry is full; false when the name
    /// already had that shard.
    fn bind(&mut self, name: &str, shard: usize, max_names: usize) -> bool {
        if let Some(a) = self.assignments.get_mut(name) {
            return std::mem::replace(&mut a.shard, shard) != shard;
        }
        if self.assignments.len() >= max_names.max(1) {
            let oldest = self.assignments.iter().min_by_key(|(_, a)| a.order).map(|(n, _)| n.clone());
            if let Some(oldest) = oldest {
                tracing::info!(name = %oldest, max_names, "volunteer registry full: forgetting the oldest name");
                self.assignments.remove(&oldest);
            }
        }
        self.bindings += 1;
        self.assignments.insert(name.to_owned(), Assignment { shard, order: self.bindings });
        true
    }
}

/// Session tokens of the connected clients, for their HTTP uploads, and the rollout videos each may upload.
#[derive(Clone, Default)]
pub struct Sessions {
    inner: Arc<Mutex<SessionTable>>,
}

#[derive(Default)]
struct SessionTable {
    by_token: HashMap<String, u64>,
    /// Client id -> (round, videos it may still upload for that round).
    uploads: HashMap<u64, (u64, u32)>,
}

impl Sessions {
    /// A fresh unguessable token for `client_id`.
    pub fn open(&self, client_id: u64) -> String {
        let token = crate::console::random_token();
        self.table().by_token.insert(token.clone(), client_id);
        token
    }

    pub fn close(&self, client_id: u64) {
        let mut table = self.table();
        table.by_token.retain(|_, id| *id != client_id);
        table.uploads.remove(&client_id);
    }

    /// Lets `client_id` upload `videos` rollout videos for `round` (its task asked for that many episodes).
    pub fn allow_uploads(&self, client_id: u64, round: u64, videos: u32) {
        self.table().uploads.insert(client_id, (round, videos));
    }

    /// Ends every upload permission of `round` (it closed).
    pub fn end_uploads(&self, round: u64) {
        self.table().uploads.retain(|_, (r, _)| *r != round);
    }

    fn client(&self, token: &str) -> Option<u64> {
        self.table().by_token.get(token).copied()
    }

    /// Takes one of `client_id`'s video uploads for `round`.
    fn take_upload(&self, client_id: u64, round: u64) -> Result<(), ServerError> {
        match self.table().uploads.get_mut(&client_id) {
            Some((r, left)) if *r == round && *left > 0 => {
                *left -= 1;
                Ok(())
            }
            Some((r, 0)) if *r == round => Err(ServerError::Forbidden(format!(
                "client {client_id} has uploaded every video round {round} asked it for"
            ))),
            _ => Err(ServerError::Forbidden(format!("round {round} asked client {client_id} for no rollout videos"))),
        }
    }

    fn table(&self) -> MutexGuard<'_, SessionTable> {
        self.inner.lock().expect("sessions lock")
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
    /// A shard the volunteer wants (`fedvla join --shard`); it becomes the name's shard.
    shard: Option<usize>,
}

/// The setup of a volunteer (`?name=` keeps a returning one on its shard).
async fn get_setup(
    State(state): State<AppState>,
    Query(query): Query<SetupQuery>,
) -> Result<Json<VolunteerSetup>, ServerError> {
    let v = Arc::clone(&state.volunteers);
    let (binding, changed) =
        v.assign(query.name.as_deref(), query.shard).map_err(|e| ServerError::BadRequest(e.to_string()))?;
    if changed {
        persist(&v).await?;
    }
    let index = binding.map_or(0, |b| b.index);
    Ok(Json(VolunteerSetup {
        protocol_version: PROTOCOL_VERSION,
        workload: v.offer.workload.clone(),
        shard_index: index as u32,
        shard_count: v.offer.shards.len() as u32,
        shard_url: format!("/shard/{index}"),
        shard_manifest_url: format!("/shard/{index}/manifest"),
        policy: v.offer.policy.clone(),
        frozen_url: v.frozen_tag.as_ref().map(|tag| format!("/policy/frozen/{tag}")),
        frozen_bytes: v.offer.frozen.as_ref().map_or(0, |b| b.len() as u64),
        rollout_task_tokens: v.offer.rollout_task_tokens.clone(),
        rollout_task_mask: v.offer.rollout_task_mask.clone(),
        model_version: state.model.borrow().version,
    }))
}

/// Writes the registry off the async runtime.
pub async fn persist(volunteers: &Arc<Volunteers>) -> Result<(), ServerError> {
    let v = Arc::clone(volunteers);
    match tokio::task::spawn_blocking(move || v.persist()).await {
        Ok(result) => result.map_err(|e| ServerError::Storage(e.to_string())),
        Err(e) => std::panic::resume_unwind(e.into_panic()),
    }
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
    let path = state.volunteers.shard_file(index)?;
    let bytes = tokio::fs::read(path).await.map_err(|e| ServerError::ShardIo(format!("{}: {e}", path.display())))?;
    Ok(([(CONTENT_TYPE, "application/octet-stream")], bytes).into_response())
}

async fn get_shard_manifest(Path(index): Path<usize>, State(state): State<AppState>) -> Result<Response, ServerError> {
    let path = fedvla_data::shard::sidecar_path(state.volunteers.shard_file(index)?);
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
    state.sessions.take_upload(client_id, round)?;
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
