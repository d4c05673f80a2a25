//! The client's side of the protocol shared by the native and the browser clients: proving its identity on a new
//! connection ([`identify`]) and the round loop ([`run_client`]).
//!
//! Runtime-agnostic: plain async, no executor, no clock of its own (`Instant` panics on wasm32), so the
//! platform supplies both through [`ClientTransport`].

use std::future::Future;

use crate::codec::{apply_model_deltas, encode_delta_payload, encode_frames, encode_payload};
use crate::data_report::{DataReport, NormalizationStats};
use crate::error::{BoxError, CodecError, TensorError};
use crate::identity::Identity;
use crate::protocol::{
    Capabilities, ClientMessage, ErrorCode, ModelDeltas, PROTOCOL_VERSION, RolloutEpisode, RolloutRequest,
    RoundMetrics, RoundTask, ServerMessage, UpdateEncoding, VolunteerSetup,
};
use crate::tensors::NamedTensors;

/// What a round of local training produced.
#[derive(Debug, Clone, PartialEq)]
pub struct TrainOutput {
    /// The trainable tensors after local training (not a delta), same names and shapes as the global ones.
    pub update: NamedTensors,
    pub examples: u64,
    pub train_loss: f64,
}

/// Loss of the current tensors on the client's held-out split.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EvalOutput {
    pub examples: u64,
    pub loss: f64,
}

/// A recorded rollout video.
#[derive(Debug, Clone, PartialEq)]
pub struct Video {
    /// e.g. "episode_0.webm"; the server stores it under this name.
    pub file_name: String,
    /// e.g. "video/webm".
    pub mime: String,
    pub bytes: Vec<u8>,
}

/// One rolled-out episode and its video (the episode's `video` field is filled in by the round loop).
#[derive(Debug, Clone, PartialEq)]
pub struct RolloutOutput {
    pub episode: RolloutEpisode,
    pub video: Option<Video>,
}

/// Trains the trainable tensors on the local shard. The policy implements this (natively and in the browser).
pub trait LocalTrainer {
    fn capabilities(&self) -> Capabilities;

    /// Replaces the trainable tensors with the global ones; frozen tensors are untouched.
    fn set_global(&mut self, global: &NamedTensors) -> Result<(), BoxError>;

    /// What to add to the direction of each local step from now on (SCAFFOLD's `c - c_i`, per unit of learning
    /// rate); empty: nothing. A trainer that cannot refuses a correction.
    fn set_correction(&mut self, correction: &NamedTensors) -> Result<(), BoxError> {
        match correction.is_empty() {
            true => Ok(()),
            false => Err("this trainer cannot apply SCAFFOLD's correction".into()),
        }
    }

    /// Normalises state and action with `stats` from now on (the run's, which the server sends before the first
    /// task). Trainers whose data needs no normalisation ignore them.
    fn set_norm_stats(&mut self, stats: &NormalizationStats) -> Result<(), BoxError> {
        let _ = stats;
        Ok(())
    }

    /// Runs `task.local_steps` steps at `task.batch_size` and `task.lr` from the tensors last set.
    fn train(&mut self, task: &RoundTask) -> impl Future<Output = Result<TrainOutput, BoxError>>;

    /// Evaluates the tensors last set on the local held-out split.
    fn evaluate(&mut self) -> impl Future<Output = Result<EvalOutput, BoxError>>;

    /// Rolls the tensors last set out in the sim. Clients that cannot (no sim or no way to film it) report no
    /// episodes, and the server records that.
    fn rollout(&mut self, request: &RolloutRequest) -> impl Future<Output = Result<Vec<RolloutOutput>, BoxError>> {
        let _ = request;
        async { Ok(Vec::new()) }
    }
}

/// The client's connection to the server: a WebSocket for control and update frames, HTTP for models.
pub trait ClientTransport {
    /// Sends one text frame (a JSON control message).
    fn send_text(&mut self, text: String) -> impl Future<Output = Result<(), BoxError>>;

    /// Sends one binary frame (a chunk of an update).
    fn send_binary(&mut self, frame: Vec<u8>) -> impl Future<Output = Result<(), BoxError>>;

    /// Next text frame from the server; `None` once the connection is closed.
    fn recv_text(&mut self) -> impl Future<Output = Result<Option<String>, BoxError>>;

    /// Downloads the global trainable tensors of `version` as safetensors bytes (`GET /model/{version}`,
    /// authorised by the session token from the admission).
    fn fetch_model(&mut self, version: u64, session: &str) -> impl Future<Output = Result<Vec<u8>, BoxError>>;

