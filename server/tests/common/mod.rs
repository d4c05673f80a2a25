//! Helpers for the loopback tests: a server on 127.0.0.1:0 with the linreg workload, native clients, raw
//! WebSocket clients that misbehave on purpose, and an independent reading of the run directory.

#![allow(dead_code)] // each test binary uses its own subset

use std::path::Path;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use fedvla_aggregator::config::{Partitioning, RunConfig};
use fedvla_aggregator::coordinator::RunStatus;
use fedvla_aggregator::parts::ServerParts;
use fedvla_aggregator::records::{MetricsLine, read_metrics};
use fedvla_aggregator::run_dir::{METRICS_FILE, RunDir};
use fedvla_app::server::{self, ServerHandle};
use fedvla_federation::{
    BoxError, Capabilities, ClientError, ClientMessage, ClientOptions, ClientSummary, EvalOutput, Identity,
    Introduction, LocalTrainer, NamedTensors, PROTOCOL_VERSION, RoundMetrics, RoundTask, ServerMessage, TrainOutput,
    identify, run_client,
};
use fedvla_server::native_client::NativeTransport;
pub use fedvla_server::native_client::simulated_identity;
use fedvla_workloads::linreg::{self, LinRegEvaluator, LinRegTrainer, LinRegWorkload};
use fedvla_workloads::workload::Workload;
use futures_util::{SinkExt, StreamExt};
use tokio::net::TcpStream;
use tokio::sync::Semaphore;
use tokio::task::JoinHandle;
use tokio_tungstenite::tungstenite::Message;
use tokio_tungstenite::{MaybeTlsStream, WebSocketStream};

/// Small, fast defaults under FedAvg (the tests check its example-weighted mean); `overrides` as on the command
/// line.
pub fn config(overrides: &str) -> RunConfig {
    RunConfig::default()
        .with_overrides(&format!(
            "strategy=fedavg num-server-rounds=2 eval-every=1 min-clients=3 min-fit=3 fraction-fit=1.0 local-steps=30 \
             batch-size=8 lr=0.05 round-deadline-ms=10000 max-frame-bytes=64 {overrides}"
        ))
        .expect("test config is valid")
}

/// A server of the linreg workload (one shard per `num-clients`, weighing `linreg::train_examples`).
pub async fn start(config: RunConfig, run_dir: RunDir) -> ServerHandle {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    server::start(parts(config, run_dir), listener).unwrap()
}

/// What [`start`] starts a server of.
pub fn parts(config: RunConfig, run_dir: RunDir) -> ServerParts {
    ServerParts {
        initial: linreg::initial_model(config.seed),
        volunteer: LinRegWorkload::from_config(&config).volunteer_offer().unwrap(),
        strategy: fedvla_workloads::workload::strategy(&config),
        config,
        run_dir,
        evaluator: Box::new(LinRegEvaluator::default()),
        exporters: Vec::new(),
    }
}

/// Waits (at most 20 s) until the status satisfies `pred`.
pub async fn wait_status(handle: &ServerHandle, pred: impl Fn(&RunStatus) -> bool) -> RunStatus {
    let mut rx = handle.status();
    let status = tokio::time::timeout(Duration::from_secs(20), rx.wait_for(|s| pred(s)))
        .await
        .expect("status condition within 20 s")
        .expect("server alive");
    status.clone()
}

/// Every update a client produced, by round.
pub type Recorded = Arc<Mutex<Vec<(u64, TrainOutput)>>>;

/// Every task a client was given.
pub type Tasks = Arc<Mutex<Vec<RoundTask>>>;

/// Every global model a client was set to train from, in order (one a task).
pub type Globals = Arc<Mutex<Vec<NamedTensors>>>;

/// The linreg trainer, recording its tasks and outputs, optionally hanging (a straggler) from some round on, and
/// optionally training only when the test hands out a permit.
pub struct TestTrainer {
    inner: LinRegTrainer,
    recorded: Recorded,
    tasks: Tasks,
    globals: Globals,
    hang_from_round: Option<u64>,
    gate: Option<Arc<Semaphore>>,
}

