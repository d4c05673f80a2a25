//! The one aggregation task: owns the clients' outboxes, the global model, the strategy and the run directory,
//! and is fed by the connections through a channel. It tells the operator console ([`ConsoleHub`]) what happens
//! and takes the operator's decisions (pause, stop, settings) from it at round boundaries.
//!
//! Round lifecycle: wait until the operator lets rounds run and `min-clients` are connected; take up the
//! operator's new settings; sample clients (seeded, by `fraction-fit`); send tasks; collect until every sampled
//! client is done or the deadline passes; aggregate; evaluate; persist; next round. A round with fewer than
//! `min-fit` updates is retried with a fresh sample. Stopped by the operator, the run ends after the current round.

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use axum::body::Bytes;
use fedvla_federation::{
    AggregateError, BoxError, Capabilities, ErrorCode, EvalMetrics, Evaluator, NamedTensors, RolloutEpisode,
    RolloutRequest, RoundMetrics, RoundTask, ServerMessage, Strategy,
};
use rand::SeedableRng;
use rand::rngs::StdRng;
use serde_json::json;
use tokio::sync::{mpsc, watch};
use tokio_util::sync::CancellationToken;

use crate::app::PublishedModel;
use crate::config::RunConfig;
use crate::console::{ClientState, ConsoleHub, RunState, Settings};
use crate::run_dir::{ModelExporter, RunDir, RunDirError};
use crate::volunteer::{Sessions, ShardBinding};

/// What connections tell the coordinator.
#[derive(Debug)]
pub enum Event {
    Joined {
        client_id: u64,
        name: String,
        capabilities: Capabilities,
        /// The shard the client trains on; `None` when the workload offers none (its updates weigh equally).
        shard: Option<ShardBinding>,
        outbox: mpsc::UnboundedSender<ServerMessage>,
    },
    Left {
        client_id: u64,
    },
    Update {
        client_id: u64,
        update: Box<UpdateReceived>,
    },
    Metrics {
        client_id: u64,
        metrics: RoundMetrics,
    },
    EvalResult {
        client_id: u64,
        round: u64,
        examples: u64,
        loss: f64,
    },
    /// Sim rollouts of the model version a task started from (videos already stored by HTTP).
    RolloutResult {
        client_id: u64,
        round: u64,
        model_version: u64,
        episodes: Vec<RolloutEpisode>,
    },
    /// A client announced an update (`UpdateHeader`); its frames are on the way.
    Uploading {
        client_id: u64,
    },
    /// Input refused by a connection (already answered with an `Error`); `None` before the client joined.
    Rejected {
        client_id: Option<u64>,
        code: ErrorCode,
    },
}

/// A complete, validated update.
#[derive(Debug)]
pub struct UpdateReceived {
    pub round: u64,
    pub tensors: NamedTensors,
    /// What the update header said; the update weighs what the client's shard holds.
    pub claimed_examples: u64,
    pub train_loss: f64,
    /// Bytes of the update's binary frames, headers included.
    pub bytes: u64,
}

/// Where the run stands, published after every change.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct RunStatus {
    pub completed_rounds: u64,
    pub connected: usize,
    /// Refused client inputs by error code, since the server started.
    pub rejections: BTreeMap<ErrorCode, u64>,
    /// Round attempts that closed with too few updates.
    pub retried_rounds: u64,
    /// Rounds whose every aggregate failed (or whose evaluation did): the global model stayed as it was.
    pub skipped_rounds: u64,
    /// Updates whose example count claim differed from their shard's training examples (the shard's count was
    /// used).
    pub corrected_claims: u64,
    pub finished: bool,
}