    /// Downloads the chain of deltas taking the global model of version `from` to `version`
    /// (`GET /model/{version}/deltas/{from}`, authorised by the session token).
    fn fetch_model_deltas(
        &mut self,
        version: u64,
        from: u64,
        session: &str,
    ) -> impl Future<Output = Result<Vec<u8>, BoxError>>;

    /// Downloads this client's SCAFFOLD correction for `round` as safetensors bytes (`GET /scaffold/{round}`,
    /// authorised by the session token).
    fn fetch_correction(&mut self, round: u64, session: &str) -> impl Future<Output = Result<Vec<u8>, BoxError>>;

    /// Uploads a rollout video of `round` (`POST /rollout/{round}/{file_name}`, authorised by the session
    /// token).
    fn upload_video(&mut self, round: u64, session: &str, video: Video) -> impl Future<Output = Result<(), BoxError>>;

    /// Seconds on a monotonic clock (`performance.now()` in browsers).
    fn now_seconds(&self) -> f64;
}

/// Who a volunteer says it is on a new connection, beside its key.
#[derive(Debug, Clone, PartialEq)]
pub struct Introduction {
    pub name: String,
    /// The run's auth token, for a run that has one.
    pub auth_token: Option<String>,
    /// A shard it asks for (granted when no other key holds it); `None`: the one bound to its key, or the next.
    pub shard: Option<u32>,
    /// It trains on its own dataset, not on a server shard.
    pub own_dataset: bool,
}

/// What the server grants a proven volunteer: its id, the session every download and upload presents, and its
/// setup (its shard, the policy, where the weights are).
#[derive(Debug, Clone, PartialEq)]
pub struct Admission {
    pub client_id: u64,
    pub session: String,
    pub setup: VolunteerSetup,
}

/// What the round loop needs beside the transport and the trainer.
#[derive(Debug, Clone, PartialEq)]
pub struct ClientOptions {
    /// The admission's session.
    pub session: String,
    /// What the client tells the server of its data on join (see [`DataReport`]).
    pub data: Option<DataReport>,
}

/// Progress notifications, for progress bars and logs.
#[derive(Debug, Clone, PartialEq)]
pub enum ClientEvent {
    Joined {
        client_id: u64,
    },
    Task {
        round: u64,
        local_steps: u32,
    },
    Trained {
        round: u64,
        examples: u64,
        train_loss: f64,
    },
    /// An update went out: its bytes, and everything sent and received since joining.
    Uploaded {
        round: u64,
        bytes: u64,
        total_up: u64,
        total_down: u64,
    },
    RolledOut {
        round: u64,
        episodes: u32,
        successes: u32,
    },
    RoundClosed {
        round: u64,
        accepted: bool,
    },
    Refused {
        code: ErrorCode,
        message: String,
    },
}

/// What a client did over a run.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct ClientSummary {
    pub client_id: u64,
    pub rounds_trained: u64,
    pub bytes_up: u64,
    pub bytes_down: u64,
    /// Non-fatal refusals from the server (e.g. a stale update).
    pub refusals: Vec<(ErrorCode, String)>,
}

#[derive(Debug, thiserror::Error)]
pub enum ClientError {
    #[error("transport: {0}")]
    Transport(BoxError),
    #[error("local trainer: {0}")]
    Trainer(BoxError),
    #[error("server refused ({}): {message}", code.as_str())]
    Refused { code: ErrorCode, message: String },
    #[error("protocol: {0}")]
    Protocol(String),
    #[error("global model version {version}: {source}")]
    Model { version: u64, source: TensorError },
    #[error("global model version {version} from the deltas since version {from}: {source}")]
    ModelDeltas { version: u64, from: u64, source: CodecError },
    #[error(
        "global model version {version} rebuilt from the deltas since version {from} has checksum {got:#010x}, the \
         server's {expected:#010x}"
    )]
    ModelChecksum { version: u64, from: u64, expected: u32, got: u32 },
    #[error("SCAFFOLD correction of round {round}: {source}")]
    Correction { round: u64, source: TensorError },
    #[error("connection closed before the run finished")]
    Closed,
}

