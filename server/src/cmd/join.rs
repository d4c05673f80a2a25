//! `fedvla join URL`: a native volunteer. It downloads what the server offers (`GET /api/volunteer`: its shard,
//! the policy configuration and the frozen weights), then runs the shared round loop.

use fedvla_federation::{ClientError, ClientEvent, ClientOptions, ErrorCode, LocalTrainer, run_client};
use fedvla_server::config::Partitioning;
use fedvla_server::linreg::LinRegTrainer;
use fedvla_server::native_client::{NativeTransport, smolvla_volunteer};
use tracing_subscriber::filter::LevelFilter;

#[derive(clap::Args)]
pub struct Args {
    /// Server address: ws://host:port or http://host:port.
    url: String,
    /// Name shown to the server; the same name gets the same shard back after a restart (defaults to a random
    /// native-XXXXXX).
    #[arg(long)]
    name: Option<String>,
    /// Train on this shard instead of the one the server assigns.
    #[arg(long)]
    shard: Option<u32>,
    /// Token required by a server started with auth-token set.
    #[arg(long)]
    auth_token: Option<String>,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    super::init_tracing(None, LevelFilter::INFO);
    super::runtime()?.block_on(async move {
        let mut transport = NativeTransport::connect(&args.url).await.map_err(super::boxed)?;
        let name = args.name.unwrap_or_else(|| format!("native-{}", &fedvla_server::console::random_token()[..6]));
        let setup = transport.fetch_setup(&name, args.shard).await.map_err(super::boxed)?;
        let options = ClientOptions { name, auth_token: args.auth_token, shard: Some(setup.shard_index) };
        tracing::info!(workload = %setup.workload, shard = setup.shard_index, of = setup.shard_count, "volunteer setup");
        match setup.workload.as_str() {
            // The linreg shard is generated from its index (the partitioning only changes the data skew).
            "linreg" => {
                let mut trainer = LinRegTrainer::new(setup.shard_index as usize, Partitioning::ByEpisode);
                train(&mut transport, &mut trainer, &options).await
            }
            "smolvla" => {
                let mut trainer = smolvla_volunteer(&transport, &setup, &options.name).await.map_err(super::boxed)?;
                train(&mut transport, &mut trainer, &options).await
            }
            other => anyhow::bail!("the server runs workload {other:?}, which this client does not know"),
        }
    })
}

async fn train<L: LocalTrainer>(
    transport: &mut NativeTransport,
    trainer: &mut L,
    options: &ClientOptions,
) -> anyhow::Result<()> {
    let result = run_client(transport, trainer, options, |event| match event {
        ClientEvent::Trained { round, examples, train_loss } => {
            tracing::info!(round, examples, train_loss, "trained");
        }
        ClientEvent::Refused { code, message } => {
            tracing::warn!(code = code.as_str(), %message, "refused");
        }
        other => tracing::info!(?other),
    })
    .await;
    let summary = match result {
        Err(ClientError::Refused { code: ErrorCode::ShuttingDown, .. }) => {
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
