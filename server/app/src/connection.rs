//! One client's WebSocket: the identity handshake (a fresh challenge, the client's signed answer, its admission
//! with a session bound to its key's shard and its setup), the join once it has downloaded what it needs, control
//! messages, update reassembly and validation. Generic over Sink/Stream so it runs over channels in unit tests.
//! Bad input is answered with an `Error` message to this client and counted by the coordinator; only fatal errors
//! close the connection (and any error before the join). The bounds of [`crate::bounds`] apply here: admissions
//! per address, messages per second; and the upload budget ([`fedvla_aggregator::upload_budget`]): an update that
//! does not fit waits, its frames left unread in the socket, until the updates ahead of it are taken by the
//! coordinator (at most a round's deadline, then it is refused), and its own reservation goes with it to the
//! coordinator.

use std::fmt::Display;
use std::net::IpAddr;
use std::sync::Arc;
use std::time::Duration;

use axum::extract::ws::Message;
use fedvla_aggregator::records::DataSource;
use fedvla_aggregator::registry::ShardBinding;
use fedvla_federation::codec::decode_payload;
use fedvla_federation::identity::{NONCE_BYTES, to_hex, verify_proof};
use fedvla_federation::{
    ClientMessage, CodecError, ErrorCode, NormalizationStats, PROTOCOL_VERSION, Reassembler, ServerMessage,
    UpdateValues,
};
use futures_util::{Sink, SinkExt, Stream, StreamExt};
use tokio::sync::mpsc;

use fedvla_aggregator::coordinator::{Event, UpdateReceived};
use fedvla_aggregator::sessions::{random_hex, same_secret};
use fedvla_aggregator::upload_budget::Reservation;

use crate::bounds::MessageRate;
use crate::state::SocketState;
use crate::volunteer;

/// A connection that has not identified by then is closed.
const IDENTIFY_TIMEOUT: Duration = Duration::from_secs(30);

/// An admitted connection that has not joined by then is closed: long enough for a first visit's downloads (the
/// frozen weights) over a slow line; the connection is pinged meanwhile.
const JOIN_TIMEOUT: Duration = Duration::from_secs(3600);

/// Serves one connection from `peer` until the client leaves, a fatal error, or shutdown.
pub async fn handle_socket<S, R, E>(sink: S, mut stream: R, state: SocketState, peer: IpAddr)
where
    S: Sink<Message> + Unpin,
    S::Error: Display,
    R: Stream<Item = Result<Message, E>> + Unpin,
    E: Display,
{
    let rate = MessageRate::new(state.messages_per_second);
    let mut conn = Connection { sink, state, client_id: None, upload: Upload::Idle, rate };
    let Some(admission) = conn.admit(&mut stream, peer).await else {
        conn.close().await;
        return;
    };
    let client_id = admission.client_id;
    // A ping keeps an idle connection (a volunteer downloading, or waiting for its next round) open through proxies
    // that close silent ones, and through the listener's idle timeout; browsers and tungstenite answer pings by
    // themselves.
    let every = conn.state.keepalive;
    let mut keepalive = tokio::time::interval_at(tokio::time::Instant::now() + every, every);
    let Some(mut outbox) = conn.join(&mut stream, admission, &mut keepalive).await else {
        conn.state.sessions.close(client_id);
        conn.close().await;
        return;
    };
    loop {
        // Biased: messages the coordinator queued (e.g. `Finished`) go out before a shutdown closes the socket.
        let flow = tokio::select! {
            biased;
            msg = outbox.recv() => match msg {
                Some(msg) => conn.send(&msg).await,
                None => Flow::Close,
            },
            () = conn.state.cancel.cancelled() => {
                conn.send(&ServerMessage::Error { code: ErrorCode::ShuttingDown, message: "server shutting down".into() }).await;
                Flow::Close
            }
            _ = keepalive.tick() => conn.ping().await,
            frame = stream.next() => match frame {
                Some(Ok(Message::Text(text))) => conn.on_text(text.as_str()).await,
                Some(Ok(Message::Binary(data))) => conn.on_binary(&data).await,
                Some(Ok(Message::Ping(_) | Message::Pong(_))) => Flow::Continue,
                Some(Ok(Message::Close(_))) | None => Flow::Gone,
                Some(Err(e)) => {
                    tracing::info!(client_id, error = %e, "websocket error");
                    Flow::Gone
                }
            },
        };
        match flow {
            Flow::Continue => {}
            Flow::Close => {
                conn.close().await;
                break;
            }
            Flow::Gone => break,
        }
    }
    tracing::info!(client_id, "client left");
    conn.state.sessions.close(client_id);
    conn.state.events.send(Event::Left { client_id }).await.ok();
}

