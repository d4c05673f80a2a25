//! A round in flight: sampling its clients, sending their tasks, and handling what connections report until every
//! sampled client is done or the deadline passes. Each update is folded into the round's aggregation as soon as
//! the norm screen ([`super::screen`]) has decided on it, mostly on arrival, and then let go: the round holds one
//! running aggregate, not its clients' models (but for the few the screen is still deciding on, and what a robust
//! rule buffers itself).

use std::collections::BTreeMap;
use std::time::Duration;

use fedvla_federation::{
    Aggregation, Contribution, ErrorCode, ModelDeltas, NamedTensors, RolloutRequest, RoundMetrics, RoundTask,
    ServerMessage, fnv1a, mix,
};
use rand::SeedableRng;
use rand::rngs::StdRng;

use super::screen::Verdict;
use super::state::{ClientEntry, CoordinatorError, Event, Running, UpdateReceived};
use crate::events::{ClientState, RunEvent};
use crate::records::{ClientRecord, DataSource, RolloutResults};

/// First seed of the layouts clients roll out (far from the seeds datasets are recorded on); each shard has its
/// own block of them, the same every round, so success rates compare from round to round.
const CLIENT_ROLLOUT_SEED: u64 = 20_000;
const CLIENT_ROLLOUT_SEEDS_PER_SHARD: u64 = 1_000;

#[derive(Default)]
pub(super) struct Participant {
    name: String,
    data: Option<DataSource>,
    /// The accepted update (its values folded, held in `held` or let go).
    update: Option<AcceptedUpdate>,
    /// The client's trained tensors while the norm screen has not decided on them.
    held: Option<NamedTensors>,
    /// Whether the update is in the round's aggregate.
    pub(super) folded: bool,
    /// Whether the norm screen left the update out (its reason, which names the round's median, is written when
    /// the round closes).
    pub(super) outlier: bool,
    /// What the update weighs: the client's shard's training examples, or its own data's within the cap (1 each
    /// where neither is known).
    examples: u64,
    /// Who the client is from round to round, for the strategies that keep state per client: its shard, or its
    /// name's hash where it has none.
    key: u64,
    /// The sum of the learning rates of its task's local steps.
    lr_sum: f64,
    /// Why the update was left out of the aggregate, when it was.
    pub(super) dropped: Option<String>,
    metrics: Option<RoundMetrics>,
    eval: Option<(u64, f64)>,
    rollout: Option<RolloutResults>,
    refused: Vec<ErrorCode>,
    done: bool,
}

/// What the round keeps of an accepted update besides its tensors.
#[derive(Clone, Copy)]
struct AcceptedUpdate {
    claimed_examples: u64,
    train_loss: f64,
    /// Bytes of the update's binary frames, headers included.
    bytes: u64,
    /// The L2 norm of its change from the round's global model.
    norm: f64,
}

pub(super) struct RoundState {
    round: u64,
    pub(super) participants: BTreeMap<u64, Participant>,
    /// Whether the tasks asked for sim rollouts, which clients run after their held-out evaluation.
    rollouts_requested: bool,
    /// The strategy's aggregation of the round, opened from the global model its clients train from; taken when
    /// the round closes.
    pub(super) aggregation: Option<Box<dyn Aggregation>>,
}

impl Participant {
    /// The norm of its accepted update's change from the round's global model.
    pub(super) fn norm(&self) -> Option<f64> {
        self.update.map(|u| u.norm)
    }
}

impl RoundState {
    pub(super) fn round(&self) -> u64 {
        self.round
    }

    /// The norms of the round's accepted updates.
    pub(super) fn norms(&self) -> Vec<f64> {
        self.participants.values().filter_map(Participant::norm).collect()
    }

    /// Updates accepted (decoded, fitting the model), screened or not.
    pub(super) fn accepted(&self) -> usize {
        self.participants.values().filter(|p| p.update.is_some()).count()
    }