#[derive(Debug, thiserror::Error)]
pub enum CoordinatorError {
    #[error("cancelled")]
    Cancelled,
    #[error(transparent)]
    RunDir(#[from] RunDirError),
    #[error("evaluation failed: {0}")]
    Evaluate(BoxError),
}

/// Everything the coordinator owns.
pub struct Coordinator {
    pub config: RunConfig,
    pub events: mpsc::Receiver<Event>,
    pub cancel: CancellationToken,
    /// Locked only by the coordinator's own blocking jobs (aggregation runs off the async runtime).
    pub strategy: Arc<Mutex<Box<dyn Strategy + Send>>>,
    pub evaluator: Arc<Mutex<Box<dyn Evaluator + Send>>>,
    pub exporters: Arc<Vec<Box<dyn ModelExporter>>>,
    pub run_dir: RunDir,
    pub global: Arc<NamedTensors>,
    /// The last completed round; `None` for a fresh run (round 0, the initial evaluation, is still to do).
    pub completed: Option<u64>,
    pub model_tx: watch::Sender<Arc<PublishedModel>>,
    pub status_tx: watch::Sender<RunStatus>,
    pub console: ConsoleHub,
    /// Upload rights of the clients asked for rollout videos.
    pub sessions: Sessions,
}

struct ClientEntry {
    name: String,
    shard: Option<ShardBinding>,
    outbox: mpsc::UnboundedSender<ServerMessage>,
}

#[derive(Default)]
struct Participant {
    name: String,
    update: Option<UpdateReceived>,
    /// What the update weighs: the client's shard's training examples (1 each where no shard is known).
    examples: u64,
    /// Why the update was left out of the aggregate, when it was.
    dropped: Option<String>,
    metrics: Option<RoundMetrics>,
    eval: Option<(u64, f64)>,
    rollout: Option<serde_json::Value>,
    refused: Vec<ErrorCode>,
    done: bool,
}

struct RoundState {
    round: u64,
    participants: BTreeMap<u64, Participant>,
    /// Whether the tasks asked for sim rollouts, which clients run after their held-out evaluation.
    rollouts_requested: bool,
}

impl Coordinator {
    pub async fn run(self) -> Result<RunStatus, CoordinatorError> {
        let mut this = Running { c: self, clients: BTreeMap::new(), round_rejections: BTreeMap::new() };
        let result = this.run().await;
        match &result {
            Err(CoordinatorError::Cancelled) => tracing::info!("coordinator cancelled"),
            Err(e) => tracing::error!(error = %e, "coordinator stopped"),
            Ok(_) => {}
        }
        result
    }
}

struct Running {
    c: Coordinator,
    clients: BTreeMap<u64, ClientEntry>,
    /// Refusals since the last metrics line.
    round_rejections: BTreeMap<ErrorCode, u64>,
}

impl Running {
    async fn run(&mut self) -> Result<RunStatus, CoordinatorError> {
        let first = match self.c.completed {
            Some(round) => {
                tracing::info!(round, "resuming after the last completed round");
                round + 1
            }
            None => {
                let metrics = self.evaluate(0, Arc::clone(&self.c.global)).await.map_err(CoordinatorError::Evaluate)?;
                let line = self.persist(0, json!({ "clients": [], "global": metrics })).await?;
                self.c.console.round_closed(0, 0, 0, Some(&line));
                1
            }
        };
        if *self.c.console.run_state().borrow() == RunState::WaitingForStart {
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
        self.c.console.finish();
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
            if let Some((config, changed)) = self.c.console.take_settings() {
                tracing::info!(round, changed = %json!(changed), "this round uses the operator's new settings");
                self.c.config = config;
                // Written back so that a resumed run goes on with them.
                let (run_dir, config) = (self.c.run_dir.clone(), self.c.config.clone());
                blocking(move || run_dir.write_config(&config)).await?;
                new_settings.merge(changed);
            }
            let started = Instant::now();
            let state = self.start_round(round, attempt);
            let mut state = self.collect(state).await?;
            self.c.sessions.end_uploads(round);
            let mut updates: Vec<(&str, u64, NamedTensors, u64)> = state
                .participants
                .iter_mut()
                .filter_map(|(id, p)| {
                    let tensors = std::mem::take(&mut p.update.as_mut()?.tensors);
                    Some((p.name.as_str(), *id, tensors, p.examples))
                })
                .collect();
            // Aggregation order follows the clients' names, so the sum does not depend on arrival or id order.
            updates.sort_by(|a, b| (a.0, a.1).cmp(&(b.0, b.1)));
            let updates: Vec<(u64, NamedTensors, u64)> = updates.into_iter().map(|(_, id, t, n)| (id, t, n)).collect();
            let accepted = updates.len() as u32;
            if updates.len() < self.c.config.min_fit {
                tracing::warn!(round, attempt, updates = accepted, min_fit = self.c.config.min_fit, "round retried");
                self.broadcast(ServerMessage::RoundClosed {
                    round,
                    accepted: false,
                    model_version: self.c.global_version(),
                    updates: accepted,
                });
                self.c.status_tx.send_modify(|s| s.retried_rounds += 1);
                self.c.console.round_closed(round, attempt, accepted, None);
                attempt += 1;
                continue;
            }
            let evaluate = round.is_multiple_of(self.c.config.eval_every) || round == self.c.config.num_server_rounds;
            let outcome = self.aggregate_checked(round, updates, evaluate, &mut state).await?;
            let seconds = started.elapsed().as_secs_f64();
            let clients = client_records(&state);
            let mut line = json!({ "attempt": attempt, "seconds": seconds, "clients": clients });
            let contributors = match outcome {
                Aggregated::Accepted { metrics, contributors } => {
                    line["global"] = json!(metrics);
                    contributors
                }
                Aggregated::Skipped { reason } => {
                    tracing::warn!(round, %reason, "round skipped: the global model stays as it was");
                    self.c.status_tx.send_modify(|s| s.skipped_rounds += 1);
                    line["global"] = serde_json::Value::Null;
                    line["skipped"] = json!(reason);
                    Vec::new()
                }
            };
            if !new_settings.is_empty() {
                line["settings"] = json!(new_settings);
            }
            let line = self.persist(round, line).await?;
            self.broadcast(ServerMessage::RoundClosed {
                round,
                accepted: true,
                model_version: round,
                updates: contributors.len() as u32,
            });
            for id in contributors {
                self.c.console.client_changed(id, |c| c.updates_accepted += 1);
            }
            self.c.console.round_closed(round, attempt, accepted, Some(&line));
            return Ok(true);
        }
    }

