//! Starting and stopping a server: the coordinator task and the HTTP/WebSocket listener over it, from the
//! [`ServerParts`] a workload supplies.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use axum::body::Bytes;
use fedvla_aggregator::control::Controls;
use fedvla_aggregator::coordinator::{Coordinator, CoordinatorError, PublishedModel, RunStatus};
use fedvla_aggregator::parts::ServerParts;
use fedvla_aggregator::registry::{Volunteers, read_allowed_keys};
use fedvla_aggregator::run_dir::{ModelExporter, RunDirError, TrainableSafetensors};
use fedvla_aggregator::sessions::{Sessions, random_token};
use fedvla_aggregator::upload_budget::UploadBudget;
use fedvla_federation::{TensorError, UpdateLimits};
use tokio::net::TcpListener;
use tokio::sync::{mpsc, watch};
use tokio::task::JoinHandle;
use tokio_util::sync::CancellationToken;
use tokio_util::task::TaskTracker;

use crate::app;
use crate::bounds::JoinLimiter;
use crate::console::ConsoleHub;
use crate::http::{self, HttpLimits};
use crate::state::{AppState, ConsoleState, SocketState, VolunteerState, WwwState};
use crate::tls::{self, TlsError};

/// Headroom over the exact update size before an update counts as oversized.
const UPDATE_HEADROOM_BYTES: u64 = 64 * 1024;

#[derive(Debug, thiserror::Error)]
pub enum StartError {
    #[error(transparent)]
    RunDir(#[from] RunDirError),
    #[error("the saved model does not match the workload's trainable tensors: {0}")]
    Spec(TensorError),
    #[error("listener: {0}")]
    Io(#[from] std::io::Error),
    #[error("TLS: {0}")]
    Tls(#[from] TlsError),
    #[error(
        "max-upload-memory-bytes ({budget}) cannot hold one update of the trainable tensors ({update} bytes): raise it"
    )]
    UploadBudget { budget: u64, update: u64 },
}

/// A running server.
pub struct ServerHandle {
    addr: SocketAddr,
    cancel: CancellationToken,
    status: watch::Receiver<RunStatus>,
    operator_token: String,
    coordinator: JoinHandle<Result<RunStatus, CoordinatorError>>,
    http: JoinHandle<std::io::Result<()>>,
    sockets: TaskTracker,
    /// The coordinator's blocking jobs (see `Coordinator::jobs`).
    jobs: TaskTracker,
}

/// Starts serving on `listener`; resumes after the last completed round if the run directory has one.
pub fn start(parts: ServerParts, listener: TcpListener) -> Result<ServerHandle, StartError> {
    let ServerParts { config, run_dir, initial, mut strategy, evaluator, exporters, volunteer } = parts;
    let tls = config.tls_files().map(|(cert, key)| tls::acceptor(cert, key)).transpose()?;
    let spec = Arc::new(initial.spec());
    let completed = run_dir.resume_point()?;
    let global = match completed {
        Some(round) => {
            let saved = run_dir.load_model(round)?;
            saved.validate(&spec).map_err(StartError::Spec)?;
            // The strategy goes on with what it carried out of that round.
            strategy.commit(run_dir.load_strategy_state(round)?);
            saved
        }
        None => initial,
    };
    let version = completed.unwrap_or(0);
    let bytes = global.to_safetensors().map_err(StartError::Spec)?;
    let (model_tx, model_rx) = watch::channel(Arc::new(PublishedModel::first(version, Bytes::from(bytes))));
    let (status_tx, status) = watch::channel(RunStatus { completed_rounds: version, ..RunStatus::default() });
    let (events_tx, events) = mpsc::channel(1024);
    let generated_token = config.operator_token.is_empty();
    let operator_token = if generated_token { random_token() } else { config.operator_token.clone() };
    let controls = Controls::new(&config);
    let console = ConsoleHub::new(operator_token.clone(), controls.clone(), status.clone());
    let cancel = CancellationToken::new();
    let encoding = config.encoding();
    let limits = UpdateLimits::for_spec(&spec, encoding, config.max_frame_bytes, UPDATE_HEADROOM_BYTES);
    let update = limits.max_payload_bytes - UPDATE_HEADROOM_BYTES;
    if config.max_upload_memory_bytes < update {
        return Err(StartError::UploadBudget { budget: config.max_upload_memory_bytes, update });
    }
    let uploads = UploadBudget::new(config.max_upload_memory_bytes);
    let http_limits = HttpLimits {
        max_connections: config.max_connections,
        header_read_timeout: Duration::from_millis(config.header_read_timeout_ms),
        idle_timeout: Duration::from_millis(config.idle_timeout_ms),
    };
    let sessions = Sessions::default();
    let auth_token: Option<Arc<str>> = config.auth_token().map(Arc::from);
    // A run that agrees its statistics by federated statistics has none until round 1 (or a resume reads them).
    let dataset_stats = volunteer.norm_stats.clone();
    let norm_stats = match run_dir.read_norm_stats()? {
        Some(agreed) => Some(agreed),
        None if config.federated_stats => None,
        None => dataset_stats.clone(),
    };
    let volunteers =
        Volunteers::new(volunteer, run_dir.clone(), config.max_volunteer_names, config.own_data_max_examples)?;
    let volunteers = Arc::new(match config.allowed_keys_file() {
        Some(path) => volunteers.with_allowed_keys(read_allowed_keys(path)?),
        None => volunteers,
    });
    let sockets = TaskTracker::new();
    let jobs = TaskTracker::new();
    let state = AppState {
        socket: SocketState {
            events: events_tx,
            cancel: cancel.clone(),
            spec,
            encoding,
            limits,
            keepalive: http_limits.keepalive(),
            auth_token: auth_token.clone(),
            volunteers: Arc::clone(&volunteers),
            model: model_rx.clone(),
            sessions: sessions.clone(),
            joins: JoinLimiter::new(config.joins_per_address_per_minute),
            messages_per_second: config.max_messages_per_second,
            uploads: uploads.clone(),
            upload_wait: Duration::from_millis(config.round_deadline_ms),
            sockets: sockets.clone(),
        },
        volunteers: VolunteerState {
            volunteers,
            sessions: sessions.clone(),
            model: model_rx,
            run_dir: run_dir.clone(),
            console: console.clone(),
            uploads,
            max_video_bytes: config.max_video_bytes,
        },
        console: ConsoleState { hub: console.clone(), run_dir: run_dir.clone(), cancel: cancel.clone() },
        www: WwwState { dir: Arc::new(PathBuf::from(&config.www_dir)) },
    };
    let mut all_exporters: Vec<Box<dyn ModelExporter>> = vec![Box::new(TrainableSafetensors)];
    all_exporters.extend(exporters);
    let coordinator = Coordinator {
        config,
        events,
        cancel: cancel.clone(),
        strategy: Arc::new(Mutex::new(strategy)),
        evaluator: Arc::new(Mutex::new(evaluator)),
        exporters: Arc::new(all_exporters),
        run_dir,
        global: Arc::new(global),
        completed,
        model_tx,
        status_tx,
        controls,
        observer: Arc::new(console.clone()),
        sessions,
        norm_stats,
        dataset_stats,
        jobs: jobs.clone(),
    };
    let addr = listener.local_addr()?;
    let coordinator = tokio::spawn(coordinator.run());
    let shutdown = cancel.clone();
    let scheme = if tls.is_some() { "https" } else { "http" };
    let http = tokio::spawn(http::serve(listener, app(state), http_limits, tls, console, shutdown));
    tracing::info!(%addr, scheme, "listening");
    if generated_token {
        tracing::info!("console: {scheme}://{addr}/console  token: {operator_token}");
    } else {
        tracing::info!("console: {scheme}://{addr}/console  (token: operator-token of the run configuration)");
    }
    Ok(ServerHandle { addr, cancel, status, operator_token, coordinator, http, sockets, jobs })
}

impl ServerHandle {
    pub fn addr(&self) -> SocketAddr {
        self.addr
    }