enum Flow {
    Continue,
    /// Close our side (after a fatal error or at shutdown).
    Close,
    /// The client closed or the socket broke.
    Gone,
}

/// Where an upload stands.
enum Upload {
    Idle,
    Receiving {
        header: AnnouncedUpdate,
        reassembler: Option<Reassembler>,
        bytes: u64,
        /// The announced size, held in the upload budget until the coordinator has taken the decoded update (or it
        /// is refused).
        reservation: Reservation,
    },
    /// A refused update: its remaining frames are dropped silently until the next control message.
    Discarding,
}

/// A proven client, admitted but not yet joined.
struct Admission {
    client_id: u64,
    name: String,
    public_key: String,
    /// The shard bound to its key; `None` for a volunteer on its own dataset or a workload without shards.
    shard: Option<ShardBinding>,
    own_dataset: bool,
}

#[derive(Clone, Copy)]
struct AnnouncedUpdate {
    round: u64,
    examples: u64,
    train_loss: f64,
    payload_bytes: u64,
}

struct Connection<S> {
    sink: S,
    state: SocketState,
    client_id: Option<u64>,
    upload: Upload,
    rate: MessageRate,
}

impl<S> Connection<S>
where
    S: Sink<Message> + Unpin,
    S::Error: Display,
{
    /// Challenges the client, waits for its `Identify`, checks `peer`'s admission rate, the version, the token and
    /// the signature, has the registry admit the key, and answers with the session and the setup.
    async fn admit<R, E>(&mut self, stream: &mut R, peer: IpAddr) -> Option<Admission>
    where
        R: Stream<Item = Result<Message, E>> + Unpin,
    {
        let nonce = random_hex::<NONCE_BYTES>();
        if !matches!(self.send(&ServerMessage::Challenge { nonce: nonce.clone() }).await, Flow::Continue) {
            return None;
        }
        let text = tokio::select! {
            () = self.state.cancel.cancelled() => return None,
            () = tokio::time::sleep(IDENTIFY_TIMEOUT) => {
                self.refuse(ErrorCode::UnexpectedMessage, format!("no identify within {IDENTIFY_TIMEOUT:?}")).await;
                return None;
            }
            frame = stream.next() => match frame {
                Some(Ok(Message::Text(text))) => text,
                Some(Ok(Message::Close(_)) | Err(_)) | None => return None,
                Some(Ok(_)) => {
                    self.refuse(ErrorCode::UnexpectedMessage, "the first message must be an identify".into()).await;
                    return None;
                }
            },
        };
        // Before anything else of the message is looked at, so that guessing tokens, names or keys costs
        // admissions too.
        if !self.state.joins.allow(peer) {
            self.refuse(ErrorCode::JoinRateLimited, format!("{peer} has joined too often in the last minute")).await;
            return None;
        }
        let (name, public_key, shard, own_dataset) = match serde_json::from_str::<ClientMessage>(text.as_str()) {
            Ok(ClientMessage::Identify {
                protocol_version,
                auth_token,
                name,
                public_key,
                signature,
                shard,
                own_dataset,
            }) => {
                if protocol_version != PROTOCOL_VERSION {
                    let message =
                        format!("client speaks protocol version {protocol_version}, server speaks {PROTOCOL_VERSION}");
                    self.refuse(ErrorCode::ProtocolVersion, message).await;
                    return None;
                }
                if let Some(expected) = &self.state.auth_token
                    && !auth_token.as_deref().is_some_and(|token| same_secret(token, expected))
                {
                    self.refuse(ErrorCode::Unauthorized, "missing or wrong auth token".into()).await;
                    return None;
                }
                match verify_proof(&public_key, &signature, &nonce, &name) {
                    // The key as the registry spells it (lowercase hex), whatever case the client wrote.
                    Ok(key) => (name, to_hex(&key), shard, own_dataset),
                    Err(e) => {
                        self.refuse(ErrorCode::Unauthorized, format!("identity not proven: {e}")).await;
                        return None;
                    }
                }
            }
            // What a client of protocol 5 or before sends first.
            Ok(ClientMessage::Join { .. }) => {
                let message = format!(
                    "this server speaks protocol {PROTOCOL_VERSION}, whose connections begin with an identify: \
                     update the client"
                );
                self.refuse(ErrorCode::ProtocolVersion, message).await;
                return None;
            }
            Ok(other) => {
                let message = format!("the first message must be an identify, got {other:?}");
                self.refuse(ErrorCode::UnexpectedMessage, message).await;
                return None;
            }
            Err(e) => {
                self.refuse(ErrorCode::MalformedMessage, format!("bad identify message: {e}")).await;
                return None;
            }
        };
        let admitted = match self.state.volunteers.admit(&public_key, &name, shard, own_dataset) {
            Ok(admitted) => admitted,
            Err(e) => {
                self.refuse(e.code(), e.to_string()).await;
                return None;
            }
        };
        if admitted.persist
            && let Err(e) = volunteer::persist(&self.state.volunteers).await
        {
            tracing::error!(error = %e, "the volunteer registry could not be saved; refusing the admission");
            self.refuse(ErrorCode::ShuttingDown, "the server cannot save its volunteer registry".into()).await;
            return None;
        }
        let client_id = admitted.client_id;
        self.client_id = Some(client_id);
        let session = self.state.sessions.open(client_id, admitted.shard.map(|s| s.index));
        let setup = Box::new(self.state.volunteers.setup(admitted.shard, self.state.model.borrow().version));
        tracing::info!(client_id, %name, %public_key, shard = ?admitted.shard, "client admitted");
        match self.send(&ServerMessage::Admitted { client_id, session, setup }).await {
            Flow::Continue => Some(Admission { client_id, name, public_key, shard: admitted.shard, own_dataset }),
            Flow::Close | Flow::Gone => {
                self.state.sessions.close(client_id);
                None
            }
        }
    }

    /// Waits (pinging) for the admitted client's `Join`, checks its data against its admission and the run,
    /// registers with the coordinator and welcomes the client.
    async fn join<R, E>(
        &mut self,
        stream: &mut R,
        admission: Admission,
        keepalive: &mut tokio::time::Interval,
    ) -> Option<mpsc::UnboundedReceiver<ServerMessage>>
    where
        R: Stream<Item = Result<Message, E>> + Unpin,
    {
        let deadline = tokio::time::sleep(JOIN_TIMEOUT);
        tokio::pin!(deadline);
        let (capabilities, report) = loop {
            let text = tokio::select! {
                () = self.state.cancel.cancelled() => return None,
                () = &mut deadline => {
                    self.refuse(ErrorCode::UnexpectedMessage, format!("no join within {JOIN_TIMEOUT:?}")).await;
                    return None;
                }
                _ = keepalive.tick() => match self.ping().await {
                    Flow::Continue => continue,
                    Flow::Close | Flow::Gone => return None,
                },
                frame = stream.next() => match frame {
                    Some(Ok(Message::Text(text))) => text,
                    Some(Ok(Message::Ping(_) | Message::Pong(_))) => continue,
                    Some(Ok(Message::Close(_)) | Err(_)) | None => return None,
                    Some(Ok(Message::Binary(_))) => {
                        self.refuse(ErrorCode::UnexpectedMessage, "a binary frame before the join".into()).await;
                        return None;
                    }
                },
            };
            if !self.rate.allow() {
                self.refuse_rate().await;
                return None;
            }
            match serde_json::from_str::<ClientMessage>(text.as_str()) {
                Ok(ClientMessage::Heartbeat) => {}
                Ok(ClientMessage::Join { capabilities, data }) => break (capabilities, data),
                Ok(other) => {
                    let message = format!("an admitted client joins before anything else, got {other:?}");
                    self.refuse(ErrorCode::UnexpectedMessage, message).await;
                    return None;
                }
                Err(e) => {
                    self.refuse(ErrorCode::MalformedMessage, format!("bad join message: {e}")).await;
                    return None;
                }
            }
        };
        // Moments that could never combine are refused now, not when the run agrees its statistics.
        if let Some(Err(e)) = report.as_ref().map(|d| NormalizationStats::combine(&[d])) {
            self.refuse(ErrorCode::MalformedMessage, format!("the join's data moments: {e}")).await;
            return None;
        }
        let Admission { client_id, name, public_key, shard, own_dataset } = admission;
        let data = match (own_dataset, report.as_ref().and_then(|r| r.own.as_ref())) {
            (false, None) => shard.map(|s| DataSource::Shard { index: s.index, examples: s.train_examples }),
            (true, Some(own)) => match self.state.volunteers.own_data(own) {
                Ok(data) => Some(data),
                Err(e) => {
                    self.refuse(e.code(), e.to_string()).await;
                    return None;
                }
            },
            (admitted_for_own, _) => {
                let message = match admitted_for_own {
                    true => "admitted for an own dataset, the join reports none",
                    false => "admitted for a server shard, the join reports an own dataset",
                };
                self.refuse(ErrorCode::IncompatibleDataset, message.into()).await;
                return None;
            }
        };
        let (outbox, inbox) = mpsc::unbounded_channel();
        tracing::info!(client_id, %name, ?data, backend = %capabilities.backend, "client joined");
        let report = report.map(Box::new);
        let joined = Event::Joined { client_id, name, public_key, capabilities, data, report, outbox };
        if self.state.events.send(joined).await.is_err() {
            return None;
        }
        let welcome = ServerMessage::Welcome {
            client_id,
            protocol_version: PROTOCOL_VERSION,
            max_frame_bytes: self.state.limits.max_frame_bytes as u32,
        };
        match self.send(&welcome).await {
            Flow::Continue => Some(inbox),
            Flow::Close | Flow::Gone => {
                self.state.events.send(Event::Left { client_id }).await.ok();
                None
            }
        }
    }

    async fn on_text(&mut self, text: &str) -> Flow {
        let client_id = self.client_id.expect("joined");
        if !self.rate.allow() {
            return self.refuse_rate().await;
        }
        if matches!(self.upload, Upload::Receiving { .. }) {
            self.upload = Upload::Idle;
            return self.refuse(ErrorCode::MalformedFrame, "control message in the middle of an update".into()).await;
        }
        self.upload = Upload::Idle;
        let msg = match serde_json::from_str::<ClientMessage>(text) {
            Ok(msg) => msg,
            Err(e) => {
                return self.refuse(ErrorCode::MalformedMessage, format!("bad control message: {e}")).await;
            }
        };
        let event = match msg {
            ClientMessage::Identify { .. } | ClientMessage::Join { .. } => {
                return self.refuse(ErrorCode::UnexpectedMessage, "already joined".into()).await;
            }
            ClientMessage::Heartbeat => {
                tracing::trace!(client_id, "heartbeat");
                return Flow::Continue;
            }
            ClientMessage::UpdateHeader { round, examples, train_loss, payload_bytes } => {
                let limit = self.state.limits.max_payload_bytes;
                // A refused update's frames are still on their way: dropped silently, not refused one by one.
                if payload_bytes > limit {
                    self.upload = Upload::Discarding;
                    return self.refuse_codec(CodecError::Oversized { len: payload_bytes, limit }).await;
                }
                // Back-pressure: while the budget is taken, this connection reads nothing more (its frames wait in
                // the socket, then in the client).
                let wait = self.state.upload_wait;
                let reserved = tokio::select! {
                    () = self.state.cancel.cancelled() => None,
                    reserved = tokio::time::timeout(wait, self.state.uploads.reserve_when_free(payload_bytes)) => {
                        reserved.ok().flatten()
                    }
                };
                let Some(reservation) = reserved else {
                    self.upload = Upload::Discarding;
                    let message = format!(
                        "an update of {payload_bytes} bytes found no room within {wait:?} in the {} bytes held for \
                         uploads in flight",
                        self.state.uploads.limit()
                    );
                    return self.refuse(ErrorCode::UploadBudget, message).await;
                };
                let header = AnnouncedUpdate { round, examples, train_loss, payload_bytes };
                self.upload = Upload::Receiving { header, reassembler: None, bytes: 0, reservation };
                // For the console's client table: training is over, the update is on its way.
                return self.emit(Event::Uploading { client_id }).await;
            }
            ClientMessage::Metrics(metrics) => Event::Metrics { client_id, metrics },
            ClientMessage::RolloutResult { round, model_version, episodes } => {
                Event::RolloutResult { client_id, round, model_version, episodes }
            }
            ClientMessage::EvalResult { round, examples, loss } => {
                Event::EvalResult { client_id, round, examples, loss }
            }
        };
        self.emit(event).await
    }

    async fn on_binary(&mut self, frame: &[u8]) -> Flow {
        let Upload::Receiving { header, reassembler, bytes, .. } = &mut self.upload else {
            if matches!(self.upload, Upload::Discarding) {
                return Flow::Continue;
            }
            // An update's own frames are bounded by its announced size; stray ones count as messages.
            if !self.rate.allow() {
                return self.refuse_rate().await;
            }
            return self.refuse(ErrorCode::UnexpectedMessage, "binary frame without an update header".into()).await;
        };
        let header = *header;
        *bytes += frame.len() as u64;
        let pushed = match reassembler {
            Some(r) => r.push(frame),
            None => Reassembler::start(frame, self.state.limits).and_then(|r| {
                let first = r.header();
                if first.round != header.round || first.payload_len != header.payload_bytes {
                    return Err(CodecError::Malformed(format!(
                        "frames carry round {} and {} bytes, the update header announced round {} and {} bytes",
                        first.round, first.payload_len, header.round, header.payload_bytes
                    )));
                }
                *reassembler = Some(r);
                Ok(())
            }),
        };
        if let Err(e) = pushed {
            return self.refuse_codec(e).await;
        }
        if !reassembler.as_ref().is_some_and(Reassembler::is_complete) {
            return Flow::Continue;
        }
        let bytes = *bytes;
        // The reservation goes with the decoded update to the coordinator, or ends here if it is refused.
        let Upload::Receiving { reassembler: Some(reassembler), reservation, .. } =
            std::mem::replace(&mut self.upload, Upload::Idle)
        else {
            unreachable!("checked above")
        };
        let (spec, encoding) = (Arc::clone(&self.state.spec), self.state.encoding);
        let decoded = tokio::task::spawn_blocking(move || -> Result<UpdateValues, CodecError> {
            decode_payload(&reassembler.finish()?, &spec, encoding)
        })
        .await
        .expect("decoding does not panic");
        match decoded {
            Ok(values) => {
                let client_id = self.client_id.expect("joined");
                tracing::debug!(client_id, round = header.round, bytes, "update received");
                let update = UpdateReceived {
                    round: header.round,
                    values,
                    claimed_examples: header.examples,
                    train_loss: header.train_loss,
                    bytes,
                    reservation,
                };
                self.emit(Event::Update { client_id, update: Box::new(update) }).await
            }
            Err(e) => self.refuse_codec(e).await,
        }
    }

    async fn refuse_rate(&mut self) -> Flow {
        let message = format!("more than {} messages a second", self.state.messages_per_second);
        self.refuse(ErrorCode::MessageRateLimited, message).await
    }

    async fn refuse_codec(&mut self, e: CodecError) -> Flow {
        self.refuse(e.code(), e.to_string()).await
    }

    /// Sends an error to this client, has the coordinator count it, and closes only on fatal errors.
    async fn refuse(&mut self, code: ErrorCode, message: String) -> Flow {
        tracing::warn!(client_id = ?self.client_id, code = code.as_str(), %message, "refused client input");
        if !matches!(self.upload, Upload::Idle) {
            self.upload = Upload::Discarding;
        }
        self.emit(Event::Rejected { client_id: self.client_id, code }).await;
        let flow = self.send(&ServerMessage::Error { code, message }).await;
        if code.is_fatal() { Flow::Close } else { flow }
    }

    async fn emit(&mut self, event: Event) -> Flow {
        match self.state.events.send(event).await {
            Ok(()) => Flow::Continue,
            Err(_) => Flow::Close,
        }
    }

    async fn send(&mut self, msg: &ServerMessage) -> Flow {
        let text = serde_json::to_string(msg).expect("server messages serialize");
        match self.sink.send(Message::Text(text.into())).await {
            Ok(()) => Flow::Continue,
            Err(e) => {
                tracing::info!(client_id = ?self.client_id, error = %e, "send failed");
                Flow::Gone
            }
        }
    }

    async fn ping(&mut self) -> Flow {
        match self.sink.send(Message::Ping(Default::default())).await {
            Ok(()) => Flow::Continue,
            Err(_) => Flow::Gone,
        }
    }

    async fn close(&mut self) {
        self.sink.send(Message::Close(None)).await.ok();
    }
}

