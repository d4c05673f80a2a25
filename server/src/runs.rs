//! Whole runs in one process, for `fedvla simulate`, `fedvla train` and the experiment runner: a federation (a
//! server and N native volunteers over real loopback WebSockets, each downloading its setup, shard and weights
//! over HTTP as `fedvla join` does) and its centralized baseline (one trainer on the
//! union of the clients' training episodes, for as many samples as the federation consumes, evaluated at the same
//! sample counts). Both write the same `outputs/<run>/` layout, a baseline "round" being the samples of one
//! federated round, so every reader of a federation's outputs reads a baseline's too.

use std::path::PathBuf;
use std::time::Duration;

use anyhow::Context;
use fedvla_aggregator::config::{ComputeDevice, RunConfig, WorkloadKind};
use fedvla_aggregator::coordinator::RunStatus;
use fedvla_aggregator::records::{GlobalMetrics, MetricsLine, timestamp};
use fedvla_aggregator::run_dir::{ModelExporter, RunDir, TrainableSafetensors};
use fedvla_app::server;
use fedvla_federation::{ClientEvent, LocalTrainer, NamedTensors, RoundTask, StrategyParams};
use fedvla_learner::trainer::StepProgress;
use fedvla_workloads::linreg::LinRegWorkload;
use fedvla_workloads::smolvla::SmolVlaWorkload;
use fedvla_workloads::workload::{Workload, server_parts};
use indicatif::{MultiProgress, ProgressBar, ProgressDrawTarget, ProgressStyle};
use tokio::net::TcpListener;
use tokio::sync::oneshot;

use crate::attack::Attack;
use crate::native_client::{self, Volunteer, VolunteerData};

/// Where a run shows its progress bars (hidden inside an experiment, which has one bar for its grid).
#[derive(Clone)]
pub struct Bars {
    multi: MultiProgress,
    /// Inside an experiment: lines go nowhere either.
    quiet: bool,
}

impl Bars {
    pub fn terminal() -> Self {
        Self { multi: MultiProgress::new(), quiet: false }
    }

    pub fn hidden() -> Self {
        Self { multi: MultiProgress::with_draw_target(ProgressDrawTarget::hidden()), quiet: true }
    }

    fn bar(&self, len: u64, prefix: String) -> anyhow::Result<ProgressBar> {
        let bar = self.multi.add(ProgressBar::new(len));
        bar.set_style(ProgressStyle::with_template("{prefix:>10} [{bar:30}] {pos}/{len} {msg}")?);
        bar.set_prefix(prefix);
        Ok(bar)
    }

    /// Prints a line above the bars; to plain stdout where there is no terminal to draw bars on (a log, CI),
    /// nowhere inside an experiment.
    fn println(&self, line: String) {
        if self.quiet {
            return;
        }
        if self.multi.is_hidden() {
            println!("{line}");
        } else {
            self.multi.println(line).ok();
        }
    }
}

/// The directory shards are written to inside a run.
pub const SHARDS_DIR: &str = "shards";

/// A federation of `config.num_clients` native clients, one per shard, and one per `own-datasets` entry on that
/// dataset, until its last round.
pub fn federated(config: RunConfig, run_dir: RunDir, bars: &Bars) -> anyhow::Result<RunStatus> {
    let clients = config.num_clients + config.own_datasets.len();
    anyhow::ensure!(
        clients >= config.min_clients,
        "{clients} clients is below min-clients {}: no round would start",
        config.min_clients
    );
    match config.workload {
        WorkloadKind::Linreg => serve_clients(&LinRegWorkload::from_config(&config), config, run_dir, bars),
        WorkloadKind::Smolvla => {
            let workload = SmolVlaWorkload::prepare(&config, &run_dir.path().join(SHARDS_DIR))?;
            bars.println(workload.inputs().to_owned());
            serve_clients(&workload, config, run_dir, bars)
        }
    }
}

