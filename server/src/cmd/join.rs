//! `fedvla join URL`: a native client.

use fedvla_federation::{
    ClientError, ClientEvent, ClientOptions, ErrorCode, LocalTrainer, run_client,
};
use fedvla_server::config::WorkloadKind;
use fedvla_server::linreg::LinRegWorkload;
use fedvla_server::smolvla_workload::SmolVlaWorkload;
use fedvla_server::native_client::NativeTransport;
use fedvla_server::workload::Workload;
use tracing_subscriber::filter::LevelFilter;

use super::ConfigArgs;

#[derive(clap::Args)]
pub struct Args {
    /// Server address: ws://host:port or http://host:port.
    url: String,
    /// The run configuration's workload and partitioning pick what this client trains.
    #[command(flatten)]
    config: ConfigArgs,
    /// Name shown to the server (defaults to shard-<N>).
    #[arg(long)]
    name: Option<String>,
    /// Which shard of the dataset this client trains on.
    #[arg(long, default_value_t = 0)]
    shard: usize,
    /// Token required by a server started with auth-token set.
    #[arg(long)]
    auth_token: Option<String>,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    super::init_tracing(None, LevelFilter::INFO);
    let config = args.config.load()?;
    match config.workload {
        WorkloadKind::Linreg => join(LinRegWorkload::from_config(&config), args),
        WorkloadKind::Smolvla => {
            // The client cuts its shard from its own copy of the dataset, as the server partitions it.
            let shard_dir = std::env::temp_dir().join(format!("fedvla-join-{}", std::process::id()));
            let workload = SmolVlaWorkload::prepare(&config, &shard_dir)?;
            join(workload, args)
        }
    }
}

fn join<W: Workload>(workload: W, args: Args) -> anyhow::Result<()> {
    let mut trainer = workload.trainer(args.shard).map_err(super::boxed)?;
    let options = ClientOptions {
        name: args.name.unwrap_or_else(|| format!("shard-{}", args.shard)),
        auth_token: args.auth_token,
    };
    super::runtime()?.block_on(async move {
        let mut transport = NativeTransport::connect(&args.url)
            .await
            .map_err(super::boxed)?;
        train(&mut transport, &mut trainer, &options).await
    })
}

async fn train<L: LocalTrainer>(
    transport: &mut NativeTransport,
    trainer: &mut L,
    options: &ClientOptions,
) -> anyhow::Result<()> {
    let result = run_client(transport, trainer, options, |event| match event {
        ClientEvent::Trained {
            round,
            examples,
            train_loss,
        } => {
            tracing::info!(round, examples, train_loss, "trained");
        }
        ClientEvent::Refused { code, message } => {
            tracing::warn!(code = code.as_str(), %message, "refused");
        }
        other => tracing::info!(?other),
    })
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
}
