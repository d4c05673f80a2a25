//! What a round's aggregation costs the server, measured on a real one: `fedvla bench`'s aggregation figures and
//! the memory test (server/tests/aggregation_memory.rs). The server runs in a process of its own
//! ([`serve_round`], `fedvla aggregation-server`), so that what is measured is its memory alone and no other
//! measure's pages the allocator kept; its global model is a SmolVLA size's tensors (every one of them, as the main
//! job trains `small`). It takes one FedAvg round of N volunteers of this process ([`measure_round`]), each sending
//! an update of that size (its own) once the one before it has sent its frames; the server's peak resident memory
//! is read from /proc/<pid>/status over the round alone (its peak is reset once every volunteer has its task).
//!
//! The server's upload budget holds two updates (`max-upload-memory-bytes`), so at most two are decoded and not yet
//! folded at once: the next one waits in its socket (and its volunteer) until the coordinator has taken one. No
//! held-out data here: the evaluator reports the mean square of the model's values (finite when the aggregate is),
//! so the round closes as in a real run, without a dataset to load. The norm screen is off
//! (`update-norm-factor=0`): in a run's first round it holds the updates that arrive before the round's median norm
//! can be bounded (see the coordinator's `screen`), which a first round is.

use std::io::{BufRead, BufReader, Read};
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::sync::Arc;
use std::time::Instant;

use anyhow::Context;
use fedvla_aggregator::config::RunConfig;
use fedvla_aggregator::parts::ServerParts;
use fedvla_aggregator::run_dir::RunDir;
use fedvla_app::server;
use fedvla_federation::codec::{encode_payload, encode_update};
use fedvla_federation::{
    BoxError, Capabilities, ClientMessage, ClientTransport, EvalMetrics, Evaluator, Introduction, NamedTensors,
    RoundMetrics, ServerMessage, identify,
};
use fedvla_policy::SmolVlaConfig;
use fedvla_workloads::linreg::LinRegWorkload;
use fedvla_workloads::workload::{Workload, strategy};
use serde::{Deserialize, Serialize};
use tokio::net::TcpListener;
use tokio::sync::Semaphore;

use crate::native_client::{NativeTransport, simulated_identity};

/// What one measured round cost.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RoundMemory {
    pub clients: usize,
    /// Bytes of the global model (f32), which is each update's size.
    pub model_bytes: u64,
    /// The server's resident memory when the round's tasks were out (its model, the volunteers connected).
    pub before_rss_bytes: u64,
    /// The peak over the round: every upload, fold, the close, the evaluation and the model's files.
    pub peak_rss_bytes: u64,
    pub round_seconds: f64,
}

impl RoundMemory {
    /// The round's growth over the memory before it, in models.
    pub fn growth_in_models(&self) -> f64 {
        self.peak_rss_bytes.saturating_sub(self.before_rss_bytes) as f64 / self.model_bytes as f64
    }
}

/// Every tensor of SmolVLA `size`, seeded values of a trained model's magnitude.
pub fn model_of_size(size: &str, seed: u64) -> anyhow::Result<NamedTensors> {
    let mut model = NamedTensors::new();
    let mut state = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
    for spec in SmolVlaConfig::preset(size)?.param_specs() {
        let values = (0..spec.shape.iter().product::<usize>())
            .map(|_| {
                state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                ((state >> 40) as f32 / (1u64 << 24) as f32 - 0.5) * 0.1
            })
            .collect();
        model.insert(spec.name, spec.shape, values)?;
    }
    Ok(model)
}

/// The stand-in for held-out data: the mean square of the model's values.
struct MeanSquare;

impl Evaluator for MeanSquare {
    fn evaluate(&mut self, global: &NamedTensors) -> Result<EvalMetrics, BoxError> {
        let (sum, n) = global
            .iter()
            .flat_map(|(_, t)| &t.values)
            .fold((0.0, 0u64), |(s, n), &v| (s + f64::from(v) * f64::from(v), n + 1));
        Ok(EvalMetrics { heldout_loss: sum / n.max(1) as f64, ..EvalMetrics::default() })
    }
}

/// The volunteers' frame size: each connection keeps a buffer of about one frame for as long as it lives, which is
/// what grows with the number of connections whatever the aggregation does (1 MiB a connection at the default
/// frame size, next to nothing beside a base-size model of 400 MB but a fifth of `small`'s); frames of 64 KiB keep
/// it out of the measure of what the aggregation holds.
const FRAME_BYTES: usize = 64 << 10;

