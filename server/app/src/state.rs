//! What the routes share, split by the route groups that need it: the WebSocket ([`SocketState`]), the
//! volunteers' downloads and uploads ([`VolunteerState`]), the operator console ([`ConsoleState`]) and the pages
//! ([`WwwState`]). Each handler extracts only its own group's state; [`AppState`] holds them all for the router.

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use axum::extract::FromRef;
use fedvla_aggregator::coordinator::{Event, PublishedModel};
use fedvla_aggregator::registry::Volunteers;
use fedvla_aggregator::run_dir::RunDir;
use fedvla_aggregator::sessions::Sessions;
use fedvla_aggregator::upload_budget::UploadBudget;
use fedvla_federation::{TensorSpec, UpdateEncoding, UpdateLimits};
use tokio::sync::{mpsc, watch};
use tokio_util::sync::CancellationToken;
use tokio_util::task::TaskTracker;

use crate::bounds::JoinLimiter;
use crate::console::ConsoleHub;

#[derive(Clone)]
pub struct AppState {
    pub socket: SocketState,
    pub volunteers: VolunteerState,
    pub console: ConsoleState,
    pub www: WwwState,
}

/// The federation WebSocket's: channels to the coordinator and what a join and an update are checked against.
#[derive(Clone)]
pub struct SocketState {
    pub events: mpsc::Sender<Event>,
    pub cancel: CancellationToken,
    pub spec: Arc<TensorSpec>,
    /// The run's update encoding: updates in another are refused.
    pub encoding: UpdateEncoding,
    pub limits: UpdateLimits,
    /// How often an idle WebSocket is pinged (well within the listener's idle timeout).
    pub keepalive: Duration,
    /// Token clients must present when they identify; `None` means a public run.
    pub auth_token: Option<Arc<str>>,
    /// Who trains on which shard.
    pub volunteers: Arc<Volunteers>,
    /// The global model, whose version an admission's setup names.
    pub model: watch::Receiver<Arc<PublishedModel>>,
    /// Download and upload sessions, opened by each admission.
    pub sessions: Sessions,
    /// Joins per address per minute.
    pub joins: JoinLimiter,
    /// Messages each connection may send a second (`max-messages-per-second`).
    pub messages_per_second: u32,
    /// Memory for updates on their way in, shared with the videos'.
    pub uploads: UploadBudget,
    /// How long an update waits for room in the budget before it is refused: a round's deadline, past which it
    /// could not count anyway.
    pub upload_wait: Duration,
    /// The WebSocket handlers, which run on past their HTTP connection (hyper hands the socket over at the
    /// upgrade): a shutdown waits for them to send what the coordinator queued (`Finished`) and close.
    pub sockets: TaskTracker,
}

/// The volunteers' HTTP routes': shards, frozen weights, the tokenizer, the global model, SCAFFOLD corrections,
/// rollout videos; each answers only a request presenting an admitted connection's session.
#[derive(Clone)]
pub struct VolunteerState {
    pub volunteers: Arc<Volunteers>,
    pub sessions: Sessions,
    pub model: watch::Receiver<Arc<PublishedModel>>,
    /// Where uploads are filed.
    pub run_dir: RunDir,
    /// Told of every video stored, and counts the uploads refused.
    pub console: ConsoleHub,
    /// Memory for videos on their way in, shared with the updates'.
    pub uploads: UploadBudget,
    /// Largest rollout video accepted (`max-video-bytes`).
    pub max_video_bytes: u64,
}

/// The operator console's API's.
#[derive(Clone)]
pub struct ConsoleState {
    pub hub: ConsoleHub,
    pub run_dir: RunDir,
    /// Ends the event streams at shutdown.
    pub cancel: CancellationToken,
}

/// The pages served to browsers (`www-dir`).
#[derive(Clone)]
pub struct WwwState {
    pub dir: Arc<PathBuf>,
}

impl FromRef<AppState> for SocketState {
    fn from_ref(state: &AppState) -> Self {
        state.socket.clone()
    }
}

impl FromRef<AppState> for VolunteerState {
    fn from_ref(state: &AppState) -> Self {
        state.volunteers.clone()
    }
}

impl FromRef<AppState> for ConsoleState {
    fn from_ref(state: &AppState) -> Self {
        state.console.clone()
    }
}

impl FromRef<AppState> for WwwState {
    fn from_ref(state: &AppState) -> Self {
        state.www.clone()
    }
}

impl FromRef<AppState> for ConsoleHub {
    fn from_ref(state: &AppState) -> Self {
        state.console.hub.clone()
    }
}