#[cfg(test)]
mod tests {
    use std::convert::Infallible;

    use fedvla_aggregator::config::RunConfig;
    use fedvla_aggregator::coordinator::PublishedModel;
    use fedvla_aggregator::registry::{ShardOffer, VolunteerOffer, Volunteers};
    use fedvla_aggregator::run_dir::RunDir;
    use fedvla_aggregator::sessions::Sessions;
    use fedvla_aggregator::upload_budget::UploadBudget;
    use fedvla_federation::codec::{DEFAULT_MAX_FRAME_BYTES, encode_payload, encode_update};
    use fedvla_federation::{Capabilities, Identity, NamedTensors, UpdateEncoding, UpdateLimits};
    use futures_util::{sink, stream};
    use tokio_util::sync::CancellationToken;

    use super::*;
    use crate::bounds::JoinLimiter;

    const KEEPALIVE: Duration = Duration::from_secs(20);

    fn tensors(bias: f32) -> NamedTensors {
        let mut t = NamedTensors::new();
        t.insert("w", vec![2, 2], vec![1.0, 2.0, 3.0, 4.0]).unwrap();
        t.insert("b", vec![1], vec![bias]).unwrap();
        t
    }

    struct Harness {
        /// The global model the harness's server offers, kept so the model channel stays open.
        _model: tokio::sync::watch::Sender<Arc<PublishedModel>>,
        to_server: mpsc::UnboundedSender<Message>,
        from_server: mpsc::UnboundedReceiver<Message>,
        events: mpsc::Receiver<Event>,
        cancel: CancellationToken,
        task: tokio::task::JoinHandle<()>,
        _run_base: tempfile::TempDir,
    }

