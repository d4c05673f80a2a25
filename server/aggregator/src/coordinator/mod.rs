//! The one aggregation task: owns the clients' outboxes, the global model, the strategy and the run directory,
//! and is fed by the connections through a channel. It reports what happens to a [`RunObserver`] (the operator
//! console) and takes the operator's decisions (pause, stop, settings) from the run's [`Controls`] at round
//! boundaries.
//!
//! Round lifecycle: wait until the operator lets rounds run and `min-clients` are connected; take up the
//! operator's new settings; sample clients (seeded, by `fraction-fit`); send tasks; collect until every sampled
//! client is done or the deadline passes, folding each update into the round's aggregation once the norm screen
//! ([`screen`]) has decided on it ([`round`]); close the aggregate, evaluate and persist ([`close`]); next round. A
//! round with fewer than `min-fit` updates is retried with a fresh sample. Stopped by the operator, the run ends
//! after the current round.
//!
//! Normalisation: every client gets the run's statistics on join. A run with `federated-stats` agrees them
//! before its first round from the moments its connected clients reported on join ([`Running::agree_stats`]),
//! so no client's data is pooled; round 0 (the initial model) is evaluated with the dataset's.

mod close;
mod round;
mod screen;
mod state;

use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::Instant;

use fedvla_federation::{DataReport, ErrorCode, NormalizationStats, ServerMessage, StatsSource};
use serde_json::json;

pub use self::state::{Coordinator, CoordinatorError, Event, PublishedModel, RunStatus, UpdateReceived};
use self::state::{Running, blocking};
use crate::control::{RunState, Settings};
use crate::events::RunEvent;
use crate::records::{MetricsLine, read_metrics};

impl Coordinator {
    pub async fn run(self) -> Result<RunStatus, CoordinatorError> {
        // A resumed run screens its next round's updates against the norms its last aggregated round accepted, as
        // it would have gone on.
        let accepted_norms = match self.completed {
            Some(_) => read_metrics(self.run_dir.path())
                .ok()
                .and_then(|lines| lines.iter().rev().find_map(MetricsLine::accepted_update_norms))
                .unwrap_or_default(),
            None => Vec::new(),
        };
        let screen = screen::NormScreen::new(accepted_norms);
        let mut this = Running { c: self, clients: BTreeMap::new(), round_rejections: BTreeMap::new(), screen };
        let result = this.run().await;
        match &result {
            Err(CoordinatorError::Cancelled) => tracing::info!("coordinator cancelled"),
            Err(e) => tracing::error!(error = %e, "coordinator stopped"),
            Ok(_) => {}
        }
        result
    }
}

impl Running {
    async fn run(&mut self) -> Result<RunStatus, CoordinatorError> {
        // A resumed run goes on with the statistics it agreed.
        if let Some(stats) = self.c.norm_stats.clone().filter(|s| s.source == StatsSource::Federated) {
            self.adopt_stats(&stats)?;
        }
        let first = match self.c.completed {
            Some(round) => {
                tracing::info!(round, "resuming after the last completed round");
                round + 1
            }
            None => {
                let eval = self.evaluate(0, Arc::clone(&self.c.global)).await.map_err(CoordinatorError::Evaluate)?;
                let line = self.persist(0, MetricsLine::default(), Some(eval), None).await?;
                self.observe(RunEvent::RoundClosed { round: 0, attempt: 0, updates: 0, line: Some(Box::new(line)) });
                1
            }
        };
        if self.c.controls.state() == RunState::WaitingForStart {
            tracing::info!("waiting for the operator to start the run in the console");
        }
        for round in first..=self.c.config.num_server_rounds {
            if !self.run_round(round).await? {
                tracing::info!(round, "stopped by the operator before this round");
                break;
            }
        }
        let rounds = self.c.global_version();
        for client in self.clients.values() {
            client.outbox.send(ServerMessage::Finished { rounds }).ok();
        }
        self.c.controls.finish();
        self.observe(RunEvent::Finished);
        self.c.status_tx.send_modify(|s| s.finished = true);
        tracing::info!(rounds, "run finished");
        Ok(self.c.status_tx.borrow().clone())
    }

