//! What the console's server-sent events carry, one JSON object per event with its `type` (www/console.js
//! switches on `type` and reads `client`, `state`, `attempt`, `metrics` by these names).

use fedvla_aggregator::control::{ControlAction, RunState, Settings};
use fedvla_aggregator::records::MetricsLine;
use serde::Serialize;

use super::{AttemptOutcome, ClientRow, RoundAttempt};

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
