//! `fedvla join URL`: a native client.

use fedvla_federation::{ClientError, ClientEvent, ClientOptions, ErrorCode, run_client};
use fedvla_server::config::Partitioning;
use fedvla_server::linreg::LinRegTrainer;
use fedvla_server::native_client::NativeTransport;
use tracing_subscriber::filter::LevelFilter;

#[derive(clap::Args)]
pub struct Args {
    /// Server address: ws://host:port or http://host:port.
    url: String,
    /// Name shown to the server (defaults to shard-<N>).
    #[arg(long)]
    name: Option<String>,
    /// Which shard of the synthetic dataset this client trains on.
    #[arg(long, default_value_t = 0)]
    shard: usize,
    #[arg(long, value_enum, default_value_t = Partitioning::Iid)]
    partitioning: Partitioning,
    /// Token required by a server started with auth-token set.
    #[arg(long)]
    auth_token: Option<String>,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    super::init_tracing(None, LevelFilter::INFO);
    let options = ClientOptions {
        name: args.name.unwrap_or_else(|| format!("shard-{}", args.shard)),
        auth_token: args.auth_token,
    };
    let mut trainer = LinRegTrainer::new(args.shard, args.partitioning);
    super::runtime()?.block_on(async move {
        let mut transport = NativeTransport::connect(&args.url)
            .await
            .map_err(|e| anyhow::anyhow!(e))?;
        let result = run_client(
            &mut transport,
            &mut trainer,
            &options,
            |event| match event {
                ClientEvent::Trained {
                    round,
                    examples,
                    train_loss,
                } => {
                    tracing::info!(round, examples, train_loss, "trained");
                }
                ClientEvent::Refused { code, message } => {
                    tracing::warn!(code = code.as_str(), %message, "refused")
                }
                other => tracing::info!(?other),
            },
        )
        .await;
        let summary = match result {
            Err(ClientError::Refused {
                code: ErrorCode::ShuttingDown,
                ..
            }) => {
                tracing::info!("the server shut down before the run finished");
                return Ok(());
            }
            other => other?,
        };
        tracing::info!(
            rounds = summary.rounds_trained,
            bytes_up = summary.bytes_up,
            bytes_down = summary.bytes_down,
            "run finished"
        );
        Ok(())
    })
}