impl TestTrainer {
    pub fn new(shard: usize, hang_from_round: Option<u64>) -> (Self, Recorded) {
        let recorded = Recorded::default();
        let trainer = Self {
            inner: LinRegTrainer::new(shard, Partitioning::ByEpisode),
            recorded: recorded.clone(),
            tasks: Tasks::default(),
            globals: Globals::default(),
            hang_from_round,
            gate: None,
        };
        (trainer, recorded)
    }

    /// Each training first takes a permit from `gate`: the test decides when rounds can finish.
    pub fn gated(mut self, gate: Arc<Semaphore>) -> Self {
        self.gate = Some(gate);
        self
    }

    pub fn tasks(&self) -> Tasks {
        self.tasks.clone()
    }

    pub fn globals(&self) -> Globals {
        self.globals.clone()
    }
}

impl LocalTrainer for TestTrainer {
    fn capabilities(&self) -> Capabilities {
        self.inner.capabilities()
    }

    fn set_global(&mut self, global: &NamedTensors) -> Result<(), BoxError> {
        self.globals.lock().unwrap().push(global.clone());
        self.inner.set_global(global)
    }

    fn set_correction(&mut self, correction: &NamedTensors) -> Result<(), BoxError> {
        self.inner.set_correction(correction)
    }

    async fn train(&mut self, task: &RoundTask) -> Result<TrainOutput, BoxError> {
        self.tasks.lock().unwrap().push(task.clone());
        if let Some(gate) = &self.gate {
            gate.acquire().await.expect("gate stays open").forget();
        }
        if self.hang_from_round.is_some_and(|r| task.round >= r) {
            std::future::pending::<()>().await;
        }
        let out = self.inner.train(task).await?;
        self.recorded.lock().unwrap().push((task.round, out.clone()));
        Ok(out)
    }

    async fn evaluate(&mut self) -> Result<EvalOutput, BoxError> {
        self.inner.evaluate().await
    }
}

/// A native client named `client-<shard>` over a real WebSocket.
pub fn spawn_client(
    handle: &ServerHandle,
    shard: usize,
    hang_from_round: Option<u64>,
) -> (JoinHandle<Result<ClientSummary, ClientError>>, Recorded) {
    let (trainer, recorded) = TestTrainer::new(shard, hang_from_round);
    (spawn_trainer(handle, shard, trainer), recorded)
}

/// A native client named `client-<shard>` over a real WebSocket, training with `trainer`.
pub fn spawn_trainer(
    handle: &ServerHandle,
    shard: usize,
    trainer: TestTrainer,
) -> JoinHandle<Result<ClientSummary, ClientError>> {
    spawn_trainer_at(&format!("ws://{}", handle.addr()), shard, trainer)
}

/// A native client named `client-<shard>` (with its name's simulated key) training with `trainer`, joining the
/// server at `url` (one started as a process of the `fedvla` binary, which a test may kill before the client
/// connects: a transport error then).
pub fn spawn_trainer_at(
    url: &str,
    shard: usize,
    mut trainer: TestTrainer,
) -> JoinHandle<Result<ClientSummary, ClientError>> {
    let url = url.to_owned();
    tokio::spawn(async move {
        let mut transport = NativeTransport::connect(&url).await.map_err(ClientError::Transport)?;
        let name = format!("client-{shard}");
        let intro =
            Introduction { name: name.clone(), auth_token: None, shard: Some(shard as u32), own_dataset: false };
        let admission = identify(&mut transport, &simulated_identity(&name), &intro).await?;
        let options = ClientOptions { session: admission.session, data: None };
        run_client(&mut transport, &mut trainer, &options, |_| {}).await
    })
}

/// The metrics lines of a run, as JSON values: for the tests that check what the console and the browser read of
/// them by key.
pub fn metrics(dir: &Path) -> Vec<serde_json::Value> {
    std::fs::read_to_string(dir.join(METRICS_FILE)).unwrap().lines().map(|l| serde_json::from_str(l).unwrap()).collect()
}

/// The metrics lines of a run, as the record the coordinator writes.
pub fn metrics_lines(dir: &Path) -> Vec<MetricsLine> {
    read_metrics(dir).unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
}

