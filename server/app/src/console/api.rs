//! The console's HTTP API (`/console/api/...`), every route behind the operator token: the snapshot (live state,
//! every metrics line, the gallery, downloadable rounds), the event stream, the operator's controls and settings,
//! each round's LeRobot checkpoint as a tar, and the run directory's files.

use std::convert::Infallible;
use std::io::Write;
use std::path::PathBuf;

use axum::body::{Body, Bytes};
use axum::extract::{Path as UrlPath, Query, Request, State};
use axum::http::header::{CONTENT_DISPOSITION, CONTENT_TYPE};
use axum::http::{HeaderMap, StatusCode};
use axum::middleware::{self, Next};
use axum::response::sse::{Event as SseEvent, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Json, Router};
use fedvla_aggregator::control::{ControlAction, Settings};
use fedvla_aggregator::records::{MetricsLine, read_metrics};
use fedvla_aggregator::run_dir::POLICY_DIR;
use futures_util::{Stream, StreamExt};
use serde::{Deserialize, Serialize};
use serde_json::{Value, json};
use tokio::sync::broadcast::error::RecvError;
use tokio_util::io::{ReaderStream, SyncIoBridge};

use super::events::ConsoleEvent;
use super::gallery::{RoundGallery, checkpoint_rounds, gallery};
use super::hub::{ConsoleHub, LiveSnapshot};
use crate::auth::bearer;
use crate::state::{AppState, ConsoleState};
use crate::static_files::{FileError, file_response, relative_path};