fn serve_clients(
    workload: &impl Workload,
    config: RunConfig,
    run_dir: RunDir,
    bars: &Bars,
) -> anyhow::Result<RunStatus> {
    let own_datasets: Vec<PathBuf> = config.own_datasets.iter().map(PathBuf::from).collect();
    let clients = config.num_clients;
    let rounds = config.num_server_rounds;
    let attack = Attack { kind: config.attack, strength: config.attack_strength };
    let attackers = config.attackers;
    let device = config.device;
    let auth_token = config.auth_token().map(str::to_owned);
    // Over TLS, the clients trust the server's own certificate (self-signed, or one of the Mozilla roots' chains).
    let ca_cert = config.tls_files().map(|(cert, _)| cert.to_owned());
    let parts = server_parts(workload, config, run_dir).map_err(boxed)?;
    runtime()?.block_on(async move {
        let listener = TcpListener::bind("127.0.0.1:0").await.context("binding 127.0.0.1:0")?;
        let handle = server::start(parts, listener)?;
        let scheme = if ca_cert.is_some() { "wss" } else { "ws" };
        let url = format!("{scheme}://{}", handle.addr());
        let round_bar = bars.bar(rounds, "server".into())?;
        let mut status = handle.status();
        let watcher = tokio::spawn({
            let round_bar = round_bar.clone();
            async move {
                loop {
                    let s = status.borrow_and_update().clone();
                    round_bar.set_position(s.completed_rounds);
                    let refusals = s.rejections.values().sum::<u64>();
                    round_bar.set_message(format!("rounds, {} connected, {refusals} refusals", s.connected));
                    if s.finished || status.changed().await.is_err() {
                        break;
                    }
                }
            }
        });
        let server = || Server { url: url.clone(), ca_cert: ca_cert.clone(), auth_token: auth_token.clone(), device };
        let mut tasks: Vec<_> = (0..clients)
            .map(|shard| {
                let attack = (shard < attackers).then_some(attack);
                let prefix = if attack.is_some() { format!("attacker {shard}") } else { format!("client {shard}") };
                let (name, data) = (format!("client-{shard}"), SimulatedData::Shard(shard as u32));
                Ok((name.clone(), spawn_client(server(), name, data, attack, bars.bar(rounds, prefix)?)))
            })
            .collect::<anyhow::Result<_>>()?;
        for (i, path) in own_datasets.into_iter().enumerate() {
            let bar = bars.bar(rounds, format!("own data {i}"))?;
            let name = format!("own-{i}");
            tasks.push((name.clone(), spawn_client(server(), name, SimulatedData::Own(path), None, bar)));
        }
        // A simulated federation cannot finish without its clients: the first client to fail
        // stops the run instead of leaving the server waiting for it.
        let cancel = handle.cancel_token();
        let clients: Vec<_> = tasks
            .into_iter()
            .map(|(name, done)| {
                let cancel = cancel.clone();
                tokio::spawn(async move {
                    let result = done.await.unwrap_or_else(|_| Err(anyhow::anyhow!("panicked")));
                    if result.is_err() {
                        cancel.cancel();
                    }
                    result.with_context(|| format!("volunteer {name}"))
                })
            })
            .collect();
        let status = handle.finish().await?;
        watcher.await.ok();
        round_bar.finish();
        let mut failures = Vec::new();
        for client in clients {
            match tokio::time::timeout(Duration::from_secs(5), client).await {
                Ok(Ok(Ok(()))) => {}
                Ok(Ok(Err(e))) => failures.push(format!("{e:#}")),
                Ok(Err(e)) => failures.push(e.to_string()),
                Err(_) => failures.push("a client did not finish".into()),
            }
        }
        anyhow::ensure!(failures.is_empty(), "the simulation stopped: {}", failures.join("; "));
        anyhow::Ok(status)
    })
}

/// What a simulated volunteer trains on.
enum SimulatedData {
    Shard(u32),
    Own(PathBuf),
}

/// Where `simulate`'s clients join, what they trust and present there, and the device they train on.
struct Server {
    url: String,
    ca_cert: Option<PathBuf>,
    auth_token: Option<String>,
    device: ComputeDevice,
}

/// Volunteer `name` on `data` with its own progress bar, on its own thread: trainers' futures need not be `Send`
/// (the browser's are not), and CPU-bound trainers then train in parallel.
fn spawn_client(
    server: Server,
    name: String,
    data: SimulatedData,
    attack: Option<Attack>,
    bar: ProgressBar,
) -> oneshot::Receiver<anyhow::Result<()>> {
    let (done_tx, done) = oneshot::channel();
    std::thread::spawn(move || {
        let client = async move {
            let Server { url, ca_cert, auth_token, device } = server;
            let identity = native_client::simulated_identity(&name);
            let volunteer = Volunteer {
                server: &url,
                ca_cert: ca_cert.as_deref(),
                name: &name,
                identity: &identity,
                data: match &data {
                    SimulatedData::Shard(shard) => VolunteerData::Shard(Some(*shard)),
                    SimulatedData::Own(path) => VolunteerData::Own(path),
                },
                auth_token,
                attack,
                device,
            };
            let summary = native_client::volunteer(volunteer, |event| match event {
                ClientEvent::Joined { client_id } => bar.set_message(format!("joined as {client_id}")),
                ClientEvent::Task { round, local_steps } => {
                    bar.set_message(format!("round {round}: training {local_steps} steps"));
                }
                ClientEvent::Trained { round, train_loss, .. } => {
                    bar.set_message(format!("round {round}: loss {train_loss:.4}, uploading"));
                }
                ClientEvent::Uploaded { round, bytes, .. } => {
                    bar.set_message(format!("round {round}: sent {bytes} B"));
                }
                ClientEvent::RolledOut { round, episodes, successes } => {
                    bar.set_message(format!("round {round}: {successes}/{episodes} sim successes, training"));
                }
                ClientEvent::RoundClosed { round, accepted } => {
                    if accepted {
                        bar.set_position(round);
                    }
                }
                ClientEvent::Refused { code, .. } => {
                    bar.set_message(format!("refused: {}", code.as_str()));
                }
            })
            .await
            .map_err(boxed)?;
            bar.finish_with_message(format!(
                "{} rounds, {} B up, {} B down",
                summary.rounds_trained, summary.bytes_up, summary.bytes_down
            ));
            anyhow::Ok(())
        };
        let result = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .context("client runtime")
            .and_then(|rt| rt.block_on(client));
        done_tx.send(result).ok();
    });
    done
}