/// The run configuration of a measured round of `clients`, whose updates take `payload_bytes` each.
fn round_config(clients: usize, payload_bytes: u64) -> anyhow::Result<RunConfig> {
    let defaults = RunConfig::default();
    Ok(defaults.with_overrides(&format!(
        "workload=linreg strategy=fedavg num-clients={clients} min-clients={clients} min-fit={clients} \
         fraction-fit=1.0 num-server-rounds=1 eval-every=1 rollout-episodes=0 client-rollout-episodes=0 \
         update-norm-factor=0 round-deadline-ms=600000 joins-per-address-per-minute={} max-connections={} \
         max-upload-memory-bytes={} max-video-bytes={payload_bytes}",
        clients.max(defaults.joins_per_address_per_minute as usize),
        (2 * clients + 64).max(defaults.max_connections),
        2 * payload_bytes,
    ))?)
}

/// The server of a measured round (`fedvla aggregation-server`, a child process of [`measure_round`]): one FedAvg
/// round of `clients` volunteers over every tensor of SmolVLA `size`, its run directory under `output_dir`. Prints
/// `listening ws://ADDR` once it accepts connections, and after the round waits for its standard input to close,
/// so that its memory can be read before it exits.
pub fn serve_round(size: &str, clients: usize, output_dir: &Path) -> anyhow::Result<()> {
    anyhow::ensure!(clients >= 1, "at least one volunteer");
    let global = model_of_size(size, 0)?;
    let config = round_config(clients, encode_payload(&global).len() as u64)?;
    let run_dir = RunDir::create(output_dir, &config)?;
    let parts = ServerParts {
        initial: global,
        volunteer: LinRegWorkload::from_config(&config).volunteer_offer().map_err(|e| anyhow::anyhow!("{e}"))?,
        strategy: strategy(&config),
        evaluator: Box::new(MeanSquare),
        exporters: Vec::new(),
        config,
        run_dir,
    };
    let runtime = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build()?;
    let status = runtime.block_on(async {
        let listener = TcpListener::bind("127.0.0.1:0").await.context("binding 127.0.0.1:0")?;
        let handle = server::start(parts, listener)?;
        println!("listening ws://{}", handle.addr());
        std::io::Write::flush(&mut std::io::stdout())?;
        anyhow::Ok(handle.finish().await?)
    })?;
    anyhow::ensure!(status.completed_rounds == 1, "the round did not complete: {status:?}");
    std::io::stdin().read_to_end(&mut Vec::new())?;
    Ok(())
}

/// The server child of a measured round: killed if dropped before it exits.
struct ServerProcess(Child);

impl Drop for ServerProcess {
    fn drop(&mut self) {
        if self.0.try_wait().ok().flatten().is_none() {
            self.0.kill().ok();
            self.0.wait().ok();
        }
    }
}

/// One FedAvg round of `clients` volunteers over every tensor of SmolVLA `size`, served by `fedvla` (the binary at
/// `fedvla_exe`) as a child process, its run directory under `output_dir`.
pub fn measure_round(fedvla_exe: &Path, size: &str, clients: usize, output_dir: &Path) -> anyhow::Result<RoundMemory> {
    anyhow::ensure!(clients >= 1, "at least one volunteer");
    let global = model_of_size(size, 0)?;
    let mut child = ServerProcess(
        Command::new(fedvla_exe)
            .arg("aggregation-server")
            .args(["--size", size, "--clients", &clients.to_string()])
            .arg("--output")
            .arg(output_dir)
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .spawn()
            .with_context(|| format!("starting {} aggregation-server", fedvla_exe.display()))?,
    );
    let pid = child.0.id();
    let mut first_line = String::new();
    BufReader::new(child.0.stdout.take().context("the server's stdout")?).read_line(&mut first_line)?;
    let url = first_line
        .trim()
        .strip_prefix("listening ")
        .with_context(|| format!("the server said {first_line:?}, not where it listens"))?
        .to_owned();
    let runtime = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build()?;
    let (before_rss_bytes, round_seconds) = runtime.block_on(async {
        let tasked = Arc::new(Semaphore::new(0));
        let turn = Arc::new(Semaphore::new(0));
        let shared = Arc::new(global.clone());
        let volunteers: Vec<_> = (0..clients)
            .map(|i| {
                let (url, tasked, turn, global) = (url.clone(), tasked.clone(), turn.clone(), shared.clone());
                tokio::spawn(async move { volunteer(&url, i, &global, &tasked, &turn).await })
            })
            .collect();
        // Every task out: the server's memory before the uploads.
        tasked.acquire_many(clients as u32).await?.forget();
        reset_peak_rss(pid)?;
        let before_rss_bytes = rss_of(&format!("/proc/{pid}"))?.1;
        let started = Instant::now();
        turn.add_permits(1);
        for v in volunteers {
            v.await?.map_err(|e| anyhow::anyhow!("volunteer: {e}"))?;
        }
        anyhow::Ok((before_rss_bytes, started.elapsed().as_secs_f64()))
    })?;
    // Every volunteer has the round's close, which the server sends once the model is stored.
    let peak_rss_bytes = rss_of(&format!("/proc/{pid}"))?.0;
    drop(child.0.stdin.take());
    let status = child.0.wait()?;
    anyhow::ensure!(status.success(), "the server exited with {status}");
    Ok(RoundMemory {
        clients,
        model_bytes: 4 * global.iter().map(|(_, t)| t.values.len() as u64).sum::<u64>(),
        before_rss_bytes,
        peak_rss_bytes,
        round_seconds,
    })
}