    impl Harness {
        /// `handle_socket` over in-memory channels instead of a WebSocket.
        fn new() -> Self {
            let (to_server, server_rx) = mpsc::unbounded_channel::<Message>();
            let (server_tx, from_server) = mpsc::unbounded_channel::<Message>();
            let (events_tx, events) = mpsc::channel(16);
            let cancel = CancellationToken::new();
            let run_base = tempfile::tempdir().unwrap();
            let spec = tensors(0.0).spec();
            let run_dir = RunDir::create(run_base.path(), &RunConfig::default()).unwrap();
            let shards = vec![ShardOffer { file: None, train_examples: 5 }];
            let offer = VolunteerOffer::shards_only(fedvla_federation::WorkloadKind::Linreg, shards);
            let (model, model_rx) = tokio::sync::watch::channel(Arc::new(PublishedModel::first(0, Default::default())));
            let state = SocketState {
                events: events_tx,
                cancel: cancel.clone(),
                encoding: UpdateEncoding::F32,
                limits: UpdateLimits::for_spec(&spec, UpdateEncoding::F32, DEFAULT_MAX_FRAME_BYTES, 0),
                keepalive: KEEPALIVE,
                spec: Arc::new(spec),
                auth_token: Some(Arc::from("secret")),
                volunteers: Arc::new(Volunteers::new(offer, run_dir, 16, 0).unwrap()),
                model: model_rx,
                sessions: Sessions::default(),
                joins: JoinLimiter::new(60),
                messages_per_second: 50,
                uploads: UploadBudget::new(1 << 20),
                upload_wait: Duration::from_secs(60),
                sockets: tokio_util::task::TaskTracker::new(),
            };
            let sink = Box::pin(sink::unfold(server_tx, |tx, msg: Message| async move {
                tx.send(msg).ok();
                Ok::<_, Infallible>(tx)
            }));
            let stream = Box::pin(stream::unfold(server_rx, |mut rx| async move {
                rx.recv().await.map(|m| (Ok::<_, Infallible>(m), rx))
            }));
            let task = tokio::spawn(handle_socket(sink, stream, state, IpAddr::from([127, 0, 0, 1])));
            Self { _model: model, to_server, from_server, events, cancel, task, _run_base: run_base }
        }

