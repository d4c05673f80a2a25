//! The console's live state: [`ConsoleHub`] watches the run (it is the coordinator's [`RunObserver`]) and keeps
//! the client table and round timeline from what the coordinator reports, sends every change to the open
//! consoles as a [`ConsoleEvent`], and passes the operator's decisions to the run's [`Controls`].

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{SystemTime, UNIX_EPOCH};

use fedvla_aggregator::config::ConfigError;
use fedvla_aggregator::control::{ControlAction, Controls, RunState, Settings};
use fedvla_aggregator::coordinator::RunStatus;
use fedvla_aggregator::events::{ClientState, RunEvent, RunObserver};
use fedvla_aggregator::sessions::same_secret;
use fedvla_federation::ErrorCode;
use serde::Serialize;
use tokio::sync::{broadcast, watch};

use super::events::{AttemptOutcome, ClientRow, ConsoleEvent, RoundAttempt};

/// Events a slow console may fall behind by before it is told to re-read the snapshot.
const EVENT_BACKLOG: usize = 1024;
/// Clients that left stay in the table for the operator to see, the most recent this many of them.
const LEFT_CLIENTS_KEPT: usize = 256;

/// Shared by the coordinator (as its observer) and the console's HTTP handlers; cheap to clone.
#[derive(Clone)]
pub struct ConsoleHub(Arc<Hub>);

struct Hub {
    operator_token: String,
    events: broadcast::Sender<ConsoleEvent>,
    controls: Controls,
    status: watch::Receiver<RunStatus>,
    live: Mutex<Live>,
    /// Connections the listener closed at once because `max-connections` were open.
    refused_connections: AtomicU64,
    /// Refusals of HTTP requests (rollout videos) by code; the WebSocket's are counted by the coordinator.
    http_refusals: Mutex<BTreeMap<ErrorCode, u64>>,
}

#[derive(Default)]
struct Live {
    /// The round whose tasks are out.
    current_round: Option<u64>,
    /// Every client connected now and the last [`LEFT_CLIENTS_KEPT`] that left (marked so), by id.
    clients: BTreeMap<u64, ClientRow>,
    timeline: Vec<RoundAttempt>,
}

/// What the console's snapshot reports of the run, beside the run directory's metrics and gallery.
#[derive(Debug, Clone, Serialize)]
pub struct LiveSnapshot {
    pub run: RunSummary,
    /// Every setting as the next round will have it, and those changed since a round last took them up.
    pub settings: Settings,
    pub pending_settings: Settings,
    pub clients: Vec<ClientRow>,
    pub timeline: Vec<RoundAttempt>,
}

#[derive(Debug, Clone, Serialize)]
pub struct RunSummary {
    pub state: RunState,
    pub current_round: Option<u64>,
    pub completed_rounds: u64,
    pub num_server_rounds: u64,
    pub connected: usize,
    pub min_clients: usize,
    pub retried_rounds: u64,
    pub skipped_rounds: u64,
    pub corrected_claims: u64,
    pub refused_connections: u64,
    /// Refused client inputs by code, the WebSocket's and the HTTP uploads' together.
    pub rejections: BTreeMap<String, u64>,
}

impl ConsoleHub {
    /// A hub for a run operated through `controls`; `operator_token` is what the console API wants (never empty).
    pub fn new(operator_token: String, controls: Controls, status: watch::Receiver<RunStatus>) -> Self {
        Self(Arc::new(Hub {
            operator_token,
            events: broadcast::channel(EVENT_BACKLOG).0,
            controls,
            status,
            live: Mutex::new(Live::default()),
            refused_connections: AtomicU64::new(0),
            http_refusals: Mutex::default(),
        }))
    }

    /// Sends `event` to every open console (none open is fine: nobody misses what the snapshot has).
    pub fn publish(&self, event: ConsoleEvent) {
        self.0.events.send(event).ok();
    }

    pub fn subscribe(&self) -> broadcast::Receiver<ConsoleEvent> {
        self.0.events.subscribe()
    }

    /// Applies the operator's `action` to the run's controls and tells the consoles.
    pub fn control(&self, action: ControlAction) -> Result<RunState, String> {
        let state = self.0.controls.control(action)?;
        self.publish(ConsoleEvent::RunState { state, action: Some(action) });
        Ok(state)
    }

    /// Queues the operator's settings for the next round and tells the consoles; returns every setting as the
    /// next round will have it.
    pub fn change_settings(&self, change: Settings) -> Result<Settings, ConfigError> {
        let settings = self.0.controls.change_settings(change.clone())?;
        self.publish(ConsoleEvent::SettingsChanged { changed: change, settings: settings.clone() });
        Ok(settings)
    }

    pub fn count_refused_connection(&self) {
        self.0.refused_connections.fetch_add(1, Ordering::Relaxed);
    }

