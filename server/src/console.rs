//! The operator console's server side. [`ConsoleHub`] is shared by the coordinator and the HTTP handlers: the
//! coordinator publishes into it (JSON events, the live client table, the round timeline) and reads from it what
//! the operator decided (run state, settings). The `/console/api` routes serve it, the run directory's metrics,
//! videos and checkpoints, and the operator's controls; every one of them wants the operator token.

use std::collections::BTreeMap;
use std::convert::Infallible;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{SystemTime, UNIX_EPOCH};

use axum::body::{Body, Bytes};
use axum::extract::{Path as UrlPath, Query, Request, State};
use axum::http::header::{AUTHORIZATION, CONTENT_DISPOSITION, CONTENT_TYPE};
use axum::http::{HeaderMap, StatusCode};
use axum::middleware::{self, Next};
use axum::response::sse::{Event as SseEvent, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Json, Router};
use futures_util::{Stream, StreamExt};
use percent_encoding::{AsciiSet, NON_ALPHANUMERIC, utf8_percent_encode};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use serde::{Deserialize, Serialize};
use serde_json::{Value, json};
use tokio::sync::broadcast::error::RecvError;
use tokio::sync::{broadcast, watch};
use tokio_util::io::{ReaderStream, SyncIoBridge};

use crate::app::AppState;
use crate::config::{ConfigError, RunConfig};
use crate::coordinator::RunStatus;
use crate::run_dir::{EVALUATE_DIR, METRICS_FILE, MODELS_DIR, POLICY_DIR, ROLLOUTS_DIR};
use crate::sim_eval::RESULTS_FILE;
use crate::static_files::{FileError, file_response, relative_path};

/// Events a slow console may fall behind by before it is told to re-read the snapshot.
const EVENT_BACKLOG: usize = 1024;
/// Clients that left stay in the table for the operator to see, the most recent this many of them.
const LEFT_CLIENTS_KEPT: usize = 256;

/// What the operator may change while the run goes on. Each applies from the next round's tasks on; a field left
/// out (`None`) is not changed.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case", deny_unknown_fields)]
pub struct Settings {
    #[serde(skip_serializing_if = "Option::is_none")]
    pub local_steps: Option<u32>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub batch_size: Option<u32>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub lr: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub fraction_fit: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub rollout_episodes: Option<usize>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub client_rollout_episodes: Option<u32>,
}

impl Settings {
    /// Every setting as `config` has it.
    pub fn of(config: &RunConfig) -> Self {
        Self {
            local_steps: Some(config.local_steps),
            batch_size: Some(config.batch_size),
            lr: Some(config.lr),
            fraction_fit: Some(config.fraction_fit),
            rollout_episodes: Some(config.rollout_episodes),
            client_rollout_episodes: Some(config.client_rollout_episodes),
        }
    }

    pub fn is_empty(&self) -> bool {
        *self == Self::default()
    }

    /// `config` with these settings applied, validated as a whole.
    pub fn applied_to(&self, config: &RunConfig) -> Result<RunConfig, ConfigError> {
        let mut out = config.clone();
        out.local_steps = self.local_steps.unwrap_or(out.local_steps);
        out.batch_size = self.batch_size.unwrap_or(out.batch_size);
        out.lr = self.lr.unwrap_or(out.lr);
        out.fraction_fit = self.fraction_fit.unwrap_or(out.fraction_fit);
        out.rollout_episodes = self.rollout_episodes.unwrap_or(out.rollout_episodes);
        out.client_rollout_episodes = self.client_rollout_episodes.unwrap_or(out.client_rollout_episodes);
        out.validate()?;
        Ok(out)
    }

    /// The settable keys, as the API spells them.
    fn keys() -> Vec<String> {
        let all = json!(Settings::of(&RunConfig::default()));
        all.as_object().expect("settings serialize to an object").keys().cloned().collect()
    }