        fn send(&self, msg: &ClientMessage) {
            self.to_server.send(Message::Text(serde_json::to_string(msg).unwrap().into())).unwrap();
        }

        async fn recv(&mut self) -> Message {
            self.from_server.recv().await.expect("server message")
        }

        async fn recv_control(&mut self) -> ServerMessage {
            match self.recv().await {
                Message::Text(t) => serde_json::from_str(t.as_str()).unwrap(),
                other => panic!("expected text, got {other:?}"),
            }
        }

        /// Answers the challenge with `token` and a proven key; joins once admitted.
        async fn join(&mut self, token: Option<&str>) {
            let ServerMessage::Challenge { nonce } = self.recv_control().await else { panic!("a challenge first") };
            let identity = Identity::from_seed([3; 32]);
            self.send(&ClientMessage::Identify {
                protocol_version: PROTOCOL_VERSION,
                auth_token: token.map(str::to_owned),
                name: "c".into(),
                public_key: identity.public_key_hex(),
                signature: identity.prove(&nonce, "c"),
                shard: None,
                own_dataset: false,
            });
            if token != Some("secret") {
                return;
            }
            assert!(matches!(self.recv_control().await, ServerMessage::Admitted { client_id: 1, .. }));
            self.send(&ClientMessage::Join {
                capabilities: Capabilities { backend: "test".into(), memory_bytes: 0 },
                data: None,
            });
        }

