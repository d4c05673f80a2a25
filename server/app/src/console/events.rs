//! What the console's server-sent events carry, one JSON object per event with its `type` (www/console.js
//! switches on `type` and reads `client`, `state`, `attempt`, `metrics` by these names).

use fedvla_aggregator::control::{ControlAction, RunState, Settings};
use fedvla_aggregator::events::ClientState;
use fedvla_aggregator::records::{DataSource, MetricsLine};
use serde::Serialize;

#[derive(Debug, Clone, Serialize)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum ConsoleEvent {
    ClientJoined {
        client: ClientRow,
    },
    ClientState {
        client: ClientRow,
    },
    ClientLeft {
        client: ClientRow,
    },
    RoundStarted {
        attempt: RoundAttempt,
    },
    /// An attempt closed: with its metrics line as persisted when aggregated or skipped, without when retried.
    RoundClosed {
        round: u64,
        attempt: u64,
        outcome: AttemptOutcome,
        updates: u32,
        metrics: Option<Box<MetricsLine>>,
    },
    /// The operator's action (none when the run finished by itself).
    RunState {
        state: RunState,
        action: Option<ControlAction>,
    },
    SettingsChanged {
        changed: Settings,
        settings: Settings,
    },
    VideoStored {
        round: u64,
        client_id: u64,
        file: String,
    },
    /// This console fell `missed` events behind: it should read the snapshot again.
    Resync {
        missed: u64,
    },
}

/// One row of the console's client table.
#[derive(Debug, Clone, Serialize)]
pub struct ClientRow {
    pub id: u64,
    pub name: String,
    pub backend: String,
    /// What it trains on: a server shard (examples the server counted) or its own dataset (examples claimed).
    pub data: Option<DataSource>,
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