    /// Adds a later change on top of this one: its settings win.
    pub fn merge(&mut self, later: Settings) {
        self.local_steps = later.local_steps.or(self.local_steps);
        self.batch_size = later.batch_size.or(self.batch_size);
        self.lr = later.lr.or(self.lr);
        self.fraction_fit = later.fraction_fit.or(self.fraction_fit);
        self.rollout_episodes = later.rollout_episodes.or(self.rollout_episodes);
        self.client_rollout_episodes = later.client_rollout_episodes.or(self.client_rollout_episodes);
    }
}

/// Whether rounds may start, as the operator decided.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum RunState {
    /// `auto-start = false` and the operator has not pressed Start yet.
    WaitingForStart,
    Running,
    /// The current round finishes; no new one starts.
    Paused,
    /// The current round finishes, then the run ends.
    Stopping,
    Finished,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ControlAction {
    Start,
    Pause,
    Resume,
    Stop,
}

impl ControlAction {
    fn name(self) -> &'static str {
        match self {
            Self::Start => "start",
            Self::Pause => "pause",
            Self::Resume => "resume",
            Self::Stop => "stop",
        }
    }
}

impl RunState {
    /// The state `action` leads to, or why it cannot be taken now. Start and Resume both let rounds run.
    pub fn after(self, action: ControlAction) -> Result<RunState, String> {
        use ControlAction::{Pause, Resume, Start, Stop};
        match (self, action) {
            (Self::Finished, _) => Err(format!("the run is finished; there is nothing to {}", action.name())),
            (Self::Stopping, Stop) => Ok(Self::Stopping),
            (Self::Stopping, _) => {
                Err(format!("the run is stopping after the current round; it cannot {}", action.name()))
            }
            (_, Stop) => Ok(Self::Stopping),
            (_, Start | Resume) => Ok(Self::Running),
            (_, Pause) => Ok(Self::Paused),
        }
    }
}

/// What a client is doing, as far as the server can tell from its messages.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum ClientState {
    Idle,
    Training,
    Uploading,
    /// Held-out evaluation or sim rollouts of the round's starting model (both come before training).
    Evaluating,
    Left,
}

/// One row of the console's client table.
#[derive(Debug, Clone, Serialize)]
pub struct ClientRow {
    pub id: u64,
    pub name: String,
    pub backend: String,
    pub state: ClientState,
    /// Unix milliseconds of the client's last message the coordinator saw.
    pub last_seen_ms: u64,
    /// Updates that went into an aggregated round.
    pub updates_accepted: u64,
    /// Bytes since the client joined, as its last metrics reported them.
    pub bytes_up: u64,
    pub bytes_down: u64,
}

/// One attempt at a round, on the console's timeline.
#[derive(Debug, Clone, Serialize)]
pub struct RoundAttempt {
    pub round: u64,
    pub attempt: u64,
    pub outcome: AttemptOutcome,
    pub started_ms: u64,
    pub closed_ms: Option<u64>,
    /// Client ids the round's tasks went to.
    pub sampled: Vec<u64>,
    /// Updates that arrived in time; set when the attempt closes.
    pub updates: Option<u32>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum AttemptOutcome {
    Running,
    /// Aggregated, evaluated and persisted.
    Closed,
    /// Too few updates: the round is tried again.
    Retried,
}

/// Shared by the coordinator and the console's HTTP handlers; cheap to clone.
#[derive(Clone)]
pub struct ConsoleHub(Arc<Hub>);

struct Hub {
    operator_token: String,
    events: broadcast::Sender<Value>,
    run_state: watch::Sender<RunState>,
    status: watch::Receiver<RunStatus>,
    live: Mutex<Live>,
    /// Connections the listener closed at once because `max-connections` were open.
    refused_connections: AtomicU64,
}

struct Live {
    /// The configuration the next round runs with: the run's, with the operator's settings applied.
    config: RunConfig,
    /// Settings changed since a round last took them up.
    pending: Settings,
    /// The round whose tasks are out.
    current_round: Option<u64>,
    /// Every client connected now and the last [`LEFT_CLIENTS_KEPT`] that left (marked so), by id.
    clients: BTreeMap<u64, ClientRow>,
    timeline: Vec<RoundAttempt>,
}

impl ConsoleHub {
    /// A hub for a run configured by `config`; `operator_token` is what the console API wants (never empty).
    pub fn new(operator_token: String, config: &RunConfig, status: watch::Receiver<RunStatus>) -> Self {
        let initial = if config.auto_start { RunState::Running } else { RunState::WaitingForStart };
        Self(Arc::new(Hub {
            operator_token,
            events: broadcast::channel(EVENT_BACKLOG).0,
            run_state: watch::channel(initial).0,
            status,
            refused_connections: AtomicU64::new(0),
            live: Mutex::new(Live {
                config: config.clone(),
                pending: Settings::default(),
                current_round: None,
                clients: BTreeMap::new(),
                timeline: Vec::new(),
            }),
        }))
    }