#[derive(Debug, thiserror::Error)]
pub enum ConsoleError {
    #[error("missing operator token: send `Authorization: Bearer <token>` or add `?token=<token>` to the URL")]
    MissingToken,
    #[error("wrong operator token")]
    WrongToken,
    #[error("bad {what}: {message}")]
    BadRequest { what: &'static str, message: String },
    #[error("{0}")]
    Conflict(String),
    #[error("round {round} has no LeRobot policy directory ({})", .path.display())]
    NoCheckpoint { round: u64, path: PathBuf },
    #[error(transparent)]
    File(#[from] FileError),
    #[error("reading the run directory: {0}")]
    RunDir(String),
}

impl IntoResponse for ConsoleError {
    fn into_response(self) -> Response {
        let status = match &self {
            Self::MissingToken | Self::WrongToken => StatusCode::UNAUTHORIZED,
            Self::BadRequest { .. } => StatusCode::BAD_REQUEST,
            Self::Conflict(_) => StatusCode::CONFLICT,
            Self::NoCheckpoint { .. } => StatusCode::NOT_FOUND,
            Self::File(e) => e.status(),
            Self::RunDir(_) => StatusCode::INTERNAL_SERVER_ERROR,
        };
        (status, Json(json!({ "error": self.to_string() }))).into_response()
    }
}

/// The console API, every route behind the operator token.
pub fn routes(console: &ConsoleHub) -> Router<AppState> {
    Router::new()
        .route("/console/api/snapshot", get(snapshot))
        .route("/console/api/events", get(events))
        .route("/console/api/control", post(control))
        .route("/console/api/settings", post(change_settings))
        .route("/console/api/checkpoint/{round}", get(checkpoint))
        .route("/console/api/file/{*path}", get(run_file))
        .route_layer(middleware::from_fn_with_state(console.clone(), require_operator))
}

#[derive(Deserialize)]
struct TokenQuery {
    token: Option<String>,
}

/// The token comes as `Authorization: Bearer`, or as `?token=` where a browser cannot set headers
/// (EventSource, `<video src>`, download links).
async fn require_operator(
    State(console): State<ConsoleHub>,
    Query(query): Query<TokenQuery>,
    request: Request,
    next: Next,
) -> Response {
    match bearer(request.headers()).or(query.token.as_deref()) {
        None => ConsoleError::MissingToken.into_response(),
        Some(token) if console.is_operator(token) => next.run(request).await,
        Some(_) => ConsoleError::WrongToken.into_response(),
    }
}

/// What `GET /console/api/snapshot` answers.
#[derive(Debug, Serialize)]
pub struct Snapshot {
    #[serde(flatten)]
    live: LiveSnapshot,
    metrics: Vec<MetricsLine>,
    gallery: Vec<RoundGallery>,
    /// Rounds whose LeRobot policy directory can be downloaded.
    checkpoints: Vec<u64>,
}

/// Live state, every metrics line so far, the video gallery and the rounds with a downloadable checkpoint.
async fn snapshot(State(state): State<ConsoleState>) -> Result<Json<Snapshot>, ConsoleError> {
    let run_dir = state.run_dir.clone();
    let (metrics, gallery, checkpoints) = tokio::task::spawn_blocking(move || {
        let read = || -> std::io::Result<_> {
            Ok((read_metrics(run_dir.path())?, gallery(run_dir.path())?, checkpoint_rounds(run_dir.path())?))
        };
        read().map_err(|e| ConsoleError::RunDir(format!("{}: {e}", run_dir.path().display())))
    })
    .await
    .map_err(|e| ConsoleError::RunDir(e.to_string()))??;
    Ok(Json(Snapshot { live: state.hub.live_snapshot(), metrics, gallery, checkpoints }))
}

/// Server-sent events: every event the hub publishes, as a JSON `data:` line, until the server shuts down. A
/// console that fell behind gets `{"type": "resync"}` and should re-read the snapshot.
async fn events(State(state): State<ConsoleState>) -> Sse<impl Stream<Item = Result<SseEvent, Infallible>>> {
    let stream = futures_util::stream::unfold(state.hub.subscribe(), |mut events| async move {
        let event = match events.recv().await {
            Ok(event) => event,
            Err(RecvError::Lagged(missed)) => ConsoleEvent::Resync { missed },
            Err(RecvError::Closed) => return None,
        };
        let data = serde_json::to_string(&event).expect("console events serialize");
        Some((Ok(SseEvent::default().data(data)), events))
    })
    // An open stream would otherwise hold the graceful shutdown up forever.
    .take_until(state.cancel.clone().cancelled_owned());
    Sse::new(stream).keep_alive(KeepAlive::default())
}

/// The body as `T`, or a 400 naming what was wrong with it.
fn parse_body<T: for<'de> Deserialize<'de>>(body: &Bytes, what: &'static str) -> Result<T, ConsoleError> {
    serde_json::from_slice(body).map_err(|e| ConsoleError::BadRequest { what, message: e.to_string() })
}

/// The body as settings; a bad value is named by its key (serde alone would name only its line and column).
fn parse_settings(body: &Bytes) -> Result<Settings, ConsoleError> {
    let bad = |message: String| ConsoleError::BadRequest { what: "settings", message };
    let object: serde_json::Map<String, Value> = serde_json::from_slice(body)
        .map_err(|e| bad(format!("{e}; send a JSON object such as {{\"local-steps\": 10}}")))?;
    for (key, value) in &object {
        serde_json::from_value::<Settings>(json!({ key: value })).map_err(|e| bad(format!("`{key}`: {e}")))?;
    }
    serde_json::from_value(Value::Object(object)).map_err(|e| bad(e.to_string()))
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct ControlRequest {
    action: ControlAction,
}

/// `{"action": "start" | "pause" | "resume" | "stop"}`; answers the run state it leads to.
async fn control(State(state): State<ConsoleState>, body: Bytes) -> Result<Json<Value>, ConsoleError> {
    let request: ControlRequest = parse_body(&body, "control request")?;
    let run_state = state.hub.control(request.action).map_err(ConsoleError::Conflict)?;
    Ok(Json(json!({ "state": run_state })))
}

/// Any of the [`Settings`] keys; answers every setting as the next round will have it.
async fn change_settings(State(state): State<ConsoleState>, body: Bytes) -> Result<Json<Value>, ConsoleError> {
    let change = parse_settings(&body)?;
    if change.is_empty() {
        return Err(ConsoleError::BadRequest {
            what: "settings",
            message: format!("none given; settable: {}", Settings::keys().join(", ")),
        });
    }
    let settings = state
        .hub
        .change_settings(change)
        .map_err(|e| ConsoleError::BadRequest { what: "settings", message: e.to_string() })?;
    Ok(Json(json!({ "settings": settings })))
}

/// Round `round`'s LeRobot policy directory as a tar archive, streamed as it is written.
async fn checkpoint(State(state): State<ConsoleState>, UrlPath(round): UrlPath<u64>) -> Result<Response, ConsoleError> {
    let dir = state.run_dir.model_dir(round).join(POLICY_DIR);
    if !tokio::fs::metadata(&dir).await.is_ok_and(|m| m.is_dir()) {
        return Err(ConsoleError::NoCheckpoint { round, path: dir });
    }
    let name = format!("fedvla_round_{round}_policy");
    let (reader, writer) = tokio::io::duplex(256 * 1024);
    let writer = SyncIoBridge::new(writer);
    let top = name.clone();
    tokio::task::spawn_blocking(move || {
        let mut archive = tar::Builder::new(writer);
        let written = archive
            .append_dir_all(&top, &dir)
            .and_then(|()| archive.into_inner())
            .and_then(|mut writer| writer.flush());
        if let Err(e) = written {
            // The client sees the download cut short.
            tracing::warn!(round, error = %e, "checkpoint download not completed");
        }
    });
    Ok((
        [
            (CONTENT_TYPE, "application/x-tar".to_owned()),
            (CONTENT_DISPOSITION, format!("attachment; filename=\"{name}.tar\"")),
        ],
        Body::from_stream(ReaderStream::new(reader)),
    )
        .into_response())
}

/// A file of the run directory: the gallery's videos and results.
async fn run_file(
    State(state): State<ConsoleState>,
    UrlPath(path): UrlPath<String>,
    headers: HeaderMap,
) -> Result<Response, ConsoleError> {
    let full = state.run_dir.path().join(relative_path(&path)?);
    Ok(file_response(&full, &headers).await?)
}