    /// One metrics record per sampled client.
    pub(super) fn records(&self) -> Vec<ClientRecord> {
        self.participants
            .iter()
            .map(|(&client_id, p)| ClientRecord {
                client_id,
                name: p.name.clone(),
                data: p.data,
                accepted: p.folded && p.dropped.is_none(),
                examples: p.update.as_ref().map(|_| p.examples),
                claimed_examples: p.update.as_ref().map(|u| u.claimed_examples),
                dropped: p.dropped.clone(),
                train_loss: p.update.as_ref().map(|u| u.train_loss),
                update_bytes: p.update.as_ref().map(|u| u.bytes),
                update_norm: p.update.as_ref().map(|u| u.norm),
                seconds: p.metrics.as_ref().map(|m| m.seconds),
                bytes_up: p.metrics.as_ref().map(|m| m.bytes_up),
                bytes_down: p.metrics.as_ref().map(|m| m.bytes_down),
                download_bytes: p.metrics.as_ref().map(|m| m.download_bytes),
                eval_examples: p.eval.map(|e| e.0),
                eval_loss: p.eval.map(|e| e.1),
                rollout: p.rollout.clone(),
                refused: p.refused.iter().map(|c| c.as_str().to_owned()).collect(),
            })
            .collect()
    }
}

impl Running {
    /// Samples clients and sends them their tasks.
    pub(super) fn start_round(&mut self, round: u64, attempt: u64) -> RoundState {
        let cfg = &self.c.config;
        let mut pool: Vec<(&str, u64)> = self.clients.iter().map(|(id, c)| (c.name.as_str(), *id)).collect();
        pool.sort();
        let n = pool.len();
        let k = cfg.sampled_clients(n);
        let mut rng = StdRng::seed_from_u64(mix(mix(cfg.seed, round), attempt));
        let mut picked = rand::seq::index::sample(&mut rng, n, k).into_vec();
        picked.sort_unstable();
        let version = self.c.global_version();
        // The whole model, or the deltas since the version a volunteer holds while they are served.
        let model_deltas = self
            .c
            .model_tx
            .borrow()
            .deltas_since()
            .map(|since| ModelDeltas { since, checksum: self.c.global.checksum() });
        let mut participants = BTreeMap::new();
        let mut rollouts_requested = false;
        for i in picked {
            let (name, client_id) = pool[i];
            let client = &self.clients[&client_id];
            let evaluates = round.is_multiple_of(cfg.eval_every);
            let shard = match client.data {
                Some(DataSource::Shard { index, .. }) => Some(index as u64),
                _ => None,
            };
            // Strategy state (SCAFFOLD's variates, error feedback) follows the shard bound to the client's key, or
            // the key itself: never a name, which anyone can type.
            let key = shard.unwrap_or_else(|| fnv1a(&client.public_key));
            // A shard's own layouts: a volunteer without one gets a block by its key.
            let block = shard.unwrap_or(key % 1_000);
            let strategy = self.c.strategy.lock().expect("strategy lock");
            match strategy.client_correction(key).map(|c| c.to_safetensors()) {
                Some(Ok(bytes)) => self.c.sessions.offer_correction(client_id, round, bytes.into()),
                Some(Err(e)) => tracing::error!(round, client_id, %e, "the client's correction cannot be encoded"),
                None => {}
            }
            let strategy_params = strategy.client_params();
            drop(strategy);
            let task = RoundTask {
                round,
                model_version: version,
                local_steps: cfg.local_steps,
                batch_size: cfg.batch_size,
                lr: cfg.lr,
                lr_schedule: cfg.lr_schedule(round, u64::from(cfg.local_steps)),
                seed: mix(mix(mix(cfg.seed, round), attempt), fnv1a(name)),
                strategy: strategy_params,
                keep_optimizer_state: cfg.keep_optimizer_state,
                opening_frames: cfg.opening_frames(),
                deadline_ms: cfg.round_deadline_ms,
                eval_request: evaluates,
                rollout: (cfg.client_rollout_episodes > 0 && evaluates).then(|| RolloutRequest {
                    episodes: cfg.client_rollout_episodes,
                    first_seed: CLIENT_ROLLOUT_SEED + block * CLIENT_ROLLOUT_SEEDS_PER_SHARD,
                    max_frames: cfg.rollout_max_frames,
                }),
                update_encoding: cfg.encoding(),
                model_deltas,
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
            // Weighed by what the server knows the client holds, never by what its update claims.
            let examples = client.data.map_or(1, DataSource::weight);
            let lr_sum = task.lr_sum();
            client.outbox.send(ServerMessage::RoundTask(task)).ok();
            self.observe(RunEvent::ClientState { id: client_id, state: first_step });
            let participant = Participant {
                name: name.to_owned(),
                data: client.data,
                examples,
                key,
                lr_sum,
                ..Participant::default()
            };
            participants.insert(client_id, participant);
        }
        tracing::info!(round, attempt, sampled = k, connected = n, "round started");
        self.observe(RunEvent::RoundStarted { round, attempt, sampled: participants.keys().copied().collect() });
        let aggregation = Some(self.c.strategy.lock().expect("strategy lock").begin(&self.c.global));
        RoundState { round, participants, rollouts_requested, aggregation }
    }

    /// Handles events until every participant is done or the deadline passes.
    pub(super) async fn collect(&mut self, mut state: RoundState) -> Result<RoundState, CoordinatorError> {
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
                    self.settle(&mut state, false);
                }
            }
        }
        Ok(state)
    }

    /// Folds every held update the norm screen has decided to keep and lets go of those it left out. `closing`:
    /// no more updates come, so the screen decides on all.
    pub(super) fn settle(&mut self, state: &mut RoundState, closing: bool) {
        let norms = state.norms();
        let pending = match closing {
            true => 0,
            false => state.participants.values().filter(|p| p.update.is_none() && !p.done).count(),
        };
        let (round, factor) = (state.round, self.c.config.update_norm_factor);
        for (&client_id, p) in state.participants.iter_mut().filter(|(_, p)| p.held.is_some()) {
            let Some(update) = p.update else { continue };
            match self.screen.verdict(factor, update.norm, &norms, pending) {
                Verdict::Undecided => {}
                Verdict::Outlier => {
                    p.held = None;
                    p.outlier = true;
                }
                Verdict::Keep => {
                    let tensors = p.held.take().expect("filtered on held");
                    let contribution = Contribution {
                        tensors: &tensors,
                        examples: p.examples,
                        train_loss: Some(update.train_loss),
                        client: Some(p.key),
                        lr_sum: Some(p.lr_sum),
                    };
                    let aggregation = state.aggregation.as_mut().expect("open until the round closes");
                    match aggregation.fold(contribution) {
                        Ok(()) => p.folded = true,
                        Err(e) => {
                            let reason = format!("the strategy refused it: {e}");
                            tracing::warn!(round, client_id, %reason, "update left out of the aggregate");
                            p.dropped = Some(reason);
                            self.count(ErrorCode::DroppedUpdate);
                        }
                    }
                }
            }
        }
    }

    /// Counts an update the coordinator refused and tells its client why.
    fn refuse_update(&mut self, client_id: u64, code: ErrorCode, message: String) {
        tracing::warn!(client_id, %message, "refused update");
        self.count(code);
        if let Some(c) = self.clients.get(&client_id) {
            c.outbox.send(ServerMessage::Error { code, message }).ok();
        }
    }

    pub(super) fn handle(&mut self, event: Event, round: Option<&mut RoundState>) {
        let current = round.as_deref().map(|r| r.round);
        let rollouts_requested = round.as_deref().is_some_and(|r| r.rollouts_requested);
        let mut participants = round.map(|r| &mut r.participants);
        // Each event concerns at most one participant, so the map is taken once.
        let mut participant = |id: u64| participants.take().and_then(|p| p.get_mut(&id));
        match event {
            Event::Joined { client_id, name, public_key, capabilities, data, report, outbox } => {
                tracing::debug!(client_id, ?capabilities, ?data, "registered");
                self.observe(RunEvent::ClientJoined {
                    id: client_id,
                    name: name.clone(),
                    backend: capabilities.backend,
                    data,
                });
                if let Some(stats) = &self.c.norm_stats {
                    outbox.send(ServerMessage::NormStats(stats.clone())).ok();
                }
                self.clients.insert(client_id, ClientEntry { name, public_key, data, report, outbox });
            }
            Event::Left { client_id } => {
                self.clients.remove(&client_id);
                self.observe(RunEvent::ClientLeft { id: client_id });
                if let Some(p) = participant(client_id) {
                    p.done = true;
                }
            }
            Event::Update { client_id, update } => match participant(client_id) {
                Some(p) if Some(update.round) == current && p.update.is_none() => {
                    // The reservation ends with this event, once the round holds the model (the fold follows in
                    // `settle`, on this task, before the next event is taken).
                    let UpdateReceived { round: _, values, claimed_examples, train_loss, bytes, reservation: _ } =
                        *update;
                    let model = match values.into_model(&self.c.global) {
                        Ok(model) => model,
                        Err(e) => {
                            p.refused.push(e.code());
                            self.refuse_update(
                                client_id,
                                e.code(),
                                format!("the update added to the round's global model: {e}"),
                            );
                            return;
                        }
                    };
                    let known = self.clients.get(&client_id).and_then(|c| c.data);
                    if known.is_some_and(|d| d.expected_claim() != claimed_examples) {
                        tracing::info!(
                            client_id,
                            claimed = claimed_examples,
                            weight = p.examples,
                            "update claims another example count than the client's data holds: weighed by that"
                        );
                        self.c.status_tx.send_modify(|s| s.corrected_claims += 1);
                    }
                    let norm = model.distance(&self.c.global).expect("into_model gave the global model's tensors");
                    p.update = Some(AcceptedUpdate { claimed_examples, train_loss, bytes, norm });
                    // Folded, or left out, as soon as the norm screen decides ([`Running::settle`]).
                    p.held = Some(model);
                }
                Some(_) if Some(update.round) == current => {
                    let message = format!("a second update for round {} from this client", update.round);
                    self.refuse_update(client_id, ErrorCode::DuplicateUpdate, message);
                }
                None if Some(update.round) == current => {
                    let message = format!("this client was not sampled into round {}", update.round);
                    self.refuse_update(client_id, ErrorCode::UnrequestedUpdate, message);
                }
                _ => {
                    let message =
                        format!("update for round {} is not expected (current round {current:?})", update.round);
                    self.refuse_update(client_id, ErrorCode::StaleRound, message);
                }
            },
            Event::Uploading { client_id } => {
                self.observe(RunEvent::ClientState { id: client_id, state: ClientState::Uploading });
            }
            Event::Metrics { client_id, metrics } => {
                self.observe(RunEvent::ClientState { id: client_id, state: ClientState::Idle });
                self.observe(RunEvent::ClientBytes { id: client_id, up: metrics.bytes_up, down: metrics.bytes_down });
                if let Some(p) = participant(client_id).filter(|_| Some(metrics.round) == current) {
                    p.metrics = Some(metrics);
                    p.done = true;
                }
            }
            Event::EvalResult { client_id, round: r, examples, loss } => {
                if let Some(p) = participant(client_id).filter(|_| Some(r) == current) {
                    p.eval = Some((examples, loss));
                    let next = if rollouts_requested { ClientState::Evaluating } else { ClientState::Training };
                    self.observe(RunEvent::ClientState { id: client_id, state: next });
                }
            }
            Event::RolloutResult { client_id, round: r, model_version, episodes } => {
                if let Some(p) = participant(client_id).filter(|_| Some(r) == current) {
                    let record = RolloutResults::of(format!("client {client_id}"), Some(model_version), episodes);
                    // Small: written on the coordinator's task.
                    if let Err(e) = self.c.run_dir.write_client_results(r, client_id, &record) {
                        tracing::warn!(client_id, round = r, error = %e, "client rollout results not stored");
                    }
                    tracing::info!(client_id, round = r, success_rate = ?record.success_rate, "client rolled out the global model");
                    p.rollout = Some(record);
                    self.observe(RunEvent::ClientState { id: client_id, state: ClientState::Training });
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
}