    /// Sends `event` (a JSON object with a `"type"`) to every open console. Events with live state behind them
    /// (clients, rounds, settings) go through the hub's other methods; this is for the rest, e.g.
    /// `{"type": "video_stored", "round": 3, "client_id": 7, "file": "episode_0.webm"}`.
    pub fn publish(&self, event: Value) {
        // No console open is fine: nobody misses anything the snapshot does not have.
        self.0.events.send(event).ok();
    }

    pub fn subscribe(&self) -> broadcast::Receiver<Value> {
        self.0.events.subscribe()
    }

    /// The operator's run state, for the coordinator to wait on.
    pub fn run_state(&self) -> watch::Receiver<RunState> {
        self.0.run_state.subscribe()
    }

    /// Applies the operator's `action`; the coordinator sees the new state at its next round boundary.
    pub fn control(&self, action: ControlAction) -> Result<RunState, String> {
        let mut outcome = Err(String::new());
        self.0.run_state.send_if_modified(|state| {
            outcome = state.after(action);
            match outcome {
                Ok(next) if next != *state => {
                    *state = next;
                    true
                }
                _ => false,
            }
        });
        let state = outcome?;
        tracing::info!(?action, ?state, "operator control");
        self.publish(json!({ "type": "run_state", "state": state, "action": action }));
        Ok(state)
    }

    /// Marks the run over (the coordinator's last act).
    pub fn finish(&self) {
        self.0.run_state.send_replace(RunState::Finished);
        self.publish(json!({ "type": "run_state", "state": RunState::Finished }));
    }

    /// Validates the operator's `change` against the run's configuration and queues it for the next round.
    /// Returns every setting as the next round will have it.
    pub fn change_settings(&self, change: Settings) -> Result<Settings, ConfigError> {
        let mut live = self.live();
        live.config = change.applied_to(&live.config)?;
        let settings = Settings::of(&live.config);
        tracing::info!(changed = %json!(change), "operator changed settings; they apply from the next round's tasks on");
        live.pending.merge(change.clone());
        self.publish(json!({ "type": "settings_changed", "changed": change, "settings": settings }));
        Ok(settings)
    }

    /// The configuration with every pending change applied, and those changes; `None` when there are none.
    pub fn take_settings(&self) -> Option<(RunConfig, Settings)> {
        let mut live = self.live();
        let pending = std::mem::take(&mut live.pending);
        (!pending.is_empty()).then(|| (live.config.clone(), pending))
    }

    pub fn client_joined(&self, id: u64, name: &str, backend: &str) {
        let row = ClientRow {
            id,
            name: name.to_owned(),
            backend: backend.to_owned(),
            state: ClientState::Idle,
            last_seen_ms: unix_ms(),
            updates_accepted: 0,
            bytes_up: 0,
            bytes_down: 0,
        };
        self.live().clients.insert(id, row.clone());
        self.publish(json!({ "type": "client_joined", "client": row }));
    }

    /// Applies `change` to client `id`'s row (a client that never joined is ignored) and marks it seen now.
    pub fn client_changed(&self, id: u64, change: impl FnOnce(&mut ClientRow)) {
        let row = {
            let mut live = self.live();
            let Some(row) = live.clients.get_mut(&id) else { return };
            change(row);
            row.last_seen_ms = unix_ms();
            row.clone()
        };
        let kind = if row.state == ClientState::Left { "client_left" } else { "client_state" };
        self.publish(json!({ "type": kind, "client": row }));
    }