    /// What the console API wants: `operator-token`, or the one generated at start when that is empty.
    pub fn operator_token(&self) -> &str {
        &self.operator_token
    }

    pub fn status(&self) -> watch::Receiver<RunStatus> {
        self.status.clone()
    }

    /// A token that, when cancelled, stops the run and closes every socket.
    pub fn cancel_token(&self) -> CancellationToken {
        self.cancel.clone()
    }

    /// Waits for the run to finish (or be cancelled), then shuts down gracefully.
    pub async fn finish(self) -> Result<RunStatus, CoordinatorError> {
        let result = match self.coordinator.await {
            Ok(result) => result,
            Err(e) => std::panic::resume_unwind(e.into_panic()),
        };
        self.cancel.cancel();
        if let Ok(Err(e)) = self.http.await {
            tracing::warn!(error = %e, "http server error");
        }
        // The volunteers' sockets send what they were told last (`Finished`) and close before the process may end:
        // otherwise a volunteer could see its connection reset instead.
        self.sockets.close();
        if tokio::time::timeout(http::SHUTDOWN_GRACE, self.sockets.wait()).await.is_err() {
            tracing::info!("closing WebSockets still open after {:?}", http::SHUTDOWN_GRACE);
        }
        result
    }

    /// Stops abruptly, as a crash would: tasks aborted mid-round, sockets dropped. Returns once no blocking job
    /// of the coordinator's is left running (a crash would have stopped those too), so a server started next on the
    /// same run directory finds it as this one left it.
    pub async fn kill(self) {
        self.coordinator.abort();
        self.http.abort();
        self.cancel.cancel();
        self.jobs.close();
        self.jobs.wait().await;
    }
}
