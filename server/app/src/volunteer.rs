//! What volunteers download and upload over HTTP, beside the WebSocket: the setup (`GET /api/volunteer`: which
//! shard to train on, the policy configuration, where the frozen weights are), the run's tokenizer (for a
//! volunteer that tokenizes its own dataset's tasks), the shard and its manifest, the
//! frozen weights (named by content hash so browsers cache them forever), the global model, and rollout videos
//! (`POST /rollout/{round}/{file}`, authorised by the connection's session token, for the round that asked, within
//! `max-rollout-videos`, `max-video-bytes` and the upload budget; each refusal counted on the console), and a
//! SCAFFOLD client's correction for its round (`GET /scaffold/{round}`, by the same token).
//! A run with an auth token serves its downloads only to requests that present it ([`RunToken`]).

use std::sync::Arc;

use axum::Json;
use axum::Router;
use axum::body::Body;
use axum::extract::{FromRef, FromRequestParts, Path, Query, State};
use axum::http::header::{CACHE_CONTROL, CONTENT_LENGTH, CONTENT_TYPE};
use axum::http::request::Parts;
use axum::http::{HeaderMap, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use fedvla_aggregator::registry::Volunteers;
use fedvla_aggregator::sessions::{UploadRefused, same_secret};
use fedvla_federation::{ErrorCode, PROTOCOL_VERSION, VolunteerSetup, routes};
use futures_util::StreamExt;
use serde::Deserialize;

use crate::auth::bearer;
use crate::console::ConsoleEvent;
use crate::error::ServerError;
use crate::state::{AppState, VolunteerState};

pub fn routes() -> Router<AppState> {
    Router::new()
        .route(routes::VOLUNTEER, get(get_setup))
        .route(routes::FROZEN, get(get_frozen))
        .route(routes::TOKENIZER, get(get_tokenizer))
        .route(routes::SHARD, get(get_shard))
        .route(routes::SHARD_MANIFEST, get(get_shard_manifest))
        .route(routes::MODEL, get(get_model))
        .route(routes::CORRECTION, get(get_correction))
        .route(routes::ROLLOUT_VIDEO, post(post_video))
}

/// Proof that a download request may see the run's data: it presents the run's auth token (compared in constant
/// time), or the run has none (a public run).
struct RunToken;

impl<S: Send + Sync> FromRequestParts<S> for RunToken
where
    VolunteerState: FromRef<S>,
{
    type Rejection = ServerError;

    async fn from_request_parts(parts: &mut Parts, state: &S) -> Result<Self, ServerError> {
        let Some(expected) = VolunteerState::from_ref(state).auth_token else { return Ok(Self) };
        match bearer(&parts.headers) {
            Some(token) if same_secret(token, &expected) => Ok(Self),
            Some(_) => Err(ServerError::Unauthorized("wrong auth token".into())),
            None => Err(ServerError::Unauthorized(
                "this run needs its auth token: `Authorization: Bearer <auth-token>`".into(),
            )),
        }
    }
}

/// Who asks for a setup.
#[derive(Deserialize)]
struct SetupQuery {
    name: Option<String>,
    /// A shard the volunteer wants (`fedvla join --shard`); it becomes the name's shard.
    shard: Option<usize>,
    /// The volunteer trains on its own dataset (`fedvla join --dataset`): it is assigned no shard.
    #[serde(default)]
    own_dataset: bool,
}

/// The setup of a volunteer (`?name=` keeps a returning one on its shard).
async fn get_setup(
    _: RunToken,
    State(state): State<VolunteerState>,
    Query(query): Query<SetupQuery>,
) -> Result<Json<VolunteerSetup>, ServerError> {
    let v = &state.volunteers;
    let (binding, changed) = match query.own_dataset {
        true => (None, false),
        false => v.assign(query.name.as_deref(), query.shard).map_err(|e| ServerError::BadRequest(e.to_string()))?,
    };
    if changed {
        persist(v).await?;
    }
    let index = binding.map_or(0, |b| b.index) as u32;
    let offer = v.offer();
    Ok(Json(VolunteerSetup {
        protocol_version: PROTOCOL_VERSION,
        workload: offer.workload,
        shard_index: index,
        shard_count: offer.shards.len() as u32,
        shard_url: routes::shard(index),
        shard_manifest_url: routes::shard_manifest(index),
        policy: offer.policy.clone(),
        frozen_url: v.frozen_tag().map(routes::frozen),
        frozen_bytes: offer.frozen.as_ref().map_or(0, |b| b.len() as u64),
        rollout_tasks: offer.rollout_tasks.clone(),
        model_version: state.model.borrow().version,
        tokenizer_url: offer.tokenizer.as_ref().map(|_| routes::TOKENIZER.to_owned()),
        dataset_signature: offer.signature.clone(),
    }))
}

/// The run's `tokenizer.json`.
async fn get_tokenizer(_: RunToken, State(state): State<VolunteerState>) -> Result<Response, ServerError> {
    let bytes = state.volunteers.offer().tokenizer.clone().ok_or_else(|| {
        ServerError::NotFound("this run has no tokenizer to serve (its workload tokenizes nothing)".into())
    })?;
    Ok(([(CONTENT_TYPE, "application/json")], bytes).into_response())
}

/// Writes the registry off the async runtime.
pub async fn persist(volunteers: &Arc<Volunteers>) -> Result<(), ServerError> {
    let v = Arc::clone(volunteers);
    match tokio::task::spawn_blocking(move || v.persist()).await {
        Ok(result) => result.map_err(|e| ServerError::Storage(e.to_string())),
        Err(e) => std::panic::resume_unwind(e.into_panic()),
    }
}

async fn get_frozen(
    _: RunToken,
    Path(tag): Path<String>,
    State(state): State<VolunteerState>,
) -> Result<Response, ServerError> {
    let v = &state.volunteers;
    match (&v.offer().frozen, v.frozen_tag()) {
        (Some(bytes), Some(current)) if current == tag => Ok((
            [(CONTENT_TYPE, "application/octet-stream"), (CACHE_CONTROL, "public, max-age=31536000, immutable")],
            bytes.clone(),
        )
            .into_response()),
        _ => Err(ServerError::NotFound(format!("frozen weights {tag}: this run serves {:?}", v.frozen_tag()))),
    }
}

/// The shard file as stored; clients check it against the manifest's size and SHA-256.
async fn get_shard(
    _: RunToken,
    Path(index): Path<usize>,
    State(state): State<VolunteerState>,
) -> Result<Response, ServerError> {
    let path = state.volunteers.shard_file(index)?;
    let bytes = tokio::fs::read(path).await.map_err(|e| ServerError::ShardIo(format!("{}: {e}", path.display())))?;
    Ok(([(CONTENT_TYPE, "application/octet-stream")], bytes).into_response())
}

async fn get_shard_manifest(
    _: RunToken,
    Path(index): Path<usize>,
    State(state): State<VolunteerState>,
) -> Result<Response, ServerError> {
    let path = fedvla_data::shard::sidecar_path(state.volunteers.shard_file(index)?);
    let json = tokio::fs::read(&path).await.map_err(|e| ServerError::ShardIo(format!("{}: {e}", path.display())))?;
    Ok(([(CONTENT_TYPE, "application/json")], json).into_response())
}

/// The global trainable tensors of the current version (or of the one before it).
async fn get_model(
    _: RunToken,
    Path(version): Path<u64>,
    State(state): State<VolunteerState>,
) -> Result<Response, ServerError> {
    let model = state.model.borrow().clone();
    let bytes =
        model.bytes_of(version).ok_or(ServerError::ModelVersion { requested: version, current: model.version })?;
    Ok(([(CONTENT_TYPE, "application/octet-stream")], bytes.clone()).into_response())
}

/// The client whose connection's session token the request presents.
fn session_client(state: &VolunteerState, headers: &HeaderMap) -> Result<u64, ServerError> {
    let token = bearer(headers)
        .ok_or_else(|| ServerError::Unauthorized("no `Authorization: Bearer <session>` header".into()))?;
    state
        .sessions
        .client(token)
        .ok_or_else(|| ServerError::Unauthorized("unknown session (is the client still connected?)".into()))
}

/// The SCAFFOLD correction `c - c_i` the round's task offered the asking client (safetensors).
async fn get_correction(
    Path(round): Path<u64>,
    State(state): State<VolunteerState>,
    headers: HeaderMap,
) -> Result<Response, ServerError> {
    let client_id = session_client(&state, &headers)?;
    let bytes = state.sessions.correction(client_id, round).ok_or_else(|| {
        ServerError::NotFound(format!("round {round} offered client {client_id} no SCAFFOLD correction"))
    })?;
    Ok(([(CONTENT_TYPE, "application/octet-stream")], bytes).into_response())
}

/// Stores a rollout video as `evaluate/round_N/client_K/<file>`. Its length (`Content-Length`, else
/// `max-video-bytes`) is reserved in the upload budget before its body is read.
async fn post_video(
    Path((round, file)): Path<(u64, String)>,
    State(state): State<VolunteerState>,
    headers: HeaderMap,
    body: Body,
) -> Result<Response, ServerError> {
    let refused = |code: ErrorCode, error: ServerError| {
        state.console.count_refusal(code);
        error
    };
    let client_id = session_client(&state, &headers)?;
    let safe_name = !file.is_empty()
        && file.len() <= 64
        && file.chars().all(|c| c.is_ascii_alphanumeric() || matches!(c, '_' | '-' | '.'))
        && !file.starts_with('.')
        && (file.ends_with(".webm") || file.ends_with(".mp4"));
    if !safe_name {
        return Err(ServerError::BadRequest(format!("video name {file:?}: use [A-Za-z0-9_.-], ending .webm or .mp4")));
    }
    let max = state.max_video_bytes;
    let too_large = |len: String| ServerError::TooLarge(format!("video {file}: {len} bytes, max-video-bytes is {max}"));
    let announced = headers.get(CONTENT_LENGTH).and_then(|v| v.to_str().ok()?.parse::<u64>().ok());
    if let Some(len) = announced.filter(|len| *len > max) {
        return Err(refused(ErrorCode::VideoTooLarge, too_large(len.to_string())));
    }
    let Some(_reservation) = state.uploads.reserve(announced.unwrap_or(max)) else {
        let message = format!("the {} bytes held for uploads in flight are taken; try again", state.uploads.limit());
        return Err(refused(ErrorCode::UploadBudget, ServerError::Busy(message)));
    };
    let mut body = body.into_data_stream();
    let mut video = Vec::with_capacity(announced.unwrap_or(0) as usize);
    while let Some(chunk) = body.next().await {
        let chunk = chunk.map_err(|e| ServerError::BadRequest(format!("video {file}: {e}")))?;
        if (video.len() + chunk.len()) as u64 > max {
            return Err(refused(ErrorCode::VideoTooLarge, too_large(format!("more than {max}"))));
        }
        video.extend_from_slice(&chunk);
    }
    if video.is_empty() {
        return Err(ServerError::BadRequest(format!("video {file} is empty")));
    }
    state.sessions.take_upload(client_id, round).map_err(|e| {
        let code = match e {
            UploadRefused::NotAsked { .. } => ErrorCode::UnrequestedVideo,
            UploadRefused::AllTaken { .. } => ErrorCode::TooManyVideos,
        };
        refused(code, ServerError::Forbidden(e.to_string()))
    })?;
    let dir = state.run_dir.client_eval_dir(round, client_id);
    let path = dir.join(&file);
    let len = video.len();
    let stored = {
        let (dir, path) = (dir.clone(), path.clone());
        tokio::task::spawn_blocking(move || {
            fedvla_fs::create_dir_all(&dir).and_then(|()| fedvla_fs::write_atomic(&path, &video))
        })
    };
    match stored.await {
        Ok(result) => result.map_err(|e| ServerError::Storage(format!("{}: {e}", path.display())))?,
        Err(e) => std::panic::resume_unwind(e.into_panic()),
    }
    tracing::info!(client_id, round, file = %path.display(), bytes = len, "rollout video stored");
    state.console.publish(ConsoleEvent::VideoStored { round, client_id, file });
    Ok((StatusCode::CREATED, format!("stored {len} bytes")).into_response())
}