    pub fn client_left(&self, id: u64) {
        self.client_changed(id, |row| row.state = ClientState::Left);
        let mut live = self.live();
        let left: Vec<u64> = live.clients.values().filter(|c| c.state == ClientState::Left).map(|c| c.id).collect();
        for id in &left[..left.len().saturating_sub(LEFT_CLIENTS_KEPT)] {
            live.clients.remove(id);
        }
    }

    pub fn count_refused_connection(&self) {
        self.0.refused_connections.fetch_add(1, Ordering::Relaxed);
    }

    pub fn round_started(&self, round: u64, attempt: u64, sampled: Vec<u64>) {
        let entry = RoundAttempt {
            round,
            attempt,
            outcome: AttemptOutcome::Running,
            started_ms: unix_ms(),
            closed_ms: None,
            sampled,
            updates: None,
        };
        {
            let mut live = self.live();
            live.current_round = Some(round);
            live.timeline.push(entry.clone());
        }
        self.publish(json!({ "type": "round_started", "attempt": entry }));
    }

    /// Closes an attempt: aggregated when its metrics line (`metrics`, as persisted) is given, retried otherwise.
    /// Round 0, the initial evaluation, closes without having started.
    pub fn round_closed(&self, round: u64, attempt: u64, updates: u32, metrics: Option<&Value>) {
        let outcome = if metrics.is_some() { AttemptOutcome::Closed } else { AttemptOutcome::Retried };
        {
            let mut live = self.live();
            live.current_round = None;
            if let Some(entry) = live.timeline.iter_mut().rev().find(|e| (e.round, e.attempt) == (round, attempt)) {
                entry.outcome = outcome;
                entry.closed_ms = Some(unix_ms());
                entry.updates = Some(updates);
            }
        }
        self.publish(json!({
            "type": "round_closed",
            "round": round,
            "attempt": attempt,
            "outcome": outcome,
            "updates": updates,
            "metrics": metrics,
        }));
    }

    /// Everything the hub knows, as the snapshot reports it.
    fn live_json(&self) -> Value {
        let status = self.0.status.borrow().clone();
        let state = *self.0.run_state.borrow();
        let live = self.live();
        json!({
            "run": {
                "state": state,
                "current_round": live.current_round,
                "completed_rounds": status.completed_rounds,
                "num_server_rounds": live.config.num_server_rounds,
                "connected": status.connected,
                "min_clients": live.config.min_clients,
                "retried_rounds": status.retried_rounds,
                "skipped_rounds": status.skipped_rounds,
                "corrected_claims": status.corrected_claims,
                "refused_connections": self.0.refused_connections.load(Ordering::Relaxed),
                "rejections": status.rejections,
            },
            "settings": Settings::of(&live.config),
            "pending_settings": live.pending,
            "clients": live.clients.values().collect::<Vec<_>>(),
            "timeline": live.timeline,
        })
    }

    fn live(&self) -> MutexGuard<'_, Live> {
        self.0.live.lock().expect("console state lock")
    }

    fn authorize(&self, presented: Option<&str>) -> Result<(), ConsoleError> {
        match presented {
            None => Err(ConsoleError::MissingToken),
            Some(token) if same_secret(token, &self.0.operator_token) => Ok(()),
            Some(_) => Err(ConsoleError::WrongToken),
        }
    }
}

/// A fresh token of 128 random bits from the OS, as 32 hex digits.
pub fn random_token() -> String {
    let bytes: [u8; 16] = StdRng::from_os_rng().random();
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// Compares in time independent of where the strings differ, so the token cannot be guessed byte by byte.
pub fn same_secret(a: &str, b: &str) -> bool {
    a.len() == b.len() && a.bytes().zip(b.bytes()).fold(0u8, |diff, (x, y)| diff | (x ^ y)) == 0
}

fn unix_ms() -> u64 {
    SystemTime::now().duration_since(UNIX_EPOCH).map_or(0, |d| d.as_millis() as u64)
}

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
    let bearer =
        request.headers().get(AUTHORIZATION).and_then(|v| v.to_str().ok()).and_then(|v| v.strip_prefix("Bearer "));
    match console.authorize(bearer.or(query.token.as_deref())) {
        Ok(()) => next.run(request).await,
        Err(e) => e.into_response(),
    }
}