/// The global model's held-out loss in a metrics line (the round must have evaluated it).
pub fn heldout_loss(line: &MetricsLine) -> f64 {
    let eval = line.global.as_ref().and_then(|g| g.eval.as_ref());
    eval.unwrap_or_else(|| panic!("round {} has no held-out evaluation: {line:?}", line.round)).heldout_loss
}

/// The example-weighted mean, computed here independently of the strategy.
pub fn weighted_mean(updates: &[TrainOutput]) -> NamedTensors {
    let total: f64 = updates.iter().map(|u| u.examples as f64).sum();
    let mut out = NamedTensors::new();
    for (name, t) in updates[0].update.iter() {
        let values = (0..t.values.len())
            .map(|i| {
                let sum: f64 =
                    updates.iter().map(|u| u.examples as f64 * f64::from(u.update.get(name).unwrap().values[i])).sum();
                (sum / total) as f32
            })
            .collect();
        out.insert(name, t.shape.clone(), values).unwrap();
    }
    out
}

pub fn assert_close(a: &NamedTensors, b: &NamedTensors, tol: f32) {
    assert_eq!(a.spec(), b.spec());
    for (name, t) in a.iter() {
        for (x, y) in t.values.iter().zip(&b.get(name).unwrap().values) {
            assert!((x - y).abs() <= tol, "{name}: {x} vs {y}");
        }
    }
}

/// A hand-driven WebSocket client, for protocol violations.
pub struct RawClient {
    ws: WebSocketStream<MaybeTlsStream<TcpStream>>,
}

impl RawClient {
    pub async fn connect(handle: &ServerHandle) -> Self {
        let (ws, _) = tokio_tungstenite::connect_async(format!("ws://{}/ws", handle.addr())).await.unwrap();
        Self { ws }
    }

    /// Connects from `source`, a loopback address of its own (127.0.0.2, ...): another volunteer's machine.
    pub async fn connect_from(handle: &ServerHandle, source: std::net::Ipv4Addr) -> Self {
        let socket = tokio::net::TcpSocket::new_v4().unwrap();
        socket.bind((source, 0).into()).unwrap();
        let stream = MaybeTlsStream::Plain(socket.connect(handle.addr()).await.unwrap());
        let (ws, _) = tokio_tungstenite::client_async(format!("ws://{}/ws", handle.addr()), stream).await.unwrap();
        Self { ws }
    }

    /// Connects, identifies as `name` (with its name's simulated key) and joins, leaving the shard to the server;
    /// returns the client and its id.
    pub async fn join(handle: &ServerHandle, name: &str) -> (Self, u64) {
        let (c, client_id, _) = Self::join_shard(handle, name, None).await;
        (c, client_id)
    }

    /// Connects, identifies as `name` (with its name's simulated key) asking for `shard`, and joins; returns the
    /// client, its id and its session.
    pub async fn join_shard(handle: &ServerHandle, name: &str, shard: Option<u32>) -> (Self, u64, String) {
        let mut c = Self::connect(handle).await;
        let (client_id, session) = match c.identify(&simulated_identity(name), name, shard).await {
            Some(ServerMessage::Admitted { client_id, session, .. }) => (client_id, session),
            other => panic!("expected the admission, got {other:?}"),
        };
        match c.join_admitted().await {
            Some(ServerMessage::Welcome { client_id: welcomed, .. }) => assert_eq!(welcomed, client_id),
            other => panic!("expected welcome, got {other:?}"),
        }
        (c, client_id, session)
    }

    /// The challenge's nonce, the server's first message.
    pub async fn challenge(&mut self) -> String {
        match self.recv().await {
            Some(ServerMessage::Challenge { nonce }) => nonce,
            other => panic!("expected a challenge, got {other:?}"),
        }
    }

    /// Answers the challenge as `name` with `identity`'s proof, asking for `shard`; the server's answer.
    pub async fn identify(&mut self, identity: &Identity, name: &str, shard: Option<u32>) -> Option<ServerMessage> {
        let nonce = self.challenge().await;
        self.send(&identify_message(identity, &nonce, name, shard, PROTOCOL_VERSION)).await;
        self.recv().await
    }