    /// Waits until a round may start: the operator lets rounds run and `min-clients` are connected. False when the
    /// operator stopped the run instead.
    async fn wait_until_ready(&mut self) -> Result<bool, CoordinatorError> {
        let mut operator = self.c.console.run_state();
        loop {
            let state = *operator.borrow_and_update();
            match state {
                RunState::Stopping | RunState::Finished => return Ok(false),
                RunState::Running if self.clients.len() >= self.c.config.min_clients => return Ok(true),
                RunState::WaitingForStart | RunState::Paused | RunState::Running => {}
            }
            tokio::select! {
                // The hub, which holds the sender, lives as long as the coordinator.
                _ = operator.changed() => {}
                event = self.next_event() => {
                    let event = event?;
                    self.handle(event, None);
                }
            }
        }
    }

    async fn next_event(&mut self) -> Result<Event, CoordinatorError> {
        tokio::select! {
            () = self.c.cancel.cancelled() => Err(CoordinatorError::Cancelled),
            event = self.c.events.recv() => event.ok_or(CoordinatorError::Cancelled),
        }
    }

    /// Samples clients and sends them their tasks.
    fn start_round(&mut self, round: u64, attempt: u64) -> RoundState {
        let cfg = &self.c.config;
        let mut pool: Vec<(&str, u64)> = self.clients.iter().map(|(id, c)| (c.name.as_str(), *id)).collect();
        pool.sort();
        let n = pool.len();
        let k = cfg.sampled_clients(n);
        let mut rng = StdRng::seed_from_u64(mix(mix(cfg.seed, round), attempt));
        let mut picked = rand::seq::index::sample(&mut rng, n, k).into_vec();
        picked.sort_unstable();
        let version = self.c.global_version();
        let mut participants = BTreeMap::new();
        let mut rollouts_requested = false;
        for i in picked {
            let (name, client_id) = pool[i];
            let task = RoundTask {
                round,
                model_version: version,
                local_steps: cfg.local_steps,
                batch_size: cfg.batch_size,
                lr: cfg.lr,
                seed: mix(mix(mix(cfg.seed, round), attempt), fnv1a(name)),
                strategy: self.c.strategy.lock().expect("strategy lock").client_params(),
                deadline_ms: cfg.round_deadline_ms,
                eval_request: round.is_multiple_of(cfg.eval_every),
                // Same seeds every round, so success rates compare across rounds.
                rollout: (cfg.client_rollout_episodes > 0 && round.is_multiple_of(cfg.eval_every)).then(|| {
                    RolloutRequest {
                        episodes: cfg.client_rollout_episodes,
                        first_seed: CLIENT_ROLLOUT_SEED,
                        max_frames: cfg.rollout_max_frames,
                    }
                }),
            };
            // Clients evaluate the model they start from (held-out loss, then sim rollouts) before they train.
            let first_step = if task.eval_request || task.rollout.is_some() {
                ClientState::Evaluating
            } else {
                ClientState::Training
            };
            rollouts_requested |= task.rollout.is_some();
            if let Some(request) = &task.rollout {
                self.c.sessions.allow_uploads(client_id, round, request.episodes);
            }
            self.clients[&client_id].outbox.send(ServerMessage::RoundTask(task)).ok();
            self.c.console.client_changed(client_id, |c| c.state = first_step);
            // Weighed by what the server knows the client holds, never by what its update claims.
            let examples = self.clients[&client_id].shard.map_or(1, |s| s.train_examples);
            participants.insert(client_id, Participant { name: name.to_owned(), examples, ..Participant::default() });
        }
        tracing::info!(round, attempt, sampled = k, connected = n, "round started");
        self.c.console.round_started(round, attempt, participants.keys().copied().collect());
        RoundState { round, participants, rollouts_requested }
    }