/// Live state, every metrics line so far, the video gallery and the rounds with a downloadable checkpoint.
async fn snapshot(State(state): State<AppState>) -> Result<Json<Value>, ConsoleError> {
    let run_dir = state.run_dir.clone();
    let (metrics, gallery, checkpoints) = tokio::task::spawn_blocking(move || {
        let read = || -> std::io::Result<_> {
            Ok((metrics_lines(run_dir.path())?, gallery(run_dir.path())?, checkpoint_rounds(run_dir.path())?))
        };
        read().map_err(|e| ConsoleError::RunDir(format!("{}: {e}", run_dir.path().display())))
    })
    .await
    .map_err(|e| ConsoleError::RunDir(e.to_string()))??;
    let mut snapshot = state.console.live_json();
    snapshot["metrics"] = json!(metrics);
    snapshot["gallery"] = json!(gallery);
    snapshot["checkpoints"] = json!(checkpoints);
    Ok(Json(snapshot))
}

/// Every complete line of `metrics.jsonl`, parsed (a line being appended right now is left for the next read).
fn metrics_lines(run_dir: &Path) -> std::io::Result<Vec<Value>> {
    let text = match std::fs::read_to_string(run_dir.join(METRICS_FILE)) {
        Ok(text) => text,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
        Err(e) => return Err(e),
    };
    let complete = &text[..text.rfind('\n').map_or(0, |i| i + 1)];
    complete
        .lines()
        .enumerate()
        .map(|(i, line)| {
            serde_json::from_str(line).map_err(|e| {
                std::io::Error::new(std::io::ErrorKind::InvalidData, format!("{METRICS_FILE} line {}: {e}", i + 1))
            })
        })
        .collect()
}

/// Videos and results of one round: the global model's sim rollouts and each client's.
#[derive(Debug, Default, Serialize)]
struct RoundGallery {
    round: u64,
    global: Option<VideoSet>,
    clients: Vec<ClientVideos>,
}

#[derive(Debug, Serialize)]
struct ClientVideos {
    client_id: u64,
    #[serde(flatten)]
    set: VideoSet,
}

#[derive(Debug, Serialize)]
struct VideoSet {
    /// Console URLs (`/console/api/file/...`; the page adds its token).
    videos: Vec<String>,
    /// The directory's results.json, when there is one that parses.
    results: Option<Value>,
}

/// `global_model/round_N/rollouts/` and `evaluate/round_N/client_K/`, by round; rounds without either are left out.
fn gallery(run_dir: &Path) -> std::io::Result<Vec<RoundGallery>> {
    let mut rounds: BTreeMap<u64, RoundGallery> = BTreeMap::new();
    for (round, dir) in numbered_dirs(&run_dir.join(MODELS_DIR), "round_")? {
        if let Some(set) = video_set(run_dir, &dir.join(ROLLOUTS_DIR))? {
            rounds.entry(round).or_insert_with(|| RoundGallery { round, ..RoundGallery::default() }).global = Some(set);
        }
    }
    for (round, round_dir) in numbered_dirs(&run_dir.join(EVALUATE_DIR), "round_")? {
        for (client_id, dir) in numbered_dirs(&round_dir, "client_")? {
            if let Some(set) = video_set(run_dir, &dir)? {
                let entry = rounds.entry(round).or_insert_with(|| RoundGallery { round, ..RoundGallery::default() });
                entry.clients.push(ClientVideos { client_id, set });
            }
        }
    }
    Ok(rounds.into_values().collect())
}

/// Rounds whose LeRobot policy directory can be downloaded.
fn checkpoint_rounds(run_dir: &Path) -> std::io::Result<Vec<u64>> {
    Ok(numbered_dirs(&run_dir.join(MODELS_DIR), "round_")?
        .into_iter()
        .filter(|(_, dir)| dir.join(POLICY_DIR).is_dir())
        .map(|(round, _)| round)
        .collect())
}

