//! What the coordinator reports as a run goes on ([`RunEvent`]), to whoever watches it through a
//! [`RunObserver`]: the operator console keeps its client table and round timeline from these. The coordinator
//! never waits on an observer.

use serde::Serialize;

use crate::records::{DataSource, MetricsLine};

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

#[derive(Debug, Clone, PartialEq)]
pub enum RunEvent {
    ClientJoined {
        id: u64,
        name: String,
        backend: String,
        data: Option<DataSource>,
    },
    ClientState {
        id: u64,
        state: ClientState,
    },
    /// Bytes the client has sent and received since it joined, as its last metrics said.
    ClientBytes {
        id: u64,
        up: u64,
        down: u64,
    },
    /// One of the client's updates went into an aggregated round.
    UpdateAccepted {
        id: u64,
    },
    ClientLeft {
        id: u64,
    },
    /// An attempt at a round sent its tasks to `sampled`.
    RoundStarted {
        round: u64,
        attempt: u64,
        sampled: Vec<u64>,
    },
    /// An attempt closed: aggregated (or skipped) with its metrics line written, or retried (no line). Round 0, the
    /// initial evaluation, closes without having started.
    RoundClosed {
        round: u64,
        attempt: u64,
        updates: u32,
        line: Option<Box<MetricsLine>>,
    },
    /// The run is over.
    Finished,
}

/// Whoever watches a run. Called on the coordinator's task: it must not block.
pub trait RunObserver: Send + Sync {
    fn observe(&self, event: RunEvent);
}

/// Nobody watching (a run without a console, and tests).
pub struct Unobserved;

impl RunObserver for Unobserved {
    fn observe(&self, _event: RunEvent) {}
}