/// Answers the server's challenge on a fresh connection with `identity`'s proof and `intro`, and returns the
/// admission (refusing a server of another protocol version). The client then downloads what its setup names,
/// with the admission's session, and joins with [`run_client`].
pub async fn identify<T: ClientTransport>(
    transport: &mut T,
    identity: &Identity,
    intro: &Introduction,
) -> Result<Admission, ClientError> {
    let mut link = Link { transport, bytes_up: 0, bytes_down: 0 };
    let nonce = match link.recv().await? {
        ServerMessage::Challenge { nonce } => nonce,
        other => return Err(unexpected("a challenge", other)),
    };
    link.send(&ClientMessage::Identify {
        protocol_version: PROTOCOL_VERSION,
        auth_token: intro.auth_token.clone(),
        name: intro.name.clone(),
        public_key: identity.public_key_hex(),
        signature: identity.prove(&nonce, &intro.name),
        shard: intro.shard,
        own_dataset: intro.own_dataset,
    })
    .await?;
    let (client_id, session, setup) = match link.recv().await? {
        ServerMessage::Admitted { client_id, session, setup } => (client_id, session, setup),
        other => return Err(unexpected("the admission", other)),
    };
    if setup.protocol_version != PROTOCOL_VERSION {
        return Err(ClientError::Protocol(format!(
            "the server speaks protocol {}, this client {PROTOCOL_VERSION}: update the client",
            setup.protocol_version
        )));
    }
    Ok(Admission { client_id, session, setup: *setup })
}

/// The error for `got` where `expected` should have come: the server's refusal, or a protocol error.
fn unexpected(expected: &str, got: ServerMessage) -> ClientError {
    match got {
        ServerMessage::Error { code, message } => ClientError::Refused { code, message },
        other => ClientError::Protocol(format!("expected {expected}, got {other:?}")),
    }
}