/// Subdirectories named `<prefix><number>`, by number (none when `dir` does not exist; `round_3.tmp`, a round
/// being written, is not one).
fn numbered_dirs(dir: &Path, prefix: &str) -> std::io::Result<Vec<(u64, PathBuf)>> {
    let entries = match std::fs::read_dir(dir) {
        Ok(entries) => entries,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
        Err(e) => return Err(e),
    };
    let mut out = Vec::new();
    for entry in entries {
        let entry = entry?;
        let number = entry.file_name().to_str().and_then(|n| n.strip_prefix(prefix)?.parse::<u64>().ok());
        if let Some(number) = number.filter(|_| entry.path().is_dir()) {
            out.push((number, entry.path()));
        }
    }
    out.sort();
    Ok(out)
}

/// The videos (`.mp4`, `.webm`) and results.json in `dir`, if it holds either.
fn video_set(run_dir: &Path, dir: &Path) -> std::io::Result<Option<VideoSet>> {
    let entries = match std::fs::read_dir(dir) {
        Ok(entries) => entries,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(e),
    };
    let mut names = Vec::new();
    for entry in entries {
        let name = entry?.file_name().to_string_lossy().into_owned();
        if name.ends_with(".mp4") || name.ends_with(".webm") {
            names.push(name);
        }
    }
    // episode_2 before episode_10.
    names.sort_by(|a, b| (a.len(), a).cmp(&(b.len(), b)));
    let results = match std::fs::read(dir.join(RESULTS_FILE)) {
        Ok(bytes) => serde_json::from_slice(&bytes).ok(),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => None,
        Err(e) => return Err(e),
    };
    if names.is_empty() && results.is_none() {
        return Ok(None);
    }
    let relative = dir.strip_prefix(run_dir).expect("gallery directories are inside the run directory");
    let videos = names.iter().map(|name| file_url(&relative.join(name))).collect();
    Ok(Some(VideoSet { videos, results }))
}

/// Characters a URL path segment may not carry as they are.
const SEGMENT: &AsciiSet = &NON_ALPHANUMERIC.remove(b'-').remove(b'.').remove(b'_').remove(b'~');

/// The console URL of a file in the run directory.
fn file_url(relative: &Path) -> String {
    let segments: Vec<String> = relative
        .components()
        .map(|c| utf8_percent_encode(&c.as_os_str().to_string_lossy(), SEGMENT).to_string())
        .collect();
    format!("/console/api/file/{}", segments.join("/"))
}

