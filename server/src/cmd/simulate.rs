//! `fedvla simulate`: a server and N native clients in one process, over real loopback WebSockets.

use std::path::Path;
use std::time::Duration;

use anyhow::Context;
use fedvla_federation::{ClientEvent, ClientOptions, LocalTrainer, run_client};
use fedvla_server::config::{RunConfig, WorkloadKind};
use fedvla_server::linreg::LinRegWorkload;
use fedvla_server::native_client::NativeTransport;
use fedvla_server::run_dir::{METRICS_FILE, RunDir};
use fedvla_server::server::{self, ServerParts};
use fedvla_server::smolvla_workload::SmolVlaWorkload;
use fedvla_server::workload::Workload;
use indicatif::{MultiProgress, ProgressBar, ProgressStyle};
use tokio::net::TcpListener;
use tokio::sync::oneshot;
use tracing_subscriber::filter::LevelFilter;

use super::ConfigArgs;

#[derive(clap::Args)]
pub struct Args {
    #[command(flatten)]
    config: ConfigArgs,
    /// Number of clients.
    #[arg(long, default_value_t = 3)]
    clients: usize,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let mut config = args.config.load()?;
    // One shard per simulated client.
    config.num_clients = args.clients;
    anyhow::ensure!(
        args.clients >= config.min_clients,
        "--clients {} is below min-clients {}: no round would start",
        args.clients,
        config.min_clients
    );
    let run_dir = RunDir::create(Path::new(&config.output_dir), &config)?;
    // Progress bars own the terminal: only warnings go to stderr, the full log to server.log.
    super::init_tracing(Some(run_dir.log_file()?), LevelFilter::WARN);
    println!("run directory: {}", run_dir.path().display());
    match config.workload {
        WorkloadKind::Linreg => simulate(&LinRegWorkload::from_config(&config), config, args.clients, run_dir),
        WorkloadKind::Smolvla => {
            let workload = SmolVlaWorkload::prepare(&config, &run_dir.path().join(super::SHARDS_DIR))?;
            simulate(&workload, config, args.clients, run_dir)
        }
    }
}

fn simulate<W: Workload>(workload: &W, config: RunConfig, clients: usize, run_dir: RunDir) -> anyhow::Result<()> {
    let trainers =
        (0..clients).map(|shard| workload.trainer(shard)).collect::<Result<Vec<_>, _>>().map_err(super::boxed)?;
    let metrics_path = run_dir.path().join(METRICS_FILE);
    let rounds = config.num_server_rounds;
    let parts = ServerParts::of(workload, config, run_dir).map_err(super::boxed)?;
    super::runtime()?.block_on(async move {
        let listener = TcpListener::bind("127.0.0.1:0").await.context("binding 127.0.0.1:0")?;
        let handle = server::start(parts, listener)?;
        let url = format!("ws://{}", handle.addr());
        let bars = MultiProgress::new();
        let round_bar = bars.add(ProgressBar::new(rounds));
        round_bar.set_style(ProgressStyle::with_template("{prefix:>10} [{bar:30}] {pos}/{len} rounds {msg}")?);
        round_bar.set_prefix("server");
        let mut status = handle.status();
        let watcher = tokio::spawn({
            let round_bar = round_bar.clone();
            async move {
                loop {
                    let s = status.borrow_and_update().clone();
                    round_bar.set_position(s.completed_rounds);
                    let refusals = s.rejections.values().sum::<u64>();
                    round_bar.set_message(format!("{} connected, {refusals} refusals", s.connected));
                    if s.finished || status.changed().await.is_err() {
                        break;
                    }
                }
            }
        });
        let style = ProgressStyle::with_template("{prefix:>10} [{bar:30}] {pos}/{len} {msg}")?;
        let tasks: Vec<_> = trainers
            .into_iter()
            .enumerate()
            .map(|(shard, trainer)| {
                let bar = bars.add(ProgressBar::new(rounds));
                bar.set_style(style.clone());
                bar.set_prefix(format!("client {shard}"));
                spawn_client(url.clone(), shard, trainer, bar)
            })
            .collect();
        // A simulated federation cannot finish without its clients: the first client to fail
        // stops the run instead of leaving the server waiting for it.
        let cancel = handle.cancel_token();
        let clients: Vec<_> = tasks
            .into_iter()
            .enumerate()
            .map(|(shard, done)| {
                let cancel = cancel.clone();
                tokio::spawn(async move {
                    let result = done.await.unwrap_or_else(|_| Err(anyhow::anyhow!("panicked")));
                    if result.is_err() {
                        cancel.cancel();
                    }
                    result.with_context(|| format!("client {shard}"))
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
        println!("{} rounds done; metrics in {}", status.completed_rounds, metrics_path.display());
        print_heldout_losses(&metrics_path)?;
        anyhow::Ok(())
    })
}

/// One client with its own progress bar, on its own thread: trainers' futures need not be `Send` (the
/// browser's are not), and CPU-bound trainers then train in parallel.
fn spawn_client<L: LocalTrainer + Send + 'static>(
    url: String,
    shard: usize,
    mut trainer: L,
    bar: ProgressBar,
) -> oneshot::Receiver<anyhow::Result<()>> {
    let (done_tx, done) = oneshot::channel();
    std::thread::spawn(move || {
        let client = async move {
            let mut transport = NativeTransport::connect(&url).await.map_err(super::boxed)?;
            let options =
                ClientOptions { name: format!("client-{shard}"), auth_token: None, shard: Some(shard as u32) };
            let summary = run_client(&mut transport, &mut trainer, &options, |event| match event {
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
            .await?;
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

/// Prints the global held-out loss of the first and the last evaluated round, the run's headline.
fn print_heldout_losses(metrics: &Path) -> anyhow::Result<()> {
    let text = std::fs::read_to_string(metrics).with_context(|| format!("reading {}", metrics.display()))?;
    let losses: Vec<(u64, f64)> = text
        .lines()
        .filter_map(|line| serde_json::from_str::<serde_json::Value>(line).ok())
        .filter_map(|m| Some((m["round"].as_u64()?, m["global"]["heldout_loss"].as_f64()?)))
        .collect();
    if let (Some((r0, first)), Some((rn, last))) = (losses.first(), losses.last()) {
        println!("global held-out loss: round {r0} {first:.4} -> round {rn} {last:.4}");
    }
    Ok(())
}