/// Joins on a connection [`identify`] admitted, then for each task: fetches the model if its version changed (as
/// the deltas from the version it holds where the task offers them, else whole), trains, uploads the update and
/// metrics. Returns when the server says the run is finished.
pub async fn run_client<T: ClientTransport, L: LocalTrainer>(
    transport: &mut T,
    trainer: &mut L,
    options: &ClientOptions,
    mut on_event: impl FnMut(ClientEvent),
) -> Result<ClientSummary, ClientError> {
    let mut link = Link { transport, bytes_up: 0, bytes_down: 0 };
    link.send(&ClientMessage::Join { capabilities: trainer.capabilities(), data: options.data.clone() }).await?;
    let (client_id, max_frame_bytes) = match link.recv().await? {
        ServerMessage::Welcome { client_id, max_frame_bytes, .. } => (client_id, max_frame_bytes as usize),
        other => return Err(unexpected("welcome", other)),
    };
    let session = &options.session;
    on_event(ClientEvent::Joined { client_id });
    let mut summary = ClientSummary { client_id, ..ClientSummary::default() };
    let mut global: Option<(u64, NamedTensors)> = None;
    let mut encoder = UpdateEncoder::default();
    loop {
        match link.recv().await? {
            ServerMessage::RoundTask(task) => {
                on_event(ClientEvent::Task { round: task.round, local_steps: task.local_steps });
                let start = link.transport.now_seconds();
                let bytes_before = link.bytes_up;
                let down_before = link.bytes_down;
                let version = task.model_version;
                let tensors = match (global.take(), task.model_deltas) {
                    (Some((held, tensors)), _) if held == version => tensors,
                    (Some((held, tensors)), Some(deltas)) if (deltas.since..version).contains(&held) => {
                        link.fetch_model_deltas(version, (held, &tensors), deltas, session).await?
                    }
                    _ => link.fetch_model(version, session).await?,
                };
                let download_bytes = link.bytes_down - down_before;
                trainer.set_global(&tensors).map_err(ClientError::Trainer)?;
                let global = &global.insert((task.model_version, tensors)).1;
                let correction = match task.strategy.control_variates {
                    true => link.fetch_correction(task.round, session).await?,
                    false => NamedTensors::new(),
                };
                trainer.set_correction(&correction).map_err(ClientError::Trainer)?;
                if task.eval_request {
                    let eval = trainer.evaluate().await.map_err(ClientError::Trainer)?;
                    link.send(&ClientMessage::EvalResult {
                        round: task.round,
                        examples: eval.examples,
                        loss: eval.loss,
                    })
                    .await?;
                }
                if let Some(request) = &task.rollout {
                    let outputs = trainer.rollout(request).await.map_err(ClientError::Trainer)?;
                    let mut episodes = Vec::with_capacity(outputs.len());
                    for RolloutOutput { mut episode, video } in outputs {
                        if let Some(video) = video {
                            episode.video = Some(video.file_name.clone());
                            link.bytes_up += video.bytes.len() as u64;
                            link.transport
                                .upload_video(task.round, session, video)
                                .await
                                .map_err(ClientError::Transport)?;
                        }
                        episodes.push(episode);
                    }
                    on_event(ClientEvent::RolledOut {
                        round: task.round,
                        episodes: episodes.len() as u32,
                        successes: episodes.iter().filter(|e| e.success).count() as u32,
                    });
                    link.send(&ClientMessage::RolloutResult {
                        round: task.round,
                        model_version: task.model_version,
                        episodes,
                    })
                    .await?;
                }
                let TrainOutput { update, examples, train_loss } =
                    trainer.train(&task).await.map_err(ClientError::Trainer)?;
                on_event(ClientEvent::Trained { round: task.round, examples, train_loss });
                let payload = encoder.payload(&update, global, task.update_encoding).map_err(|e| {
                    ClientError::Trainer(format!("the trained tensors do not match the global model: {e}").into())
                })?;
                // The payload is all that is sent: at full size the trained tensors are another 0.4 GB.
                drop(update);
                link.send(&ClientMessage::UpdateHeader {
                    round: task.round,
                    examples,
                    train_loss,
                    payload_bytes: payload.len() as u64,
                })
                .await?;
                for frame in encode_frames(&payload, task.round, max_frame_bytes) {
                    link.bytes_up += frame.len() as u64;
                    link.transport.send_binary(frame).await.map_err(ClientError::Transport)?;
                }
                on_event(ClientEvent::Uploaded {
                    round: task.round,
                    bytes: link.bytes_up - bytes_before,
                    total_up: link.bytes_up,
                    total_down: link.bytes_down,
                });
                let seconds = link.transport.now_seconds() - start;
                let metrics = RoundMetrics {
                    round: task.round,
                    examples,
                    train_loss,
                    seconds,
                    bytes_up: link.bytes_up,
                    bytes_down: link.bytes_down,
                    download_bytes,
                };
                link.send(&ClientMessage::Metrics(metrics)).await?;
                summary.rounds_trained += 1;
            }
            ServerMessage::NormStats(stats) => {
                trainer.set_norm_stats(&stats).map_err(ClientError::Trainer)?;
            }
            ServerMessage::RoundClosed { round, accepted, .. } => {
                on_event(ClientEvent::RoundClosed { round, accepted });
            }
            ServerMessage::Error { code, message } if code.is_fatal() => {
                return Err(ClientError::Refused { code, message });
            }
            ServerMessage::Error { code, message } => {
                on_event(ClientEvent::Refused { code, message: message.clone() });
                summary.refusals.push((code, message));
            }
            ServerMessage::Finished { .. } => {
                summary.bytes_up = link.bytes_up;
                summary.bytes_down = link.bytes_down;
                return Ok(summary);
            }
            other @ (ServerMessage::Welcome { .. }
            | ServerMessage::Challenge { .. }
            | ServerMessage::Admitted { .. }) => {
                return Err(ClientError::Protocol(format!("unexpected {other:?}")));
            }
        }
    }
}

/// A client's updates across rounds: the trained tensors as each task's encoding asks, and top-k's residual (what
/// earlier rounds left out), added to the next round's delta so that nothing is lost for good (error feedback).
#[derive(Debug, Default)]
struct UpdateEncoder {
    residual: Option<NamedTensors>,
}

impl UpdateEncoder {
    fn payload(
        &mut self,
        trained: &NamedTensors,
        global: &NamedTensors,
        encoding: UpdateEncoding,
    ) -> Result<Vec<u8>, TensorError> {
        if encoding == UpdateEncoding::F32 {
            self.residual = None;
            return Ok(encode_payload(trained));
        }
        let mut delta = trained.zip_map(global, |t, g| t - g)?;
        let feedback = matches!(encoding, UpdateEncoding::Topk { .. });
        if let Some(residual) = self.residual.as_ref().filter(|_| feedback) {
            delta = delta.zip_map(residual, |d, r| d + r)?;
        }
        let payload = encode_delta_payload(&mut delta, encoding);
        self.residual = feedback.then_some(delta);
        Ok(payload)
    }
}

/// A transport with byte counters and JSON on top.
struct Link<'a, T> {
    transport: &'a mut T,
    bytes_up: u64,
    bytes_down: u64,
}