/// Server-sent events: every event the hub publishes, as a JSON `data:` line, until the server shuts down. A
/// console that fell behind gets `{"type": "resync"}` and should re-read the snapshot.
async fn events(State(state): State<AppState>) -> Sse<impl Stream<Item = Result<SseEvent, Infallible>>> {
    let stream = futures_util::stream::unfold(state.console.subscribe(), |mut events| async move {
        let event = match events.recv().await {
            Ok(event) => event,
            Err(RecvError::Lagged(missed)) => json!({ "type": "resync", "missed": missed }),
            Err(RecvError::Closed) => return None,
        };
        Some((Ok(SseEvent::default().data(event.to_string())), events))
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
async fn control(State(state): State<AppState>, body: Bytes) -> Result<Json<Value>, ConsoleError> {
    let request: ControlRequest = parse_body(&body, "control request")?;
    let run_state = state.console.control(request.action).map_err(ConsoleError::Conflict)?;
    Ok(Json(json!({ "state": run_state })))
}

/// Any of the [`Settings`] keys; answers every setting as the next round will have it.
async fn change_settings(State(state): State<AppState>, body: Bytes) -> Result<Json<Value>, ConsoleError> {
    let change = parse_settings(&body)?;
    if change.is_empty() {
        return Err(ConsoleError::BadRequest {
            what: "settings",
            message: format!("none given; settable: {}", Settings::keys().join(", ")),
        });
    }
    let settings = state
        .console
        .change_settings(change)
        .map_err(|e| ConsoleError::BadRequest { what: "settings", message: e.to_string() })?;
    Ok(Json(json!({ "settings": settings })))
}

/// Round `round`'s LeRobot policy directory as a tar archive, streamed as it is written.
async fn checkpoint(State(state): State<AppState>, UrlPath(round): UrlPath<u64>) -> Result<Response, ConsoleError> {
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
    State(state): State<AppState>,
    UrlPath(path): UrlPath<String>,
    headers: HeaderMap,
) -> Result<Response, ConsoleError> {
    let full = state.run_dir.path().join(relative_path(&path)?);
    Ok(file_response(&full, &headers).await?)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn run_state_transitions() {
        use ControlAction::*;
        use RunState::*;
        assert_eq!(WaitingForStart.after(Start), Ok(Running));
        assert_eq!(Running.after(Pause), Ok(Paused));
        assert_eq!(Paused.after(Resume), Ok(Running));
        assert_eq!(Paused.after(Stop), Ok(Stopping));
        assert_eq!(Running.after(Resume), Ok(Running), "idempotent");
        assert_eq!(Stopping.after(Stop), Ok(Stopping));
        assert_eq!(
            Stopping.after(Resume).unwrap_err(),
            "the run is stopping after the current round; it cannot resume"
        );
        assert_eq!(Finished.after(Pause).unwrap_err(), "the run is finished; there is nothing to pause");
    }

    #[test]
    fn settings_apply_validate_and_merge() {
        let config = RunConfig::default();
        let mut change = Settings { local_steps: Some(7), ..Settings::default() };
        assert_eq!(change.applied_to(&config).unwrap().local_steps, 7);
        let err = Settings { fraction_fit: Some(1.5), ..Settings::default() }.applied_to(&config).unwrap_err();
        assert_eq!(err.to_string(), "invalid configuration: fraction-fit must be in (0, 1], got 1.5");
        change.merge(Settings { lr: Some(0.1), local_steps: Some(9), ..Settings::default() });
        assert_eq!(change, Settings { local_steps: Some(9), lr: Some(0.1), ..Settings::default() });
        let err = serde_json::from_str::<Settings>(r#"{"local_steps": 3}"#).unwrap_err().to_string();
        assert!(err.contains("unknown field `local_steps`") && err.contains("`local-steps`"), "{err}");
        let mut keys = Settings::keys();
        keys.sort();
        assert_eq!(
            keys,
            ["batch-size", "client-rollout-episodes", "fraction-fit", "local-steps", "lr", "rollout-episodes"]
        );
    }

    #[test]
    fn gallery_lists_rounds_in_order_with_urls() {
        let dir = tempfile::tempdir().unwrap();
        let run = dir.path();
        let rollouts = run.join("global_model/round_2/rollouts");
        std::fs::create_dir_all(&rollouts).unwrap();
        for name in ["episode_10.mp4", "episode_2.mp4"] {
            std::fs::write(rollouts.join(name), b"x").unwrap();
        }
        std::fs::write(rollouts.join(RESULTS_FILE), br#"{"success_rate": 0.5}"#).unwrap();
        std::fs::create_dir_all(run.join("global_model/round_3.tmp/rollouts")).unwrap();
        std::fs::create_dir_all(run.join("global_model/round_1/policy")).unwrap();
        let client = run.join("evaluate/round_2/client_7");
        std::fs::create_dir_all(&client).unwrap();
        std::fs::write(client.join("a b.webm"), b"x").unwrap();

        let rounds = gallery(run).unwrap();
        assert_eq!(rounds.len(), 1, "round 1 has no videos, round_3.tmp is not a round");
        let round = &rounds[0];
        assert_eq!(round.round, 2);
        let global = round.global.as_ref().unwrap();
        assert_eq!(
            global.videos,
            [
                "/console/api/file/global_model/round_2/rollouts/episode_2.mp4",
                "/console/api/file/global_model/round_2/rollouts/episode_10.mp4"
            ]
        );
        assert_eq!(global.results.as_ref().unwrap()["success_rate"], 0.5);
        assert_eq!(round.clients[0].client_id, 7);
        assert_eq!(round.clients[0].set.videos, ["/console/api/file/evaluate/round_2/client_7/a%20b.webm"]);
        assert_eq!(checkpoint_rounds(run).unwrap(), [1]);
    }
}
