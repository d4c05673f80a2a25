//! What volunteers download and upload over HTTP, beside the WebSocket that admitted them (and gave them their
//! setup): the run's tokenizer (for a volunteer that tokenizes its own dataset's tasks), the shard and its
//! manifest, the frozen weights (named by content hash so browsers cache them forever), the global model (whole,
//! or as the deltas since a version the volunteer holds, `GET /model/{version}/deltas/{from}`), a
//! SCAFFOLD client's correction for its round (`GET /scaffold/{round}`), and rollout videos
//! (`POST /rollout/{round}/{file}`, for the round that asked, within `max-rollout-videos`, `max-video-bytes` and
//! the upload budget; each refusal counted on the console). Every route answers only a request presenting an
//! admitted connection's session ([`Session`]: 401 without one), and a shard only to a session of a key bound to
//! it (403 otherwise), public run or not.

use std::sync::Arc;

use axum::Router;
use axum::body::Body;
use axum::extract::{FromRef, FromRequestParts, Path, State};
use axum::http::header::{CACHE_CONTROL, CONTENT_LENGTH, CONTENT_TYPE};
use axum::http::request::Parts;
use axum::http::{HeaderMap, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use fedvla_aggregator::registry::Volunteers;
use fedvla_aggregator::sessions::{SessionHolder, UploadRefused};
use fedvla_federation::{ErrorCode, routes};
use futures_util::StreamExt;

use crate::auth::bearer;
use crate::console::ConsoleEvent;
use crate::error::ServerError;
use crate::state::{AppState, VolunteerState};
use crate::static_files::file_response;

pub fn routes() -> Router<AppState> {
    Router::new()
        .route(routes::FROZEN, get(get_frozen))
        .route(routes::TOKENIZER, get(get_tokenizer))
        .route(routes::SHARD, get(get_shard))
        .route(routes::SHARD_MANIFEST, get(get_shard_manifest))
        .route(routes::MODEL, get(get_model))
        .route(routes::MODEL_DELTAS, get(get_model_deltas))
        .route(routes::CORRECTION, get(get_correction))
        .route(routes::ROLLOUT_VIDEO, post(post_video))
}

/// The session a request presents (`Authorization: Bearer <session>`): that of a connection the server admitted
/// and that is still open.
struct Session(SessionHolder);

impl<S: Send + Sync> FromRequestParts<S> for Session
where
    VolunteerState: FromRef<S>,
{
    type Rejection = ServerError;

    async fn from_request_parts(parts: &mut Parts, state: &S) -> Result<Self, ServerError> {
        let token = bearer(&parts.headers).ok_or_else(|| {
            ServerError::Unauthorized(
                "no session: identify on the WebSocket, then `Authorization: Bearer <session>`".into(),
            )
        })?;
        let holder = VolunteerState::from_ref(state).sessions.holder(token);
        holder
            .map(Self)
            .ok_or_else(|| ServerError::Unauthorized("unknown session (is the client still connected?)".into()))
    }
}

impl Session {
    /// Refuses a shard other than the one bound to the session's key.
    fn may_download_shard(&self, index: usize) -> Result<(), ServerError> {
        match self.0.shard {
            Some(bound) if bound == index => Ok(()),
            _ => Err(ServerError::Forbidden(format!(
                "shard {index} is not this client's: a shard is served only to the keys bound to it"
            ))),
        }
    }
}

/// The run's `tokenizer.json`.
async fn get_tokenizer(_: Session, State(state): State<VolunteerState>) -> Result<Response, ServerError> {
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

/// The frozen weights, streamed from their file in the run directory (byte ranges too, so that a broken download
/// can go on where it stopped).
async fn get_frozen(
    _: Session,
    Path(tag): Path<String>,
    State(state): State<VolunteerState>,
    request: HeaderMap,
) -> Result<Response, axum::response::ErrorResponse> {
    let frozen = state.volunteers.frozen();
    match frozen {
        Some(file) if file.tag == tag => {
            let mut response = file_response(&file.path, &request).await?;
            response
                .headers_mut()
                .insert(CACHE_CONTROL, HeaderValue::from_static("public, max-age=31536000, immutable"));
            Ok(response)
        }
        _ => {
            let served = frozen.map(|f| &f.tag);
            Err(ServerError::NotFound(format!("frozen weights {tag}: this run serves {served:?}")).into())
        }
    }
}

/// The shard file as stored; clients check it against the manifest's size and SHA-256.
async fn get_shard(
    session: Session,
    Path(index): Path<usize>,
    State(state): State<VolunteerState>,
) -> Result<Response, ServerError> {
    session.may_download_shard(index)?;
    let path = state.volunteers.shard_file(index)?;
    let bytes = tokio::fs::read(path).await.map_err(|e| ServerError::ShardIo(format!("{}: {e}", path.display())))?;
    Ok(([(CONTENT_TYPE, "application/octet-stream")], bytes).into_response())
}

async fn get_shard_manifest(
    session: Session,
    Path(index): Path<usize>,
    State(state): State<VolunteerState>,
) -> Result<Response, ServerError> {
    session.may_download_shard(index)?;
    let path = fedvla_data::shard::sidecar_path(state.volunteers.shard_file(index)?);
    let json = tokio::fs::read(&path).await.map_err(|e| ServerError::ShardIo(format!("{}: {e}", path.display())))?;
    Ok(([(CONTENT_TYPE, "application/json")], json).into_response())
}

/// The global trainable tensors of the current version (or of the one before it).
async fn get_model(
    _: Session,
    Path(version): Path<u64>,
    State(state): State<VolunteerState>,
) -> Result<Response, ServerError> {
    let model = state.model.borrow().clone();
    let bytes =
        model.bytes_of(version).ok_or(ServerError::ModelVersion { requested: version, current: model.version })?;
    Ok(([(CONTENT_TYPE, "application/octet-stream")], bytes.clone()).into_response())
}

/// The chain of deltas taking version `from` to `version`, while the server keeps them (tasks say since when).
async fn get_model_deltas(
    _: Session,
    Path((version, from)): Path<(u64, u64)>,
    State(state): State<VolunteerState>,
) -> Result<Response, ServerError> {
    let model = state.model.borrow().clone();
    let chain = model.deltas(version, from).ok_or_else(|| {
        ServerError::NotFound(format!(
            "no deltas from version {from} to {version}: this server keeps those since {:?} to version {}; download \
             the whole model",
            model.deltas_since(),
            model.version
        ))
    })?;
    Ok(([(CONTENT_TYPE, "application/octet-stream")], chain).into_response())
}

/// The SCAFFOLD correction `c - c_i` the round's task offered the asking client (safetensors).
async fn get_correction(
    Session(SessionHolder { client_id, .. }): Session,
    Path(round): Path<u64>,
    State(state): State<VolunteerState>,
) -> Result<Response, ServerError> {
    let bytes = state.sessions.correction(client_id, round).ok_or_else(|| {
        ServerError::NotFound(format!("round {round} offered client {client_id} no SCAFFOLD correction"))
    })?;
    Ok(([(CONTENT_TYPE, "application/octet-stream")], bytes).into_response())
}

/// Stores a rollout video as `evaluate/round_N/client_K/<file>`. Its length (`Content-Length`, else
/// `max-video-bytes`) is reserved in the upload budget before its body is read.
async fn post_video(
    Session(SessionHolder { client_id, .. }): Session,
    Path((round, file)): Path<(u64, String)>,
    State(state): State<VolunteerState>,
    headers: HeaderMap,
    body: Body,
) -> Result<Response, ServerError> {
    let refused = |code: ErrorCode, error: ServerError| {
        state.console.count_refusal(code);
        error
    };
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