    /// Counts an HTTP request refused for `code`; the snapshot reports it among the rejections.
    pub fn count_refusal(&self, code: ErrorCode) {
        *self.0.http_refusals.lock().expect("refusal counts lock").entry(code).or_default() += 1;
    }

    /// Everything the hub knows, as the snapshot reports it.
    pub fn live_snapshot(&self) -> LiveSnapshot {
        let status = self.0.status.borrow().clone();
        let (config, pending_settings) = self.0.controls.next_round();
        let mut rejections = status.rejections.clone();
        for (code, n) in self.0.http_refusals.lock().expect("refusal counts lock").iter() {
            *rejections.entry(*code).or_default() += n;
        }
        let live = self.live();
        LiveSnapshot {
            run: RunSummary {
                state: self.0.controls.state(),
                current_round: live.current_round,
                completed_rounds: status.completed_rounds,
                num_server_rounds: config.num_server_rounds,
                connected: status.connected,
                min_clients: config.min_clients,
                retried_rounds: status.retried_rounds,
                skipped_rounds: status.skipped_rounds,
                corrected_claims: status.corrected_claims,
                refused_connections: self.0.refused_connections.load(Ordering::Relaxed),
                rejections: rejections.iter().map(|(c, n)| (c.as_str().to_owned(), *n)).collect(),
            },
            settings: Settings::of(&config),
            pending_settings,
            clients: live.clients.values().cloned().collect(),
            timeline: live.timeline.clone(),
        }
    }

    /// Applies `change` to client `id`'s row (a client that never joined is ignored), marks it seen now and tells
    /// the consoles.
    fn client_changed(&self, id: u64, change: impl FnOnce(&mut ClientRow)) {
        let row = {
            let mut live = self.live();
            let Some(row) = live.clients.get_mut(&id) else { return };
            change(row);
            row.last_seen_ms = unix_ms();
            row.clone()
        };
        let event = match row.state {
            ClientState::Left => ConsoleEvent::ClientLeft { client: row },
            _ => ConsoleEvent::ClientState { client: row },
        };
        self.publish(event);
    }

    fn live(&self) -> MutexGuard<'_, Live> {
        self.0.live.lock().expect("console state lock")
    }

    /// Whether `token` is the operator's.
    pub fn is_operator(&self, token: &str) -> bool {
        same_secret(token, &self.0.operator_token)
    }
}

impl RunObserver for ConsoleHub {
    fn observe(&self, event: RunEvent) {
        match event {
            RunEvent::ClientJoined { id, name, backend, data } => {
                let row = ClientRow {
                    id,
                    name,
                    backend,
                    data,
                    state: ClientState::Idle,
                    last_seen_ms: unix_ms(),
                    updates_accepted: 0,
                    bytes_up: 0,
                    bytes_down: 0,
                };
                self.live().clients.insert(id, row.clone());
                self.publish(ConsoleEvent::ClientJoined { client: row });
            }
            RunEvent::ClientState { id, state } => self.client_changed(id, |row| row.state = state),
            RunEvent::ClientBytes { id, up, down } => {
                self.client_changed(id, |row| (row.bytes_up, row.bytes_down) = (up, down));
            }
            RunEvent::UpdateAccepted { id } => self.client_changed(id, |row| row.updates_accepted += 1),
            RunEvent::ClientLeft { id } => {
                self.client_changed(id, |row| row.state = ClientState::Left);
                let mut live = self.live();
                let left: Vec<u64> =
                    live.clients.values().filter(|c| c.state == ClientState::Left).map(|c| c.id).collect();
                for id in &left[..left.len().saturating_sub(LEFT_CLIENTS_KEPT)] {
                    live.clients.remove(id);
                }
            }
            RunEvent::RoundStarted { round, attempt, sampled } => {
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
                self.publish(ConsoleEvent::RoundStarted { attempt: entry });
            }
            RunEvent::RoundClosed { round, attempt, updates, line } => {
                let outcome = if line.is_some() { AttemptOutcome::Closed } else { AttemptOutcome::Retried };
                {
                    let mut live = self.live();
                    live.current_round = None;
                    let entry = live.timeline.iter_mut().rev().find(|e| (e.round, e.attempt) == (round, attempt));
                    if let Some(entry) = entry {
                        entry.outcome = outcome;
                        entry.closed_ms = Some(unix_ms());
                        entry.updates = Some(updates);
                    }
                }
                self.publish(ConsoleEvent::RoundClosed { round, attempt, outcome, updates, metrics: line });
            }
            RunEvent::Finished => self.publish(ConsoleEvent::RunState { state: RunState::Finished, action: None }),
        }
    }
}

fn unix_ms() -> u64 {
    SystemTime::now().duration_since(UNIX_EPOCH).map_or(0, |d| d.as_millis() as u64)
}