/// Volunteer `i`: joins, reports its task through `tasked`, waits for its `turn`, uploads `global` moved by a
/// step of its own, passes the turn on once its frames are sent, and waits for the round's close.
async fn volunteer(
    url: &str,
    i: usize,
    global: &NamedTensors,
    tasked: &Semaphore,
    turn: &Semaphore,
) -> Result<(), BoxError> {
    let mut transport = NativeTransport::connect(url).await?;
    let name = format!("memory-{i}");
    let intro = Introduction { name: name.clone(), auth_token: None, shard: None, own_dataset: false };
    identify(&mut transport, &simulated_identity(&name), &intro).await?;
    let join =
        ClientMessage::Join { capabilities: Capabilities { backend: "memory".into(), memory_bytes: 0 }, data: None };
    transport.send_text(serde_json::to_string(&join)?).await?;
    let round = loop {
        if let ServerMessage::RoundTask(task) = next(&mut transport).await? {
            break task.round;
        }
    };
    tasked.add_permits(1);
    turn.acquire().await?.forget();
    let frames = {
        let step = (i as f32 + 1.0) * 1e-4;
        let update = global.zip_map(global, |g, _| g + step)?;
        let payload_bytes = encode_payload(&update).len() as u64;
        let header = ClientMessage::UpdateHeader { round, examples: 1, train_loss: 1.0, payload_bytes };
        transport.send_text(serde_json::to_string(&header)?).await?;
        encode_update(&update, round, FRAME_BYTES)
    };
    for frame in frames {
        transport.send_binary(frame).await?;
    }
    let metrics = RoundMetrics {
        round,
        examples: 1,
        train_loss: 1.0,
        seconds: 0.0,
        bytes_up: 0,
        bytes_down: 0,
        download_bytes: 0,
    };
    transport.send_text(serde_json::to_string(&ClientMessage::Metrics(metrics))?).await?;
    turn.add_permits(1);
    loop {
        if let ServerMessage::RoundClosed { .. } | ServerMessage::Finished { .. } = next(&mut transport).await? {
            return Ok(());
        }
    }
}

async fn next(transport: &mut NativeTransport) -> Result<ServerMessage, BoxError> {
    let text = transport.recv_text().await?.ok_or("the server closed the connection")?;
    Ok(serde_json::from_str(&text)?)
}

/// Resets process `pid`'s peak resident memory (VmHWM) to its current resident memory.
fn reset_peak_rss(pid: u32) -> anyhow::Result<()> {
    let path = format!("/proc/{pid}/clear_refs");
    std::fs::write(&path, "5").with_context(|| format!("resetting the peak RSS ({path})"))
}

/// This process's peak and current resident memory, in bytes (/proc/self/status).
pub fn rss() -> anyhow::Result<(u64, u64)> {
    rss_of("/proc/self")
}

/// The peak and current resident memory of the process at `proc_dir` (/proc/PID), in bytes.
fn rss_of(proc_dir: &str) -> anyhow::Result<(u64, u64)> {
    let path = format!("{proc_dir}/status");
    let status = std::fs::read_to_string(&path).with_context(|| path.clone())?;
    let kib = |key: &str| -> anyhow::Result<u64> {
        let line = status.lines().find_map(|l| l.strip_prefix(key)).with_context(|| format!("no {key} in {path}"))?;
        let value = line.trim().trim_end_matches("kB").trim();
        Ok(value.parse::<u64>().with_context(|| format!("{key} {value}"))? * 1024)
    };
    Ok((kib("VmHWM:")?, kib("VmRSS:")?))
}
