//! `fedvla simulate`: a server and N native clients in one process, over real loopback WebSockets.

use std::path::Path;
use std::time::Duration;

use anyhow::Context;
use fedvla_federation::{ClientEvent, ClientOptions, run_client};
use fedvla_server::linreg::LinRegTrainer;
use fedvla_server::native_client::NativeTransport;
use fedvla_server::run_dir::{METRICS_FILE, RunDir};
use fedvla_server::server;
use indicatif::{MultiProgress, ProgressBar, ProgressStyle};
use tokio::net::TcpListener;
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
    let config = args.config.load()?;
    anyhow::ensure!(
        args.clients >= config.min_clients,
        "--clients {} is below min-clients {}: no round would start",
        args.clients,
        config.min_clients
    );
    let run_dir = RunDir::create(Path::new(&config.output_dir), &config)?;
    // Progress bars own the terminal: only warnings go to stderr, the full log to server.log.
    super::init_tracing(Some(run_dir.log_file()?), LevelFilter::WARN);
    let dir = run_dir.path().to_owned();
    let rounds = config.num_server_rounds;
    let partitioning = config.partitioning;
    super::runtime()?.block_on(async move {
        let listener = TcpListener::bind("127.0.0.1:0")
            .await
            .context("binding 127.0.0.1:0")?;
        let handle = server::start(super::server_parts(config, run_dir), listener)?;
        let url = format!("ws://{}", handle.addr());
        let bars = MultiProgress::new();
        let round_bar = bars.add(ProgressBar::new(rounds));
        round_bar.set_style(ProgressStyle::with_template(
            "{prefix:>10} [{bar:30}] {pos}/{len} rounds {msg}",
        )?);
        round_bar.set_prefix("server");
        let mut status = handle.status();
        let watcher = tokio::spawn({
            let round_bar = round_bar.clone();
            async move {
                loop {
                    let s = status.borrow_and_update().clone();
                    round_bar.set_position(s.completed_rounds);
                    round_bar.set_message(format!(
                        "{} connected, {} refusals",
                        s.connected,
                        s.rejections.values().sum::<u64>()
                    ));
                    if s.finished || status.changed().await.is_err() {
                        break;
                    }
                }
            }
        });
        let style = ProgressStyle::with_template("{prefix:>10} [{bar:30}] {pos}/{len} {msg}")?;
        let mut clients = Vec::new();
        for shard in 0..args.clients {
            let bar = bars.add(ProgressBar::new(rounds));
            bar.set_style(style.clone());
            bar.set_prefix(format!("client {shard}"));
            let url = url.clone();
            clients.push(tokio::spawn(async move {
                let mut transport = NativeTransport::connect(&url)
                    .await
                    .map_err(|e| anyhow::anyhow!(e))?;
                let mut trainer = LinRegTrainer::new(shard, partitioning);
                let options = ClientOptions {
                    name: format!("client-{shard}"),
                    auth_token: None,
                };
                let summary = run_client(
                    &mut transport,
                    &mut trainer,
                    &options,
                    |event| match event {
                        ClientEvent::Joined { client_id } => {
                            bar.set_message(format!("joined as {client_id}"))
                        }
                        ClientEvent::Task { round, local_steps } => {
                            bar.set_message(format!("round {round}: training {local_steps} steps"));
                        }
                        ClientEvent::Trained {
                            round, train_loss, ..
                        } => {
                            bar.set_message(format!(
                                "round {round}: loss {train_loss:.4}, uploading"
                            ));
                        }
                        ClientEvent::Uploaded { round, bytes } => {
                            bar.set_message(format!("round {round}: sent {bytes} B"))
                        }
                        ClientEvent::RoundClosed { round, accepted } => {
                            if accepted {
                                bar.set_position(round);
                            }
                        }
                        ClientEvent::Refused { code, .. } => {
                            bar.set_message(format!("refused: {}", code.as_str()))
                        }
                    },
                )
                .await?;
                bar.finish_with_message(format!(
                    "{} rounds, {} B up, {} B down",
                    summary.rounds_trained, summary.bytes_up, summary.bytes_down
                ));
                anyhow::Ok(())
            }));
        }
        let status = handle.finish().await?;
        watcher.await.ok();
        round_bar.finish();
        for (shard, client) in clients.into_iter().enumerate() {
            match tokio::time::timeout(Duration::from_secs(5), client).await {
                Ok(Ok(Ok(()))) => {}
                Ok(Ok(Err(e))) => eprintln!("client {shard}: {e:#}"),
                Ok(Err(e)) => eprintln!("client {shard} panicked: {e}"),
                Err(_) => eprintln!("client {shard} did not finish"),
            }
        }
        println!(
            "{} rounds done; metrics in {}",
            status.completed_rounds,
            dir.join(METRICS_FILE).display()
        );
        anyhow::Ok(())
    })
}