/// The centralized baseline of the federation `config` describes: same model, trainer, learning rate, held-out
/// sets and sim evaluation, one trainer on every client's training episodes.
pub fn centralized(config: RunConfig, run_dir: RunDir, bars: &Bars) -> anyhow::Result<()> {
    anyhow::ensure!(config.workload == WorkloadKind::Smolvla, "the centralized baseline trains the smolvla workload");
    let workload = SmolVlaWorkload::prepare_centralized(&config, &run_dir.path().join(SHARDS_DIR))?;
    bars.println(workload.inputs().to_owned());
    let mut trainer = workload.centralized_trainer(config.device).map_err(boxed)?;
    let mut evaluator = workload.evaluator().map_err(boxed)?;
    let mut exporters: Vec<Box<dyn ModelExporter>> = vec![Box::new(TrainableSafetensors)];
    exporters.extend(workload.exporters());

    let steps_per_round = config.sampled_clients(config.num_clients) as u32 * config.local_steps;
    let rounds = config.num_server_rounds;
    let bar = bars.bar(rounds * u64::from(steps_per_round), "central".into())?;
    // Every round's model is saved, as a federation saves it; evaluated rounds get their figures.
    let mut persist = |global: &NamedTensors, evaluate: bool, mut line: MetricsLine| -> anyhow::Result<()> {
        let eval = if evaluate { Some(evaluator.evaluate(global).map_err(boxed)?) } else { None };
        let sim = run_dir.save_model(line.round, global, &NamedTensors::new(), &exporters, &config)?;
        line.model_version = line.round;
        line.model_crc32 = global.checksum();
        let (loss, success) = (eval.as_ref().map(|e| e.heldout_loss), sim.as_ref().map(|s| s.success_rate));
        line.global = (eval.is_some() || sim.is_some()).then_some(GlobalMetrics { eval, sim });
        line.timestamp = timestamp();
        run_dir.append_metrics(&line)?;
        run_dir.remove_superseded_models(config.keep_models)?;
        if let Some(loss) = loss {
            bars.println(format!("round {}: held-out loss {loss:.4}, sim success {success:?}", line.round));
        }
        Ok(())
    };
    let mut global = workload.initial_model().map_err(boxed)?;
    persist(&global, true, MetricsLine::default())?;
    trainer.set_global(&global).map_err(boxed)?;
    let runtime = runtime()?;
    for round in 1..=rounds {
        let started = std::time::Instant::now();
        let task = RoundTask {
            round,
            model_version: round - 1,
            local_steps: steps_per_round,
            batch_size: config.batch_size,
            lr: config.lr,
            lr_schedule: config.lr_schedule(round, u64::from(steps_per_round)),
            seed: config.seed ^ round.wrapping_mul(0x9e37_79b9_7f4a_7c15),
            strategy: StrategyParams::plain("centralized"),
            // The optimizer's moments carry over from round to round: one continuous run.
            keep_optimizer_state: true,
            opening_frames: config.opening_frames(),
            deadline_ms: config.round_deadline_ms,
            eval_request: false,
            rollout: None,
            update_encoding: fedvla_federation::UpdateEncoding::F32,
            model_deltas: None,
        };
        let before = bar.position();
        let out = runtime
            .block_on(trainer.train_with(&task, async |p: StepProgress| {
                bar.set_position(before + u64::from(p.step));
                bar.set_message(format!("steps, round {round}, loss {:.4}", p.loss));
            }))
            .map_err(boxed)?;
        global = out.update;
        let line = MetricsLine {
            round,
            seconds: Some(started.elapsed().as_secs_f64()),
            train_loss: Some(out.train_loss),
            samples: Some(round * u64::from(steps_per_round) * u64::from(config.batch_size)),
            ..MetricsLine::default()
        };
        persist(&global, round.is_multiple_of(config.eval_every) || round == rounds, line)?;
    }
    bar.finish();
    Ok(())
}

fn runtime() -> anyhow::Result<tokio::runtime::Runtime> {
    tokio::runtime::Builder::new_multi_thread().enable_all().build().context("starting the tokio runtime")
}

/// Library errors crossing trait objects, into anyhow.
pub fn boxed(e: fedvla_federation::BoxError) -> anyhow::Error {
    anyhow::anyhow!(e)
}