    /// Joins after the admission; the server's answer.
    pub async fn join_admitted(&mut self) -> Option<ServerMessage> {
        self.send(&ClientMessage::Join {
            capabilities: Capabilities { backend: "test".into(), memory_bytes: 0 },
            data: None,
        })
        .await;
        self.recv().await
    }

    /// Waits for the next round task (skipping other messages).
    pub async fn task(&mut self) -> RoundTask {
        loop {
            match self.recv().await {
                Some(ServerMessage::RoundTask(task)) => return task,
                Some(_) => {}
                None => panic!("closed before a task"),
            }
        }
    }

    /// Uploads `tensors` for `round` claiming `examples`, then reports the round's metrics.
    pub async fn upload(&mut self, round: u64, tensors: &NamedTensors, examples: u64) {
        let payload_bytes = fedvla_federation::codec::encode_payload(tensors).len() as u64;
        self.send(&ClientMessage::UpdateHeader { round, examples, train_loss: 1.0, payload_bytes }).await;
        for frame in fedvla_federation::codec::encode_update(tensors, round, 64) {
            self.send_binary(frame).await;
        }
        let metrics = RoundMetrics {
            round,
            examples,
            train_loss: 1.0,
            seconds: 0.0,
            bytes_up: 0,
            bytes_down: 0,
            download_bytes: 0,
        };
        self.send(&ClientMessage::Metrics(metrics)).await;
    }

    pub async fn send(&mut self, msg: &ClientMessage) {
        self.send_text(serde_json::to_string(msg).unwrap()).await;
    }

    pub async fn send_text(&mut self, text: String) {
        self.ws.send(Message::text(text)).await.unwrap();
    }

    pub async fn send_binary(&mut self, frame: Vec<u8>) {
        self.ws.send(Message::binary(frame)).await.unwrap();
    }

    /// Next server message, `None` once closed.
    pub async fn recv(&mut self) -> Option<ServerMessage> {
        loop {
            let frame = tokio::time::timeout(Duration::from_secs(10), self.ws.next()).await.expect("reply within 10 s");
            match frame {
                Some(Ok(Message::Text(t))) => {
                    return Some(serde_json::from_str(t.as_str()).unwrap());
                }
                Some(Ok(Message::Close(_))) | None | Some(Err(_)) => return None,
                Some(Ok(_)) => {}
            }
        }
    }
}

/// The identify answering `nonce` as `name`, proven with `identity`, asking for `shard`, in `protocol_version`.
pub fn identify_message(
    identity: &Identity,
    nonce: &str,
    name: &str,
    shard: Option<u32>,
    protocol_version: u16,
) -> ClientMessage {
    ClientMessage::Identify {
        protocol_version,
        auth_token: None,
        name: name.into(),
        public_key: identity.public_key_hex(),
        signature: identity.prove(nonce, name),
        shard,
        own_dataset: false,
    }
}

/// A linreg head with every weight `weight` and bias `bias`.
pub fn linreg_head(weight: f32, bias: f32) -> NamedTensors {
    let mut t = NamedTensors::new();
    t.insert(linreg::WEIGHT, vec![1, linreg::FEATURES], vec![weight; linreg::FEATURES]).unwrap();
    t.insert(linreg::BIAS, vec![1], vec![bias]).unwrap();
    t
}

/// One plain HTTP/1.1 request to the server; the status and body.
pub async fn http(
    handle: &ServerHandle,
    method: &str,
    path: &str,
    headers: &[(&str, &str)],
    body: Vec<u8>,
) -> (u16, String) {
    use http_body_util::{BodyExt, Full};
    let stream = TcpStream::connect(handle.addr()).await.unwrap();
    let (mut sender, conn) = hyper::client::conn::http1::handshake(hyper_util::rt::TokioIo::new(stream)).await.unwrap();
    tokio::spawn(conn);
    let mut request = hyper::Request::builder().method(method).uri(path).header("host", "test");
    for (k, v) in headers {
        request = request.header(*k, *v);
    }
    let response = sender.send_request(request.body(Full::new(hyper::body::Bytes::from(body))).unwrap()).await.unwrap();
    let status = response.status().as_u16();
    let body = response.into_body().collect().await.unwrap().to_bytes();
    (status, String::from_utf8_lossy(&body).into_owned())
}