    /// Handles events until every participant is done or the deadline passes.
    async fn collect(&mut self, mut state: RoundState) -> Result<RoundState, CoordinatorError> {
        let deadline = tokio::time::Instant::now() + Duration::from_millis(self.c.config.round_deadline_ms);
        while !state.participants.values().all(|p| p.done) {
            tokio::select! {
                () = tokio::time::sleep_until(deadline) => {
                    let late: Vec<u64> = state.participants.iter().filter(|(_, p)| !p.done).map(|(id, _)| *id).collect();
                    tracing::warn!(round = state.round, ?late, "deadline passed");
                    break;
                }
                event = self.next_event() => {
                    let event = event?;
                    self.handle(event, Some(&mut state));
                }
            }
        }
        Ok(state)
    }

    fn handle(&mut self, event: Event, round: Option<&mut RoundState>) {
        let current = round.as_deref().map(|r| r.round);
        let rollouts_requested = round.as_deref().is_some_and(|r| r.rollouts_requested);
        let mut participants = round.map(|r| &mut r.participants);
        // Each event concerns at most one participant, so the map is taken once.
        let mut participant = |id: u64| participants.take().and_then(|p| p.get_mut(&id));
        match event {
            Event::Joined { client_id, name, capabilities, shard, outbox } => {
                tracing::debug!(client_id, ?capabilities, "registered");
                self.c.console.client_joined(client_id, &name, &capabilities.backend);
                self.clients.insert(client_id, ClientEntry { name, shard, outbox });
            }
            Event::Left { client_id } => {
                self.clients.remove(&client_id);
                self.c.console.client_left(client_id);
                if let Some(p) = participant(client_id) {
                    p.done = true;
                }
            }
            Event::Update { client_id, update } => match participant(client_id) {
                Some(p) if Some(update.round) == current && p.update.is_none() => {
                    let known = self.clients.get(&client_id).and_then(|c| c.shard);
                    if known.is_some_and(|s| s.train_examples != update.claimed_examples) {
                        tracing::info!(
                            client_id,
                            claimed = update.claimed_examples,
                            weight = p.examples,
                            "update claims another example count than its shard holds: weighed by the shard"
                        );
                        self.c.status_tx.send_modify(|s| s.corrected_claims += 1);
                    }
                    p.update = Some(*update);
                }
                _ => {
                    let message =
                        format!("update for round {} is not expected (current round {current:?})", update.round);
                    tracing::warn!(client_id, %message, "refused update");
                    self.count(ErrorCode::StaleRound);
                    if let Some(c) = self.clients.get(&client_id) {
                        c.outbox.send(ServerMessage::Error { code: ErrorCode::StaleRound, message }).ok();
                    }
                }
            },
            Event::Uploading { client_id } => {
                self.c.console.client_changed(client_id, |c| c.state = ClientState::Uploading);
            }
            Event::Metrics { client_id, metrics } => {
                let (bytes_up, bytes_down) = (metrics.bytes_up, metrics.bytes_down);
                self.c.console.client_changed(client_id, |c| {
                    c.state = ClientState::Idle;
                    (c.bytes_up, c.bytes_down) = (bytes_up, bytes_down);
                });
                if let Some(p) = participant(client_id).filter(|_| Some(metrics.round) == current) {
                    p.metrics = Some(metrics);
                    p.done = true;
                }
            }
            Event::EvalResult { client_id, round: r, examples, loss } => {
                if let Some(p) = participant(client_id).filter(|_| Some(r) == current) {
                    p.eval = Some((examples, loss));
                    let next = if rollouts_requested { ClientState::Evaluating } else { ClientState::Training };
                    self.c.console.client_changed(client_id, |c| c.state = next);
                }
            }
            Event::RolloutResult { client_id, round: r, model_version, episodes } => {
                if let Some(p) = participant(client_id).filter(|_| Some(r) == current) {
                    let record = rollout_record(model_version, &episodes);
                    // Small: written on the coordinator's task.
                    if let Err(e) = self.c.run_dir.write_client_results(r, client_id, &record) {
                        tracing::warn!(client_id, round = r, error = %e, "client rollout results not stored");
                    }
                    tracing::info!(client_id, round = r, success_rate = %record["success_rate"], "client rolled out the global model");
                    p.rollout = Some(record);
                    self.c.console.client_changed(client_id, |c| c.state = ClientState::Training);
                }
            }
            Event::Rejected { client_id, code } => {
                self.count(code);
                if let Some(p) = client_id.and_then(participant) {
                    p.refused.push(code);
                    p.done = true;
                }
            }
        }
        let connected = self.clients.len();
        self.c.status_tx.send_if_modified(|s| std::mem::replace(&mut s.connected, connected) != connected);
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

    /// Aggregates `updates` (client id, tensors, weight) into the next global model and, when `evaluate`, evaluates
    /// it. A failed aggregate or evaluation (an error, or a figure that is not finite) drops the update farthest
    /// from the current global model and tries again, as long as more than `min-fit` updates remain and at most
    /// [`MAX_DROPPED_PER_ROUND`] times; after that the round is skipped. Either way the run goes on.
    async fn aggregate_checked(
        &mut self,
        round: u64,
        mut updates: Vec<(u64, NamedTensors, u64)>,
        evaluate: bool,
        state: &mut RoundState,
    ) -> Result<Aggregated, CoordinatorError> {
        let mut dropped = 0;
        loop {
            let strategy = Arc::clone(&self.c.strategy);
            let global = Arc::clone(&self.c.global);
            let pairs: Vec<(NamedTensors, u64)> = updates.iter().map(|(_, t, n)| (t.clone(), *n)).collect();
            let aggregated = blocking(move || strategy.lock().expect("strategy lock").aggregate(&global, &pairs)).await;
            let (reason, culprit) = match aggregated {
                Ok(candidate) => {
                    let candidate = Arc::new(candidate);
                    let metrics = match evaluate {
                        true => Some(self.evaluate(round, Arc::clone(&candidate)).await),
                        false => None,
                    };
                    match metrics {
                        Some(Ok(m)) if !m.values().all(|v| v.is_finite()) => {
                            (format!("the aggregate evaluates to non-finite figures {m:?}"), None)
                        }
                        Some(Err(e)) => (format!("evaluating the aggregate failed: {e}"), None),
                        metrics => {
                            self.c.global = candidate;
                            let contributors = updates.iter().map(|(id, _, _)| *id).collect();
                            return Ok(Aggregated::Accepted { metrics: metrics.and_then(Result::ok), contributors });
                        }
                    }
                }
                Err(AggregateError::Mismatch { index, source }) => {
                    (format!("update {index} does not fit the model: {source}"), Some(index))
                }
                Err(e) => (format!("aggregation failed: {e}"), None),
            };
            if dropped == MAX_DROPPED_PER_ROUND || updates.len() <= self.c.config.min_fit {
                return Ok(Aggregated::Skipped { reason });
            }
            let culprit = culprit.unwrap_or_else(|| farthest(&self.c.global, &updates));
            let (client_id, _, _) = updates.remove(culprit);
            dropped += 1;
            tracing::warn!(round, client_id, %reason, "dropping the update farthest from the global model, re-aggregating");
            if let Some(p) = state.participants.get_mut(&client_id) {
                p.dropped = Some(reason);
            }
            self.count(ErrorCode::DroppedUpdate);
        }
    }

    async fn evaluate(&mut self, round: u64, model: Arc<NamedTensors>) -> Result<EvalMetrics, BoxError> {
        let evaluator = Arc::clone(&self.c.evaluator);
        let metrics = blocking(move || evaluator.lock().expect("evaluator lock").evaluate(&model)).await?;
        tracing::info!(round, ?metrics, "global model evaluated");
        Ok(metrics)
    }

    /// Saves the round's model, appends its metrics line, then publishes the model for download.
    /// Returns the metrics line as written.
    async fn persist(
        &mut self,
        round: u64,
        mut line: serde_json::Value,
    ) -> Result<serde_json::Value, CoordinatorError> {
        let rejections: BTreeMap<&str, u64> =
            std::mem::take(&mut self.round_rejections).into_iter().map(|(c, n)| (c.as_str(), n)).collect();
        line["round"] = json!(round);
        line["model_version"] = json!(round);
        line["model_crc32"] = json!(self.c.global.checksum());
        line["rejections"] = json!(rejections);
        line["timestamp"] = json!(chrono::Local::now().to_rfc3339());
        let (run_dir, exporters, global, config) =
            (self.c.run_dir.clone(), Arc::clone(&self.c.exporters), Arc::clone(&self.c.global), self.c.config.clone());
        let (line, bytes) = blocking(move || -> Result<_, RunDirError> {
            let measured = run_dir.save_model(round, &global, &exporters, &config)?;
            if !measured.is_empty() {
                if !line["global"].is_object() {
                    line["global"] = json!({});
                }
                for (name, value) in measured {
                    line["global"][name] = json!(value);
                }
            }
            run_dir.append_metrics(&line)?;
            let bytes = global.to_safetensors().map_err(|source| RunDirError::Model { round, source })?;
            Ok((line, bytes))
        })
        .await?;
        self.c.model_tx.send_replace(Arc::new(PublishedModel { version: round, safetensors: Bytes::from(bytes) }));
        self.c.completed = Some(round);
        self.c.status_tx.send_modify(|s| s.completed_rounds = round);
        tracing::info!(round, "round completed");
        Ok(line)
    }
}

impl Coordinator {
    /// The model version clients train from: the last completed round.
    fn global_version(&self) -> u64 {
        self.completed.unwrap_or(0)
    }
}

async fn blocking<T: Send + 'static>(f: impl FnOnce() -> T + Send + 'static) -> T {
    match tokio::task::spawn_blocking(f).await {
        Ok(out) => out,
        Err(e) => std::panic::resume_unwind(e.into_panic()),
    }
}

/// What became of a round's updates.
enum Aggregated {
    /// The global model was replaced; `metrics` is its evaluation when the round evaluates.
    Accepted { metrics: Option<EvalMetrics>, contributors: Vec<u64> },
    /// Every aggregate the round could form failed: the global model stays as it was.
    Skipped { reason: String },
}

/// Updates a round may leave out of its aggregate before it gives up and is skipped.
const MAX_DROPPED_PER_ROUND: usize = 3;

/// Index of the update farthest (Euclidean) from `global`: after a failed aggregate, the likeliest culprit.
fn farthest(global: &NamedTensors, updates: &[(u64, NamedTensors, u64)]) -> usize {
    let distance = |update: &NamedTensors| -> f64 {
        global
            .iter()
            .map(|(name, g)| {
                let u = update.get(name).map_or(&[][..], |t| t.values.as_slice());
                g.values.iter().zip(u).map(|(a, b)| (f64::from(*b) - f64::from(*a)).powi(2)).sum::<f64>()
            })
            .sum()
    };
    let distances: Vec<f64> = updates.iter().map(|(_, update, _)| distance(update)).collect();
    (0..updates.len()).max_by(|&a, &b| distances[a].total_cmp(&distances[b])).unwrap_or(0)
}

/// One metrics record per sampled client.
fn client_records(state: &RoundState) -> Vec<serde_json::Value> {
    state
        .participants
        .iter()
        .map(|(id, p)| {
            json!({
                "client_id": id,
                "name": p.name,
                "accepted": p.update.is_some() && p.dropped.is_none(),
                "examples": p.update.as_ref().map(|_| p.examples),
                "claimed_examples": p.update.as_ref().map(|u| u.claimed_examples),
                "dropped": p.dropped,
                "train_loss": p.update.as_ref().map(|u| u.train_loss),
                "update_bytes": p.update.as_ref().map(|u| u.bytes),
                "seconds": p.metrics.as_ref().map(|m| m.seconds),
                "bytes_up": p.metrics.as_ref().map(|m| m.bytes_up),
                "bytes_down": p.metrics.as_ref().map(|m| m.bytes_down),
                "eval_examples": p.eval.map(|e| e.0),
                "eval_loss": p.eval.map(|e| e.1),
                "rollout": p.rollout,
                "refused": p.refused.iter().map(|c| c.as_str()).collect::<Vec<_>>(),
            })
        })
        .collect()
}

/// First seed of the episodes clients roll out (apart from the seeds datasets are recorded on).
const CLIENT_ROLLOUT_SEED: u64 = 20_000;

/// A client's rollouts as `results.json` and its metrics line record them.
fn rollout_record(model_version: u64, episodes: &[RolloutEpisode]) -> serde_json::Value {
    let successes = episodes.iter().filter(|e| e.success).count();
    let success_rate = if episodes.is_empty() { None } else { Some(successes as f64 / episodes.len() as f64) };
    json!({ "model_version": model_version, "episodes": episodes, "success_rate": success_rate })
}

/// splitmix64 of `a` combined with `b`: seeds derived per round, attempt and client.
fn mix(a: u64, b: u64) -> u64 {
    let mut z = a ^ b.wrapping_add(0x9e37_79b9_7f4a_7c15).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

fn fnv1a(s: &str) -> u64 {
    s.bytes().fold(0xcbf2_9ce4_8422_2325, |h, b| (h ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3))
}