        fn upload(&self, t: &NamedTensors) {
            let payload_bytes = encode_payload(t).len() as u64;
            self.send(&ClientMessage::UpdateHeader { round: 3, examples: 5, train_loss: 0.25, payload_bytes });
            for frame in encode_update(t, 3, 40) {
                self.to_server.send(Message::Binary(frame.into())).unwrap();
            }
        }
    }

    #[tokio::test]
    async fn join_update_refusal_outbox_and_shutdown() {
        let mut h = Harness::new();
        h.join(Some("secret")).await;
        assert!(matches!(h.recv_control().await, ServerMessage::Welcome { client_id: 1, .. }));
        let Some(Event::Joined { client_id: 1, outbox, .. }) = h.events.recv().await else { panic!("joined") };

        h.upload(&tensors(0.5));
        assert!(matches!(h.events.recv().await, Some(Event::Uploading { client_id: 1 })));
        match h.events.recv().await {
            Some(Event::Update { client_id: 1, update }) => {
                assert_eq!(update.values, UpdateValues::Model(tensors(0.5)));
                assert_eq!((update.round, update.claimed_examples, update.train_loss), (3, 5, 0.25));
                let frames = encode_update(&tensors(0.5), 3, 40);
                assert_eq!(update.bytes, frames.iter().map(|f| f.len() as u64).sum::<u64>());
            }
            other => panic!("expected update, got {other:?}"),
        }

        h.upload(&tensors(f32::NAN));
        assert!(matches!(h.events.recv().await, Some(Event::Uploading { client_id: 1 })));
        assert!(matches!(
            h.events.recv().await,
            Some(Event::Rejected { client_id: Some(1), code: ErrorCode::NonFinite })
        ));
        assert!(matches!(h.recv_control().await, ServerMessage::Error { code: ErrorCode::NonFinite, .. }));

        outbox.send(ServerMessage::Finished { rounds: 1 }).unwrap();
        assert_eq!(h.recv_control().await, ServerMessage::Finished { rounds: 1 });

        h.cancel.cancel();
        assert!(matches!(h.recv_control().await, ServerMessage::Error { code: ErrorCode::ShuttingDown, .. }));
        assert!(matches!(h.recv().await, Message::Close(_)));
        assert!(matches!(h.events.recv().await, Some(Event::Left { client_id: 1 })));
        h.task.await.unwrap();
    }

    #[tokio::test(start_paused = true)]
    async fn an_idle_connection_is_pinged_to_keep_it_open() {
        let mut h = Harness::new();
        h.join(Some("secret")).await;
        assert!(matches!(h.recv_control().await, ServerMessage::Welcome { client_id: 1, .. }));
        // The coordinator's end of the outbox stays open: a closed one ends the connection.
        let Some(Event::Joined { client_id: 1, outbox: _outbox, .. }) = h.events.recv().await else { panic!("joined") };
        tokio::time::advance(KEEPALIVE + Duration::from_secs(1)).await;
        let message = h.recv().await;
        assert!(matches!(message, Message::Ping(_)), "a ping after {KEEPALIVE:?} of silence, got {message:?}");
    }

    #[tokio::test]
    async fn wrong_token_is_refused_and_closed() {
        let mut h = Harness::new();
        h.join(Some("guess")).await;
        assert!(matches!(h.recv_control().await, ServerMessage::Error { code: ErrorCode::Unauthorized, .. }));
        assert!(matches!(h.recv().await, Message::Close(_)));
        assert!(matches!(
            h.events.recv().await,
            Some(Event::Rejected { client_id: None, code: ErrorCode::Unauthorized })
        ));
        h.task.await.unwrap();
    }
}