    /// Runs round `round` to completion; false when the operator stopped the run before it could start.
    async fn run_round(&mut self, round: u64) -> Result<bool, CoordinatorError> {
        let mut attempt = 0;
        // The operator's changes this round's tasks are the first to use, for its metrics line.
        let mut new_settings = Settings::default();
        loop {
            if !self.wait_until_ready().await? {
                return Ok(false);
            }
            if let Some((config, changed)) = self.c.controls.take_settings() {
                tracing::info!(round, changed = %json!(changed), "this round uses the operator's new settings");
                self.c.config = config;
                // Written back so that a resumed run goes on with them.
                let (run_dir, config) = (self.c.run_dir.clone(), self.c.config.clone());
                blocking(&self.c.jobs, move || run_dir.write_config(&config)).await?;
                new_settings.merge(changed);
            }
            if self.c.config.federated_stats && self.c.norm_stats.is_none() {
                self.agree_stats(round).await?;
            }
            let started = Instant::now();
            let state = self.start_round(round, attempt);
            let mut state = self.collect(state).await?;
            self.c.sessions.end_uploads(round);
            let count = state.accepted() as u32;
            if state.accepted() < self.c.config.min_fit {
                tracing::warn!(round, attempt, updates = count, min_fit = self.c.config.min_fit, "round retried");
                self.broadcast(ServerMessage::RoundClosed {
                    round,
                    accepted: false,
                    model_version: self.c.global_version(),
                    updates: count,
                });
                self.c.status_tx.send_modify(|s| s.retried_rounds += 1);
                self.observe(RunEvent::RoundClosed { round, attempt, updates: count, line: None });
                attempt += 1;
                continue;
            }
            let evaluate = round.is_multiple_of(self.c.config.eval_every) || round == self.c.config.num_server_rounds;
            self.settle(&mut state, true);
            self.record_outliers(&mut state);
            let folded = state.participants.values().filter(|p| p.folded).count();
            let outcome = if folded < self.c.config.min_fit {
                let reason = format!(
                    "{folded} of {count} updates passed the norm screen and the strategy's checks, fewer than min-fit \
                     ({})",
                    self.c.config.min_fit
                );
                close::Aggregated::Skipped { reason }
            } else {
                self.aggregate_checked(round, evaluate, &mut state).await?
            };
            let mut line = MetricsLine {
                attempt: Some(attempt),
                seconds: Some(started.elapsed().as_secs_f64()),
                clients: state.records(),
                settings: (!new_settings.is_empty()).then_some(new_settings),
                ..MetricsLine::default()
            };
            let (contributors, eval, delta) = match outcome {
                close::Aggregated::Accepted { eval, contributors, delta } => (contributors, eval, delta),
                close::Aggregated::Skipped { reason } => {
                    tracing::warn!(round, %reason, "round skipped: the global model stays as it was");
                    self.c.status_tx.send_modify(|s| s.skipped_rounds += 1);
                    line.skipped = Some(reason);
                    (Vec::new(), None, None)
                }
            };
            let line = self.persist(round, line, eval, delta).await?;
            if let Some(norms) = line.accepted_update_norms() {
                self.screen.remember(norms);
            }
            self.broadcast(ServerMessage::RoundClosed {
                round,
                accepted: true,
                model_version: round,
                updates: contributors.len() as u32,
            });
            for id in contributors {
                self.observe(RunEvent::UpdateAccepted { id });
            }
            self.observe(RunEvent::RoundClosed { round, attempt, updates: count, line: Some(Box::new(line)) });
            return Ok(true);
        }
    }

    /// Waits until a round may start: the operator lets rounds run and `min-clients` are connected. False when the
    /// operator stopped the run instead.
    async fn wait_until_ready(&mut self) -> Result<bool, CoordinatorError> {
        let mut operator = self.c.controls.run_state();
        loop {
            let state = *operator.borrow_and_update();
            match state {
                RunState::Stopping | RunState::Finished => return Ok(false),
                RunState::Running if self.clients.len() >= self.c.config.min_clients => return Ok(true),
                RunState::WaitingForStart | RunState::Paused | RunState::Running => {}
            }
            tokio::select! {
                // The controls, which hold the sender, live as long as the coordinator.
                _ = operator.changed() => {}
                event = self.next_event() => {
                    let event = event?;
                    self.handle(event, None);
                }
            }
        }
    }

    /// Federated statistics: combines the moments of the connected clients' data exactly into the run's
    /// normalisation statistics, records them and sends them to every client, the evaluator and the exporters.
    /// Clients that reported no moments are left out; with none at all the run keeps the dataset's.
    async fn agree_stats(&mut self, round: u64) -> Result<(), CoordinatorError> {
        let reports: Vec<&DataReport> = self.clients.values().filter_map(|c| c.report.as_deref()).collect();
        let stats = match NormalizationStats::combine(&reports) {
            Ok(stats) => stats,
            Err(reason) => {
                tracing::warn!(round, %reason, "no federated statistics: the run keeps its dataset's");
                self.c.norm_stats = self.c.dataset_stats.clone();
                return Ok(());
            }
        };
        tracing::info!(round, clients = stats.clients, "normalisation statistics agreed by federated statistics");
        let (run_dir, record) = (self.c.run_dir.clone(), stats.clone());
        blocking(&self.c.jobs, move || run_dir.write_norm_stats(&record)).await?;
        self.adopt_stats(&stats)?;
        self.broadcast(ServerMessage::NormStats(stats.clone()));
        self.c.norm_stats = Some(stats);
        Ok(())
    }

    /// Hands `stats` to the evaluator and the exporters.
    fn adopt_stats(&self, stats: &NormalizationStats) -> Result<(), CoordinatorError> {
        self.c.evaluator.lock().expect("evaluator lock").set_norm_stats(stats).map_err(CoordinatorError::Evaluate)?;
        for exporter in self.c.exporters.iter() {
            exporter.set_norm_stats(stats).map_err(CoordinatorError::Evaluate)?;
        }
        Ok(())
    }

    async fn next_event(&mut self) -> Result<Event, CoordinatorError> {
        tokio::select! {
            () = self.c.cancel.cancelled() => Err(CoordinatorError::Cancelled),
            event = self.c.events.recv() => event.ok_or(CoordinatorError::Cancelled),
        }
    }

    fn observe(&self, event: RunEvent) {
        self.c.observer.observe(event);
    }

    fn count(&mut self, code: ErrorCode) {
        *self.round_rejections.entry(code).or_default() += 1;
        self.c.status_tx.send_modify(|s| *s.rejections.entry(code).or_default() += 1);
    }

    fn broadcast(&self, msg: ServerMessage) {
        for client in self.clients.values() {
            client.outbox.send(msg.clone()).ok();
        }
    }
}