impl<T: ClientTransport> Link<'_, T> {
    async fn send(&mut self, msg: &ClientMessage) -> Result<(), ClientError> {
        let text = serde_json::to_string(msg).expect("client messages serialize");
        self.bytes_up += text.len() as u64;
        self.transport.send_text(text).await.map_err(ClientError::Transport)
    }

    async fn recv(&mut self) -> Result<ServerMessage, ClientError> {
        let text = self.transport.recv_text().await.map_err(ClientError::Transport)?.ok_or(ClientError::Closed)?;
        self.bytes_down += text.len() as u64;
        serde_json::from_str(&text).map_err(|e| ClientError::Protocol(format!("bad server message: {e}")))
    }

    async fn fetch_model(&mut self, version: u64, session: &str) -> Result<NamedTensors, ClientError> {
        let bytes = self.transport.fetch_model(version, session).await.map_err(ClientError::Transport)?;
        self.bytes_down += bytes.len() as u64;
        checked_tensors(&bytes).map_err(|source| ClientError::Model { version, source })
    }

    /// The model of `version` from the one held (its version and tensors) and the deltas between them, checked
    /// against the server's checksum of it.
    async fn fetch_model_deltas(
        &mut self,
        version: u64,
        (from, held): (u64, &NamedTensors),
        deltas: ModelDeltas,
        session: &str,
    ) -> Result<NamedTensors, ClientError> {
        let chain = self.transport.fetch_model_deltas(version, from, session).await.map_err(ClientError::Transport)?;
        self.bytes_down += chain.len() as u64;
        let model = apply_model_deltas(held, from, version, &chain).map_err(|source| ClientError::ModelDeltas {
            version,
            from,
            source,
        })?;
        match model.checksum() {
            got if got == deltas.checksum => Ok(model),
            got => Err(ClientError::ModelChecksum { version, from, expected: deltas.checksum, got }),
        }
    }

    async fn fetch_correction(&mut self, round: u64, session: &str) -> Result<NamedTensors, ClientError> {
        let bytes = self.transport.fetch_correction(round, session).await.map_err(ClientError::Transport)?;
        self.bytes_down += bytes.len() as u64;
        checked_tensors(&bytes).map_err(|source| ClientError::Correction { round, source })
    }
}

/// Downloaded safetensors bytes as tensors, every value checked (finite, lengths matching shapes).
fn checked_tensors(bytes: &[u8]) -> Result<NamedTensors, TensorError> {
    let tensors = NamedTensors::from_safetensors(bytes)?;
    tensors.validate(&tensors.spec())?;
    Ok(tensors)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::codec::{UpdateValues, decode_payload};

    /// Top-k's error feedback over three rounds: whatever a round leaves out goes out later, so what the server
    /// received plus the client's residual is exactly the sum of the rounds' deltas.
    #[test]
    fn topk_error_feedback_carries_what_each_round_left_out() {
        let mut global = NamedTensors::new();
        global.insert("w", vec![8], vec![0.0; 8]).unwrap();
        let step = [0.8f32, 0.1, -0.05, 0.3, 0.02, -0.6, 0.2, 0.01];
        let encoding = UpdateEncoding::Topk { fraction: 0.25 };
        let mut encoder = UpdateEncoder::default();
        let mut received = vec![0f32; 8];
        let mut sent_indices = Vec::new();
        for round in 1..=3 {
            let mut trained = global.clone();
            for (t, s) in trained.get_mut("w").unwrap().values.iter_mut().zip(step) {
                *t += s;
            }
            let payload = encoder.payload(&trained, &global, encoding).unwrap();
            let Ok(UpdateValues::Delta(delta)) = decode_payload(&payload, &global.spec(), encoding) else {
                panic!("round {round}: top-k sends a delta")
            };
            let values = &delta.get("w").unwrap().values;
            sent_indices.push((0..8).filter(|&i| values[i] != 0.0).collect::<Vec<_>>());
            for (r, d) in received.iter_mut().zip(values) {
                *r += d;
            }
            let residual = &encoder.residual.as_ref().unwrap().get("w").unwrap().values;
            for i in 0..8 {
                let total = step[i] * round as f32;
                assert!((received[i] + residual[i] - total).abs() < 1e-6, "round {round}, value {i}");
            }
        }
        // Round 1 sends the two largest; the small values' residuals grow until they are sent too.
        assert_eq!(sent_indices[0], [0, 5]);
        assert_ne!(sent_indices[1], sent_indices[0]);
        // Another encoding drops the residual: it only ever belongs to top-k.
        encoder.payload(&global, &global, UpdateEncoding::Int8).unwrap();
        assert!(encoder.residual.is_none());
    }
}
